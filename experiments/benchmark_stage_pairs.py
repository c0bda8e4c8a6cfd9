r"""Benchmark the re-making of stage-k pairs in memory (what a stage-k > 1 chunk of
``experiments.paper_schedule`` does before it trains): ms per pair with 1 and 2 threads, the
model replaced by an oracle that looks each pair's answer up.

  python -m experiments.benchmark_stage_pairs                   # bundled photographs
  python -m experiments.benchmark_stage_pairs --images=../shared/data/coco_mini/train \
      --samples_per_image=40

Prints one JSON object (machine, seed, command, results).
"""

from __future__ import annotations

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.data import sources
from stnh_tf.evaluation import data_benchmark as benchmark
from stnh_tf.paths import check_apart

flags.DEFINE_string("images", "bundled", "Photographs: 'bundled' or folders (comma-separated).")
flags_common.define_max_images()
flags.DEFINE_integer("samples_per_image", 40, "Pairs made from each photograph.")
flags.DEFINE_list("threads", ["1", "2"], "Thread counts to time.")
flags.DEFINE_integer("repeats", 2, "Timings per thread count.")
flags.DEFINE_float("error_px", 8.0, "Oracle error: each corner moved by up to this (pixels).")
flags_common.define_seed("Pair and oracle seed.")
flags_common.define_json_out()
FLAGS = flags.FLAGS
flags.adopt_module_key_flags(flags_common)  # --help lists them


def main(argv):
    del argv
    with common.user_errors("benchmark_stage_pairs"):
        folders = [] if FLAGS.images == "bundled" else sources.split_folders(FLAGS.images)
        check_apart({"--json_out": FLAGS.json_out}, {"--images": folders})
        result = benchmark.stage_pairs_benchmark(FLAGS.images, FLAGS.samples_per_image,
                                                 FLAGS.threads, FLAGS.repeats, FLAGS.error_px,
                                                 FLAGS.seed, FLAGS.max_images)
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
