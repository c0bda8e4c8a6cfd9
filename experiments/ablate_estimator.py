r"""The ablation table of ``estimate_images``' default (issue 79, item 5): each rule of
``EstimateOptions.photographs()`` switched off in turn (``stnh_tf.evaluation.ablation.ABLATIONS``)
on every group of the camera-pair sets given (folders written by
``experiments.make_camera_pairs``), scored as ``experiments.benchmark_camera_pairs`` scores the
estimator: successes (< 3 px), mean error, good estimates flagged, silent failures (> 5 px,
unflagged; and 10 px or more), ms per pair (docs/estimate.md, "Ablation").

  python -m experiments.ablate_estimator --pairs_dirs=D1,D2,D3 --json_out=ablation.json
  python -m experiments.ablate_estimator --pairs_dirs=D --ablations=search,verify \
      --max_pairs_per_group=20 --json_out=ablation.json

The default row (``photographs()`` as it is) always runs first; every ablation runs on a pair
before the next pair. Prints a markdown table (rows the ablations, columns the groups) and each
ablation's differences from the default; --json_out=FILE writes the full JSON (with the commit
and the machine), --json_out=- prints it instead. An unknown ablation name, or a --json_out that
cannot be written, ends it in one line before any work.
"""

from __future__ import annotations

from absl import app, flags

from experiments import common
from stnh_tf.evaluation import ablation, summaries

flags.DEFINE_list("pairs_dirs", None, "Folders of pairs (make_camera_pairs), comma-separated; a "
                  "group found in several is scored over all of them.", required=True)
flags.DEFINE_list("ablations", ["all"], "'all', or ablation names among "
                  f"{','.join(ablation.ABLATIONS)} (the default row always runs).")
flags.DEFINE_integer("max_pairs_per_group", 0, "Only the first this many pairs of each group, "
                     "over the folders in order (0: all).", lower_bound=0)
flags.DEFINE_string("model", None, "Model or hierarchy (default: the shipped weights).")
flags.DEFINE_string("json_out", None, summaries.JSON_OUT_HELP, required=True)
FLAGS = flags.FLAGS


def main(argv):
    del argv
    with common.user_errors("ablate_estimator"):
        names = ablation.resolve(FLAGS.ablations)
        common.check_flags_apart(("json_out",), ("pairs_dirs",), models=("model",))
        summaries.check_json_out(FLAGS.json_out)
        result = ablation.run_folders(FLAGS.pairs_dirs, names, FLAGS.model,
                                      FLAGS.max_pairs_per_group)
    summaries.emit(result, ablation.table(result), FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
