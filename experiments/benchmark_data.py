r"""Benchmark data generation (samples/s with 1 and 2 workers) and tf.data reading (batch 64).

  python -m experiments.benchmark_data                       # bundled photographs, repeated
  python -m experiments.benchmark_data --source=folder --image_dir=../shared/data/coco_mini/train

Generation writes to a temporary directory (removed afterwards) with the real writer
(``stnh_tf.data.writer.write_sharded`` + the stage-1 worker); the timing includes starting the
worker processes. Reading times ``stnh_tf.data.tfrecords.load_split`` (interleave, shuffle, batch,
parse, prefetch) after a short warm-up. ``--resume_skip_batches=N`` also times how long a resumed
training stream takes to deliver its first batch after skipping N batches, with the skip before
parsing (``load_split(skip_batches=N)``, what training uses) and after it (``.skip(N)`` on the
parsed stream). Prints one JSON object (machine, seed, command, results).
Goals on the 2-core development machine: generation >= 1,000 samples/s, reading >= 5,000.
"""

from __future__ import annotations

from absl import app, flags

from stnh_tf.evaluation import data_benchmark as benchmark
from experiments import common, flags_common

flags.DEFINE_enum("source", "bundled", ["bundled", "folder"], "Image source.")
flags.DEFINE_string("image_dir", None, "Folder for --source=folder.")
flags_common.define_max_images()
flags.DEFINE_integer("repeat", 0, "Use the image list this many times as distinct items "
                     "(0 = enough for about 1,500 samples), so the timing is not all start-up.")
flags.DEFINE_list("workers", ["1", "2"], "Worker counts to time.")
flags.DEFINE_integer("num_shards", 8, "Shards written.", lower_bound=1)
flags.DEFINE_integer("batch_size", 64, "Read batch size.", lower_bound=1)
flags.DEFINE_integer("read_batches", 200, "Batches timed when reading (after 10 warm-up).",
                     lower_bound=1)
flags.DEFINE_integer("resume_skip_batches", 0, "Also time resuming the stream at this batch "
                     "(0: not timed).")
flags_common.define_seed("Generation seed.")
flags_common.define_json_out()
FLAGS = flags.FLAGS
flags.adopt_module_key_flags(flags_common)  # --help lists them


def main(argv):
    del argv
    with common.user_errors("benchmark_data"):
        common.check_flags_apart(("json_out",), ("image_dir",))
        if FLAGS.source == "folder" and not FLAGS.image_dir:
            raise ValueError("--source=folder reads --image_dir: give one.")
        result = benchmark.data_benchmark(  # (an empty folder, every file unusable: one line)
            FLAGS.source, FLAGS.image_dir, FLAGS.max_images, FLAGS.repeat, FLAGS.workers,
            FLAGS.num_shards, FLAGS.batch_size, FLAGS.read_batches, FLAGS.resume_skip_batches,
            FLAGS.seed)
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
