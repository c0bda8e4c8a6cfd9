"""Data generation and reading throughput, library core of ``experiments.benchmark_data`` (its
docstring says what is timed and how to run it): the stage-1 worker through the real writer
(:func:`stnh_tf.data.writer.write_sharded`) with each worker count, then
:func:`stnh_tf.data.tfrecords.load_split` reading what was written.
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

from stnh_tf.data import pairs, sources, stage1, writer
from stnh_tf.evaluation.benchmarks import machine_info


def repeated_items(source, image_dir, max_images, repeat, samples_per_image=3):
    """The source's WorkItems ``repeat`` times as distinct items (``repeat <= 0``: enough for about
    1,500 samples); returns ``(items, repeat)``."""
    if source == "folder":
        base, _, _ = stage1.folder_items(image_dir, max_images)
    else:
        base, _, _ = stage1.bundled_items(max_images)
    if not base:
        raise ValueError(f"no photograph to benchmark in {image_dir or 'the bundled set'}.")
    if repeat <= 0:
        repeat = max(1, -(-1500 // (len(base) * samples_per_image)))
    items = [writer.WorkItem(r * len(base) + it.index, f"{it.item_id}#{r}", it.payload)
             for r in range(repeat) for it in base]
    return items, repeat


def data_benchmark(source="bundled", image_dir=None, max_images=0, repeat=0, workers=(1, 2),
                   num_shards=8, batch_size=64, read_batches=200, resume_skip_batches=0,
                   seed=0) -> dict:
    """Runs every measurement of ``experiments.benchmark_data`` in a temporary directory (removed
    afterwards) and returns the result dict."""
    sources.quiet_opencv()
    items, repeat = repeated_items(source, image_dir, max_images, repeat)
    worker_fn = functools.partial(pairs.generate_item_samples, seed=seed,
                                  protocol=pairs.Protocol())
    result = {
        "benchmark": "data generation and tf.data reading",
        "command": " ".join(shlex.quote(a) for a in getattr(sys, "orig_argv", sys.argv)),
        "machine": machine_info(), "seed": seed, "source": source,
        "image_dir": image_dir, "num_images": len(items) // repeat, "repeat": repeat,
        "num_items": len(items), "generation": [],
    }
    import tensorflow as tf  # imported up front so its start-up is not in the timings

    result["machine"]["tensorflow"] = tf.__version__
    root = tempfile.mkdtemp(prefix="stnh-bench-")
    digests = {}
    try:
        for w in [int(x) for x in workers]:
            out = os.path.join(root, f"w{w}")
            t0 = time.perf_counter()
            sec = writer.write_sharded(out, "train", items, worker_fn, num_shards=num_shards,
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

        from stnh_tf.data import tfrecords as data

        read_dir = os.path.join(root, f"w{int(workers[0])}")
        ds = data.load_split(read_dir, "train", batch_size, shuffle=True, seed=0)
        it = iter(ds)
        for _ in range(10):
            next(it)
        t0 = time.perf_counter()
        for _ in range(read_batches):
            x, y, w = next(it)
        float(x["patch_a"][0, 0, 0, 0])  # make sure the last batch is materialized
        dt = time.perf_counter() - t0
        result["reading"] = {"batch_size": batch_size, "batches": read_batches,
                             "samples_per_s": round(read_batches * batch_size / dt, 1),
                             "wall_s": round(dt, 3),
                             "pipeline": "load_split(shuffle=True, repeat=True), 8 shards"}
        n = resume_skip_batches
        if n > 0:
            first = {}
            for where in ("skip_before_parse", "skip_after_parse"):
                t0 = time.perf_counter()
                if where == "skip_before_parse":
                    ds = data.load_split(read_dir, "train", batch_size, seed=0, skip_batches=n)
                else:
                    ds = data.load_split(read_dir, "train", batch_size, seed=0).skip(n)
                x, _, _ = next(iter(ds))
                float(x["patch_a"][0, 0, 0, 0])
                first[where] = round(time.perf_counter() - t0, 3)
            result["resume_skip"] = {"skip_batches": n, "batch_size": batch_size,
                                     "seconds_to_first_batch": first}
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return result


def stage_pairs_benchmark(images="bundled", samples_per_image=40, threads=(1, 2), repeats=2,
                          error_px=8.0, seed=0, max_images=0) -> dict:
    """Times the re-making of stage-2 pairs in memory
    (:func:`stnh_tf.hierarchy.next_stage_arrays`, what a stage-k > 1 chunk does before training)
    for the result dict of ``experiments.benchmark_stage_pairs``.

    The stage is an oracle: each pair's true ``H_ba`` composed with a random error moving each
    corner by up to ``error_px``, so the degenerate-prediction rule's clipping is exercised.
    ``ms_per_pair`` is the wall time per pair, the oracle's look-ups included (their seconds are
    reported apart as ``oracle_s``). The pairs of every thread count must be equal to the bit
    (``identical_across_threads``). ``max_images``: the first N photographs only (0: all).
    """
    import cv2
    import numpy as np

    from stnh_tf import geometry, hierarchy
    from stnh_tf.data import batches

    sources.quiet_opencv()
    images = images if images == "bundled" else sources.split_folders(images)
    t0 = time.perf_counter()
    arrays = batches.materialize(batches.PairBatches(images, 1, samples_per_image=samples_per_image,
                                                     seed=seed, max_images=max_images),
                                 context=True)
    made_s = time.perf_counter() - t0
    n = len(arrays["patch_b"])
    rng = np.random.default_rng(seed)
    corners = geometry.patch_corners().astype(np.float32)
    table = {}
    for i in range(n):
        moved = corners + rng.uniform(-error_px, error_px, (4, 2)).astype(np.float32)
        key = (arrays["patch_b"][i] / np.float32(255)).astype(np.float32).tobytes()
        table[key] = arrays["h_ba"][i] @ cv2.getPerspectiveTransform(corners, moved)
    if len(table) != n:
        raise ValueError(f"{n - len(table)} pairs share their patch_b; the oracle needs them "
                         "distinct (use more varied photographs).")
    inside = [0.0]

    def oracle(patch_a, patch_b):
        t = time.perf_counter()
        h = np.stack([table[b[..., 0].tobytes()] for b in patch_b])
        inside[0] += time.perf_counter() - t
        return h

    runs, digests = [], {}
    for t in [int(x) for x in threads]:
        for _ in range(repeats):
            inside[0] = 0.0
            t0 = time.perf_counter()
            pairs, rejected = hierarchy.next_stage_arrays(arrays, [oracle], threads=t)
            wall = time.perf_counter() - t0
            runs.append({"threads": t, "wall_s": round(wall, 3), "oracle_s": round(inside[0], 3),
                         "ms_per_pair": round(1e3 * wall / n, 4),
                         "degenerate_rule_cases": rejected})
        digest = hashlib.sha256()
        for key in sorted(pairs):
            digest.update(np.ascontiguousarray(pairs[key]).tobytes())
        digests[t] = digest.hexdigest()
    return {"benchmark": "stage-2 pairs re-made in memory (hierarchy.next_stage_arrays)",
            "command": " ".join(shlex.quote(a) for a in getattr(sys, "orig_argv", sys.argv)),
            "machine": machine_info(), "seed": seed, "images": str(images), "pairs": n,
            "samples_per_image": samples_per_image, "error_px": error_px,
            "pairs_with_context_made_s": round(made_s, 3), "runs": runs,
            "best_ms_per_pair": {t: min(r["ms_per_pair"] for r in runs if r["threads"] == t)
                                 for t in digests},
            "identical_across_threads": len(set(digests.values())) == 1, "sha256": digests}
