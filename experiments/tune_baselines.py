r"""Justify the settings of the classical baselines (ORB/SIFT + RANSAC) on paper-protocol pairs.

Generates ``--num_pairs`` synthetic pairs (DeTone et al. protocol, as in
``docs/conventions.md``) from the photographs in ``--image_dir`` (or, without it, from
scikit-image's bundled photographs), evaluates identity, the registered baselines and a small grid
of ORB and SIFT settings around them, and prints a short table (MACE, median, pairs worse than
the identity: :func:`stnh_tf.evaluation.summaries.tuning_table`); --json_out=FILE writes the full
JSON (also p90, p99, failure rate, ms per pair for each), --json_out=- prints it instead.

  python -m experiments.tune_baselines --image_dir=../shared/data/coco_mini/train \
      --num_pairs=300 --seed=0 --json_out=/tmp/tune_baselines.json

(``../shared/data/coco_mini/train``: this project's own training photographs, what BENCHMARKS.md
measured; give your folder, and ``--max_images=N`` for its first N photographs.)

Pairs come from the data generator's own protocol (:mod:`stnh_tf.data.sources` decoding and
resizing, :mod:`stnh_tf.data.pairs`), drawn in memory with one seeded generator.
"""

from __future__ import annotations

import sys

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.data.folder_counts import FolderCounts
from stnh_tf.data.sources import SourceError
from stnh_tf.evaluation import baseline_tuning, summaries

flags.DEFINE_string("image_dir", None, "Folder of photographs (jpg/png). Default: scikit-image's.")
flags_common.define_max_images()
flags.DEFINE_integer("num_pairs", 300, "Number of synthetic pairs.", lower_bound=1)
flags_common.define_seed("Seed of the pair generator.")
flags.DEFINE_enum("grid", "small", ["none", "small"],
                  "Settings grid: none (registered baselines only) or small.")
flags.DEFINE_string("json_out", None, summaries.JSON_OUT_HELP)

FLAGS = flags.FLAGS


def main(argv):
    del argv
    with common.user_errors("tune_baselines"):
        common.check_flags_apart(("json_out",), ("image_dir",))
        summaries.check_json_out(FLAGS.json_out)
    with common.user_errors("tune_baselines", (SourceError,)):  # (no photograph there)
        result = baseline_tuning.run_tuning(FLAGS.image_dir, FLAGS.num_pairs, FLAGS.seed,
                                            FLAGS.grid, FLAGS.max_images)
    if result["photographs"]:
        print(FolderCounts(**result["photographs"]).line(), file=sys.stderr)
    summaries.emit(result, summaries.tuning_table(result), FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
