r"""Realistic camera pairs from photographs (issue 46): camera rotation with zoom, viewpoint change
of a plane, in-plane rotation; blur, exposure change, sensor noise and JPEG on image_b; the true
``h_ba`` of each pair and its group by motion size (:mod:`stnh_tf.data.camera_motions`).

  python -m experiments.make_camera_pairs --output_dir=/tmp/camera_pairs
  python -m experiments.make_camera_pairs --output_dir=D --image_dir=F --pairs_per_image=3 --seed=0

Writes ``D/{k:05d}_a.png``, ``D/{k:05d}_b.png`` and ``D/pairs.json`` (every parameter, per pair
``h_ba``, group, kind, motion and degradation); prints the manifest without its pairs as JSON.
"""

from __future__ import annotations

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.data import camera_pair_files

flags.DEFINE_string("output_dir", None, "Folder of the pairs (created).", required=True)
flags.DEFINE_string("image_dir", "../shared/data/coco_mini/test",
                    "Photographs (every image file below it, sorted).")
flags.DEFINE_integer("pairs_per_image", 3, "Pairs per photograph (groups cycle over the pairs).")
flags.DEFINE_integer("seed", 0, "Seed: photograph i draws from default_rng([seed, i]).")
flags.DEFINE_bool("overwrite", False, "Replace a set already in --output_dir.")
flags_common.define_json_out()
FLAGS = flags.FLAGS


def main(argv):
    del argv
    with common.user_errors("make_camera_pairs"):
        result = camera_pair_files.write_pairs(FLAGS.image_dir, FLAGS.output_dir,
                                            FLAGS.pairs_per_image, FLAGS.seed,
                                            overwrite=FLAGS.overwrite)
    common.emit_json({"output_dir": FLAGS.output_dir, **result}, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
