r"""`make demo`, the main job: the shipped models against the classical baselines, offline.

  python -m experiments.demo [--output_dir=demo_output] [--seed=0]

1. checks the geometry conventions against OpenCV (:func:`stnh_tf.paper.demo.self_check`);
2. generates a seeded test set from the photographs bundled with scikit-image and matplotlib
   (the paper's protocol; no download);
3. evaluates identity, ORB + RANSAC, SIFT + RANSAC and the shipped models (``stnh_tf/weights``:
   one stage, and the hierarchy when shipped) on the same pairs, and prints a table of MACE and
   time per pair;
4. writes ``results.json`` and a Fig. 5-style PNG (true quadrilateral green, predicted red) to
   ``--output_dir``.
"""

from __future__ import annotations

import sys

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.paper import demo

flags.DEFINE_string("output_dir", "demo_output", "Where the test set, results.json and the PNG go.")
flags_common.define_seed("Seed of the test pairs.")
flags.DEFINE_integer("samples_per_image", 3, "Pairs per bundled photograph.", lower_bound=1)
flags.DEFINE_integer("examples", 4, "Pairs drawn in the figure.", lower_bound=0)
FLAGS = flags.FLAGS


def main(argv):
    del argv
    with common.user_errors("demo"):
        common.check_not_a_run(FLAGS.output_dir)
        result = demo.run_demo(FLAGS.output_dir, FLAGS.seed, FLAGS.samples_per_image,
                               FLAGS.examples)
    if not result["conventions"]["ok"]:
        sys.exit("demo: a convention check failed (see results.json).")


if __name__ == "__main__":
    app.run(main)
