r"""The paper's Fig. 1: value histograms of the eight regressed entries of H_bar.

  python -m experiments.plot_hbar_histogram --data_dir=data/coco_mini --output=hbar_hist.png

Reads only the ``h_bar`` feature of a split (all samples, or ``--max_samples``), draws one
histogram per entry ``h11 .. h32`` (2 x 4 panels, mean and standard deviation in each title) with
matplotlib's Agg backend, and writes the summary statistics beside the figure as JSON.
"""

from __future__ import annotations

import json
import os

from absl import app, flags

flags.DEFINE_string("data_dir", None, "Dataset directory (metadata.json + shards).")
flags.DEFINE_string("split", "train", "Split to histogram.")
flags.DEFINE_string("output", None, "Output PNG path (ending in .png; the statistics go beside "
                    "it, ending in .json).")
flags.DEFINE_integer("bins", 100, "Histogram bins per entry.", lower_bound=1)
flags.DEFINE_integer("max_samples", 0, "Use only the first N samples (0 = all).", lower_bound=0)
FLAGS = flags.FLAGS

# The library pieces (the reproduce driver draws the same figure).
from experiments import common  # noqa: E402
from stnh_tf.evaluation import summaries  # noqa: E402
from stnh_tf.paths import check_apart, check_output_file  # noqa: E402
from stnh_tf.paper.figures import ENTRY_NAMES, read_h_bar  # noqa: E402,F401
from stnh_tf.paper.figures import hbar_histogram as plot_histogram  # noqa: E402


def main(argv):
    del argv
    if not FLAGS.data_dir or not FLAGS.output:
        raise app.UsageError("--data_dir and --output are required.")
    stats_json = os.path.splitext(FLAGS.output)[0] + ".json"
    with common.user_errors("plot_hbar_histogram"):
        if not FLAGS.output.lower().endswith(".png"):
            raise ValueError(f"--output is the figure's PNG path, ending in .png; received "
                             f"{FLAGS.output!r}.")
        check_apart({"--output": [FLAGS.output, stats_json]}, {"--data_dir": FLAGS.data_dir})
        check_output_file(FLAGS.output)
        summaries.check_json_out(stats_json)  # only an earlier histogram's statistics
        h_bar = read_h_bar(FLAGS.data_dir, FLAGS.split, FLAGS.max_samples)
        stats = plot_histogram(h_bar, FLAGS.output, FLAGS.bins,
                               f"Value histogram of H_bar, {FLAGS.split} split of "
                               f"{FLAGS.data_dir} ({len(h_bar)} samples)")
        stats.update(data_dir=os.path.abspath(FLAGS.data_dir), split=FLAGS.split)
        summaries.write_json_out(stats, stats_json, sort_keys=False)
    print(json.dumps(stats["entries"], indent=1))


if __name__ == "__main__":
    app.run(main)
