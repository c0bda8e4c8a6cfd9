r"""A learning-curve figure of one run from its console logs (one file per chunk).

  python -m experiments.plot_learning_curves \
      --logs='paper_schedule/logs/stage3_*_cpu.log' --output=docs/figures/stage3_curve.png

Reads every progress and validation line of the logs (:mod:`stnh_tf.paper.learning_curves`;
a step logged twice keeps the later file's value), draws ``--metric`` (training, as logged) and
its validation against the step with the learning rate, and prints ``{"output", "points",
"last"}``; ``--json_out`` also writes the curve's points.
"""

from __future__ import annotations

import glob
import json

from absl import app, flags

from experiments import common

flags.DEFINE_list("logs", None, "Log files or glob patterns (quoted), in the run's order.",
                  required=True)
flags.DEFINE_string("output", None, "PNG to write.", required=True)
flags.DEFINE_string("metric", "h_bar_mace", "The logged metric to draw (and val_<metric>).")
flags.DEFINE_string("title", "", "The figure's title.")
flags.DEFINE_string("json_out", None, "Also write {'curve': {step: {metric: value}}} here (an "
                    "existing file must be an earlier one of this binary).")
FLAGS = flags.FLAGS


def main(argv):
    del argv
    from stnh_tf.paper import learning_curves
    from stnh_tf.evaluation import summaries
    from stnh_tf.paths import check_apart

    with common.user_errors("plot_learning_curves"):
        logs = [f for p in FLAGS.logs for f in (glob.glob(p) if glob.has_magic(p) else [p])]
        check_apart({"--output": FLAGS.output, "--json_out": FLAGS.json_out},
                    {"--logs": logs})  # (a log written over by a typo)
        summaries.check_json_out(FLAGS.json_out)  # (a document or another tool's result)
        curve = learning_curves.read_logs(FLAGS.logs)
        drawn = learning_curves.plot(curve, FLAGS.output, FLAGS.metric, FLAGS.title)
        if FLAGS.json_out:
            summaries.write_json_out({"curve": {str(k): v for k, v in curve.items()}},
                                     FLAGS.json_out, sort_keys=False)
    print(json.dumps({"output": FLAGS.output, **drawn}))


if __name__ == "__main__":
    app.run(main)
