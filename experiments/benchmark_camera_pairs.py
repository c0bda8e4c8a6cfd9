r"""The estimator, SIFT + RANSAC, ORB + RANSAC and the identity on realistic camera pairs (a folder
written by ``experiments.make_camera_pairs``), per group of motion size: MACE at the image's
corners in the pairs' own frame (320 x 240, or 640 x 480 for a set made with ``--scale=2``; and
of the central patch of the 320 x 240 frame), median, success rate (< 3 px), time per pair, and the
estimator's implausibility flag as a detector of estimates more than 5 px off
(:mod:`stnh_tf.evaluation.camera_pairs`).

  python -m experiments.benchmark_camera_pairs --pairs_dir=/tmp/camera_pairs
  python -m experiments.benchmark_camera_pairs --pairs_dir=D --methods=sift_ransac,identity
  python -m experiments.benchmark_camera_pairs --pairs_dir=D --features=none --coarse=none \
      --refine=none --verify=none                            # EstimateOptions()
  python -m experiments.benchmark_camera_pairs --pairs_dir=D --features=none --coarse=none \
      --refine=none --verify=none --search=none              # the network alone
  python -m experiments.benchmark_camera_pairs --pairs_dir=D \
      --methods=estimator,sift_ransac,sift_wide,orb_ransac,identity   # SIFT for wide baselines too
  python -m experiments.benchmark_camera_pairs --pairs_dir=D --thresholds=resolution_sigma=0

The estimator runs with ``estimate_images``' default options (``EstimateOptions.photographs()``)
unless the flags say otherwise.

Prints a short table per group and over all pairs (:func:`stnh_tf.evaluation.summaries.
camera_pairs_table`: MACE, median, pairs worse than the identity, "worse than the identity" where a
mean is above the identity's); --json_out=FILE writes the full JSON, --json_out=- prints it
instead.
"""

from __future__ import annotations

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.evaluation import camera_pairs, summaries
from stnh_tf.inference.options import EstimateOptions

flags.DEFINE_string("pairs_dir", None, "Folder of pairs (make_camera_pairs).", required=True)
flags.DEFINE_string("model", None, "Model or hierarchy (default: the shipped weights).")
flags.DEFINE_list("methods", list(camera_pairs.DEFAULT_METHODS),
                  f"Methods, among {','.join(camera_pairs.METHODS)}.")
flags.DEFINE_integer("max_pairs", 0, "Only the first this many pairs (0: all).")
flags.DEFINE_bool("per_pair", False, "Also print each pair's errors and flag.")
# estimate_images' default options
flags_common.define_estimate_flags(("search", "refine", "tta", "retry_tta", "verify", "coarse",
                                    "features"),
                                   EstimateOptions.photographs(), thresholds=True)
flags.DEFINE_string("json_out", None, summaries.JSON_OUT_HELP)
FLAGS = flags.FLAGS
flags.adopt_module_key_flags(flags_common)  # --help lists them


def main(argv):
    del argv
    with common.user_errors("benchmark_camera_pairs"):
        common.check_flags_apart(("json_out",), ("pairs_dir",), models=("model",))
        summaries.check_json_out(FLAGS.json_out)
        result = camera_pairs.benchmark_folder(
            FLAGS.pairs_dir, tuple(FLAGS.methods), FLAGS.model, flags_common.options_from_flags(),
            FLAGS.max_pairs, FLAGS.per_pair)
    summaries.emit(result, summaries.camera_pairs_table(result), FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
