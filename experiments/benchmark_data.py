r"""Benchmark data generation (samples/s with 1 and 2 workers) and tf.data reading (batch 64).

  python -m experiments.benchmark_data                       # bundled photographs, repeated
  python -m experiments.benchmark_data --source=folder --image_dir=../shared/data/coco_mini/train

Generation writes to a temporary directory (removed afterwards) with the real writer
(``data_prep.writer.write_sharded`` + the stage-1 worker); the timing includes starting the
worker processes. Reading times ``stnh_tf.data.load_split`` (interleave, shuffle, batch, parse,
prefetch) after a short warm-up. ``--resume_skip_batches=N`` also times how long a resumed
training stream takes to deliver its first batch after skipping N batches, with the skip before
parsing (``load_split(skip_batches=N)``, what training uses) and after it (``.skip(N)`` on the
parsed stream). Prints one JSON object (machine, seed, command, results).
Goals on the 2-core development machine: generation >= 1,000 samples/s, reading >= 5,000.
"""

from __future__ import annotations

import functools
import hashlib
import os
import shlex
import shutil
import sys
import tempfile
import time

from absl import app, flags

from experiments import common

flags.DEFINE_enum("source", "bundled", ["bundled", "folder"], "Image source.")
flags.DEFINE_string("image_dir", None, "Folder for --source=folder.")
flags.DEFINE_integer("max_images", 0, "First N images only (0 = all).")
flags.DEFINE_integer("repeat", 0, "Use the image list this many times as distinct items "
                     "(0 = enough for about 1,500 samples), so the timing is not all start-up.")
flags.DEFINE_list("workers", ["1", "2"], "Worker counts to time.")
flags.DEFINE_integer("num_shards", 8, "Shards written.")
flags.DEFINE_integer("batch_size", 64, "Read batch size.")
flags.DEFINE_integer("read_batches", 200, "Batches timed when reading (after 10 warm-up).")
flags.DEFINE_integer("resume_skip_batches", 0, "Also time resuming the stream at this batch "
                     "(0: not timed).")
flags.DEFINE_integer("seed", 0, "Generation seed.")
flags.DEFINE_string("json_out", None, "Also write the JSON here.")
FLAGS = flags.FLAGS


def _items(source, image_dir, max_images, repeat, samples_per_image=3):
    from data_prep import stage1, writer

    if source == "folder":
        base, _, _ = stage1.folder_items(image_dir, max_images)
    else:
        base, _, _ = stage1.bundled_items(max_images)
    if repeat <= 0:
        repeat = max(1, -(-1500 // (len(base) * samples_per_image)))
    items = [writer.WorkItem(r * len(base) + it.index, f"{it.item_id}#{r}", it.payload)
             for r in range(repeat) for it in base]
    return items, repeat


def main(argv):
    del argv
    from data_prep import writer
    from stnh_tf import pairs, sources

    sources.quiet_opencv()
    items, repeat = _items(FLAGS.source, FLAGS.image_dir, FLAGS.max_images, FLAGS.repeat)
    worker_fn = functools.partial(pairs.generate_item_samples, seed=FLAGS.seed,
                                  protocol=pairs.Protocol())
    result = {
        "benchmark": "data generation and tf.data reading",
        "command": " ".join(shlex.quote(a) for a in getattr(sys, "orig_argv", sys.argv)),
        "machine": common.machine_info(), "seed": FLAGS.seed, "source": FLAGS.source,
        "image_dir": FLAGS.image_dir, "num_images": len(items) // repeat, "repeat": repeat,
        "num_items": len(items), "generation": [],
    }
    import tensorflow as tf  # imported up front so its start-up is not in the timings

    result["machine"]["tensorflow"] = tf.__version__
    root = tempfile.mkdtemp(prefix="stnh-bench-")
    digests = {}
    try:
        for w in [int(x) for x in FLAGS.workers]:
            out = os.path.join(root, f"w{w}")
            t0 = time.perf_counter()
            sec = writer.write_sharded(out, "train", items, worker_fn, num_shards=FLAGS.num_shards,
                                       num_workers=w, top_metadata={"stage": 1},
                                       log=lambda m: None)
            wall = time.perf_counter() - t0
            h = hashlib.sha256()
            for s in sec["shards"]:
                with open(os.path.join(out, s["file"]), "rb") as f:
                    h.update(f.read())
            digests[w] = h.hexdigest()
            result["generation"].append({
                "num_workers": w, "num_samples": sec["num_samples"],
                "samples_per_s": round(sec["num_samples"] / wall, 1), "wall_s": round(wall, 3),
                "bytes_per_sample": sec["bytes_per_sample"]})
        result["shards_identical_across_worker_counts"] = len(set(digests.values())) == 1

        from stnh_tf import data

        read_dir = os.path.join(root, f"w{int(FLAGS.workers[0])}")
        ds = data.load_split(read_dir, "train", FLAGS.batch_size, shuffle=True, seed=0)
        it = iter(ds)
        for _ in range(10):
            next(it)
        t0 = time.perf_counter()
        for _ in range(FLAGS.read_batches):
            x, y, w = next(it)
        float(x["patch_a"][0, 0, 0, 0])  # make sure the last batch is materialized
        dt = time.perf_counter() - t0
        result["reading"] = {"batch_size": FLAGS.batch_size, "batches": FLAGS.read_batches,
                             "samples_per_s": round(FLAGS.read_batches * FLAGS.batch_size / dt, 1),
                             "wall_s": round(dt, 3),
                             "pipeline": "load_split(shuffle=True, repeat=True), 8 shards"}
        n = FLAGS.resume_skip_batches
        if n > 0:
            first = {}
            for where in ("skip_before_parse", "skip_after_parse"):
                t0 = time.perf_counter()
                if where == "skip_before_parse":
                    ds = data.load_split(read_dir, "train", FLAGS.batch_size, seed=0, skip_batches=n)
                else:
                    ds = data.load_split(read_dir, "train", FLAGS.batch_size, seed=0).skip(n)
                x, _, _ = next(iter(ds))
                float(x["patch_a"][0, 0, 0, 0])
                first[where] = round(time.perf_counter() - t0, 3)
            result["resume_skip"] = {"skip_batches": n, "batch_size": FLAGS.batch_size,
                                     "seconds_to_first_batch": first}
    finally:
        shutil.rmtree(root, ignore_errors=True)
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
