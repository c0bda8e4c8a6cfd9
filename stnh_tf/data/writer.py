"""Generic, deterministic, atomic sharded TFRecord writer with a process pool and progress.

Used by ``data_prep.make_dataset`` (stage 1) and reusable by later-stage generators: give it a
sequence of :class:`WorkItem` and a picklable ``worker_fn(item) -> list of sample dicts`` (the
dicts hold :data:`stnh_tf.data.features.FEATURE_NAMES`).

* **Determinism.** Item ``i`` of ``n`` goes to shard ``i * num_shards // n`` (contiguous blocks, so
  the shards read in order list the items in order); results are written in item order whatever
  ``num_workers`` is. Byte-identical output therefore only needs ``worker_fn`` to depend on the
  item alone (seed its RNG from the item's index).
* **Workers** are ``spawn``-ed processes (``num_workers > 1``) that import only what ``worker_fn``'s
  module imports (no TensorFlow for ``stnh_tf.data.pairs``); they build and serialize the samples.
  The parent process writes the records (TensorFlow's ``TFRecordWriter``, imported lazily here).
  ``num_workers <= 1`` runs everything in-process.
* **One writer per split.** A run holds the split's lock (:func:`stnh_tf.data.metadata.split_lock`)
  from start to end; a second run on the same split fails at once instead of deleting the first
  one's files.
* **Atomicity.** Every shard is written to ``<name>.tmp-<pid>``; once all are written, the split
  is marked ``"incomplete"``, the shards renamed into place, the shards of the earlier split
  that the new layout no longer has (e.g. another ``num_shards``) removed, and the section
  written: a killed or failed run never leaves a split that looks finished, and one that
  regenerates a complete split (``overwrite``) leaves it complete and readable until that swap
  (it needs the disk space of both meanwhile). A new split is marked ``"incomplete"`` from the
  start. A re-run removes its split's stale temporary files. Files named like the split's shards
  that no ``metadata.json`` lists are never written over or removed: the run is refused.
* **Bad input.** An exception from ``worker_fn`` skips that item: it is counted and listed with its
  reason in the split's ``skipped`` list (and logged); it never stops the run.
* **A failed write** (a full disk, a file size limit) stops the run with an ``OSError`` naming
  the file and the cause, whether the operating system or TensorFlow's writer reported it
  (``OutOfRangeError: File too large``, ``ResourceExhaustedError``); a new split stays marked
  ``"incomplete"`` (an earlier complete one stays as it was) and the same command regenerates it.
* **metadata.json** (``{"stage": ..., "feature_spec": ..., "splits": {split: {...}}}``) is
  read-modify-written under a file lock and replaced atomically, so separate commands can write
  ``train`` and ``test`` into one directory (:mod:`stnh_tf.data.metadata`).
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import errno
import glob
import math
import multiprocessing
import os
import re
import time
from typing import Any, Callable, Iterable, Optional

from stnh_tf.data.metadata import check_split_name, read_metadata_file, split_lock, update_metadata
from stnh_tf.data import features
from stnh_tf.data.tfrecords import METADATA_FILE
from stnh_tf.paths import check_output_dir

TARGET_SHARD_BYTES = 128 * 2 ** 20
BYTES_PER_SAMPLE_ESTIMATE = 86_600  # stage-1 record, measured (see docs/data.md)


@dataclasses.dataclass(frozen=True)
class WorkItem:
    """One unit of work: ``index`` (position in the ordered item list, seeds the RNG), ``item_id``
    (named in skip reports) and a picklable ``payload`` (a path, encoded bytes, arrays...)."""

    index: int
    item_id: str
    payload: Any = None


class SkipItem(Exception):
    """Raise from ``worker_fn`` to skip an item with a reason (any exception skips it too)."""


def shard_name(split: str, shard: int, num_shards: int) -> str:
    """``{split}-00003-of-00008.tfrecord``."""
    return f"{split}-{shard:05d}-of-{num_shards:05d}.tfrecord"


def shard_of(item_position: int, num_items: int, num_shards: int) -> int:
    """Shard of the ``item_position``-th of ``num_items`` items: contiguous, balanced blocks."""
    return item_position * num_shards // max(num_items, 1)


def auto_num_shards(num_items: int, samples_per_item: int,
                    bytes_per_sample: int = BYTES_PER_SAMPLE_ESTIMATE) -> int:
    """Shards of about 128 MiB, and at least ``min(8, num_items)`` for interleaved reading."""
    by_size = math.ceil(num_items * samples_per_item * bytes_per_sample / TARGET_SHARD_BYTES)
    return max(1, by_size, min(8, num_items))


# ------------------------------------------------------------------------------------------------
# Workers
# ------------------------------------------------------------------------------------------------
def _init_worker():
    import cv2

    cv2.setNumThreads(1)
    try:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    except AttributeError:  # pragma: no cover
        pass


def _run_chunk(worker_fn: Callable, items: list) -> list:
    """Run ``worker_fn`` on each item; returns ``[(records or None, skip reason or None)]``."""
    out = []
    for item in items:
        try:
            samples = worker_fn(item)
            out.append(([features.serialize_example(s) for s in samples], None))
        except Exception as e:  # noqa: BLE001 - bad input must never stop the run
            plain = isinstance(e, SkipItem) or any(c.__name__ == "ImageDecodeError"
                                                   for c in type(e).__mro__)  # its subclasses too
            msg = str(e) if plain else f"{type(e).__name__}: {e}"
            out.append((None, msg or type(e).__name__))
    return out


def _chunks(items: Iterable, size: int):
    buf = []
    for item in items:
        buf.append(item)
        if len(buf) == size:
            yield buf
            buf = []
    if buf:
        yield buf


def _ordered_results(items: Iterable, worker_fn: Callable, num_workers: int, chunk_size: int):
    """Yield ``(item, records, reason)`` in item order; at most a few chunks in flight."""
    if num_workers <= 1:
        import cv2

        threads = cv2.getNumThreads()
        cv2.setNumThreads(1)  # as in the workers; restored for the caller afterwards
        try:
            for chunk in _chunks(items, chunk_size):
                for item, (records, reason) in zip(chunk, _run_chunk(worker_fn, chunk)):
                    yield item, records, reason
        finally:
            cv2.setNumThreads(threads)
        return
    from concurrent.futures import ProcessPoolExecutor
    from concurrent.futures.process import BrokenProcessPool

    # spawn: workers start clean (no TensorFlow state forked from the parent); a worker that
    # dies (e.g. a decoder crash) breaks the pool: ChildProcessError below, not a hang.
    pool = ProcessPoolExecutor(num_workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_init_worker)
    try:
        pending = collections.deque()
        chunk_iter = _chunks(items, chunk_size)
        max_in_flight = 4 * num_workers
        exhausted = False
        while True:
            while not exhausted and len(pending) < max_in_flight:
                chunk = next(chunk_iter, None)
                if chunk is None:
                    exhausted = True
                    break
                pending.append((chunk, pool.submit(_run_chunk, worker_fn, chunk)))
            if not pending:
                break
            chunk, future = pending.popleft()
            try:
                done = future.result()
            except BrokenProcessPool:
                raise ChildProcessError(
                    f"a worker process stopped abruptly on one of the items {chunk[0].item_id} "
                    f"... {chunk[-1].item_id} (a crash in an image decoder, or out of memory); "
                    "run again with --num_workers=1 to see which item it is.") from None
            for item, (records, reason) in zip(chunk, done):
                yield item, records, reason
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


# ------------------------------------------------------------------------------------------------
# The writer
# ------------------------------------------------------------------------------------------------
class _Progress:
    def __init__(self, split, total, log, interval_s):
        self.split, self.total, self.log, self.interval = split, total, log, interval_s
        self.t0 = time.perf_counter()
        self.last = self.t0
        self.items = self.samples = self.skipped = 0

    def update(self, n_samples, skipped, force=False):
        self.items += 1
        self.samples += n_samples
        self.skipped += int(skipped)
        now = time.perf_counter()
        if force or now - self.last >= self.interval:
            self.last = now
            dt = max(now - self.t0, 1e-9)
            rate = self.samples / dt
            left = (self.total - self.items) * (dt / max(self.items, 1))
            self.log(f"[{self.split}] {self.items}/{self.total} items "
                     f"({100.0 * self.items / max(self.total, 1):.0f}%), {self.samples} samples, "
                     f"{self.skipped} skipped, {rate:.0f} samples/s, ETA {left:.0f} s")


def _foreign_shards(output_dir, split, listed) -> list:
    """The files in ``output_dir`` named like ``split``'s shards that ``listed`` lacks."""
    rx = re.compile(rf"^{re.escape(split)}-\d{{5}}-of-\d{{5}}\.tfrecord$")
    return sorted(n for n in os.listdir(output_dir) if rx.match(n) and n not in listed)


@contextlib.contextmanager
def _naming_write_errors(path: str, split: str):
    """Re-raise a failed write to ``path`` (an ``OSError``, or TensorFlow's error for one) as an
    ``OSError`` whose message names ``path`` and the cause (``errno`` kept where there is one)."""
    import tensorflow as tf

    try:
        yield
    except (OSError, tf.errors.OpError) as e:
        if isinstance(e, tf.errors.OpError):
            cause = f"{type(e).__name__}: {e.message}"
        else:
            cause = e.strerror or str(e)
        code = getattr(e, "errno", None)
        fix = ("raise the file size limit (ulimit -f)"
               if code == errno.EFBIG or "File too large" in cause else "free disk space")
        error = OSError(f"cannot write {path}: {cause} (split {split!r} is left incomplete: fix "
                        f"the cause, e.g. {fix}, then run the same command again)")
        error.errno = code
        raise error from None


def _remove_temporary(temps):
    for path in temps:
        with contextlib.suppress(FileNotFoundError):
            os.remove(path)


def _swap_in(output_dir, split, temps, names, existing, marker, top, check):
    """Mark the split incomplete (where ``check`` still passes), rename the written ``temps`` to
    their ``names`` and remove the shards of the ``existing`` section the new layout lacks (and
    those a swap cut short had listed: ``replacing``). A kill in this instant leaves the split
    incomplete, never a complete one mixing two runs."""
    earlier = marker["replacing"]
    meta_path = os.path.join(output_dir, METADATA_FILE)
    with _naming_write_errors(meta_path, split):
        try:
            update_metadata(output_dir, split, marker, top, check)
        except BaseException:
            _remove_temporary(temps)
            raise
        for temp, name in zip(temps, names):
            os.replace(temp, os.path.join(output_dir, name))
        for old in earlier:
            if isinstance(old, str) and old not in names and os.path.basename(old) == old:
                with contextlib.suppress(FileNotFoundError):
                    os.remove(os.path.join(output_dir, old))


def _fsync_path(path):
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_sharded(output_dir: str, split: str, work_items: Iterable, worker_fn: Callable, *,
                  num_shards: int, num_items: Optional[int] = None, num_workers: int = 1,
                  split_metadata: Optional[dict] = None, top_metadata: Optional[dict] = None,
                  preskipped: Iterable = (), chunk_size: int = 4, log: Callable = print,
                  progress_interval_s: float = 5.0, overwrite: bool = False,
                  check: Optional[Callable] = None,
                  final_metadata: Optional[Callable] = None) -> dict:
    """Generate and write ``split`` as ``num_shards`` TFRecord shards in ``output_dir``.

    Args:
      output_dir: created if needed; must be writable (checked before any work).
      split: e.g. ``"train"``; names the shards ``{split}-00003-of-00008.tfrecord``.
      work_items: :class:`WorkItem` in order (a sequence, or an iterable with ``num_items``);
        consumed lazily, a few chunks ahead of the writer.
      worker_fn: picklable (module-level function or ``functools.partial`` of one);
        ``worker_fn(item) -> list of sample dicts`` for :func:`features.serialize_example`.
        Any exception skips the item with a reason.
      num_shards: number of shards (>= 1).
      num_items: ``len(work_items)`` when ``work_items`` has no ``len``.
      num_workers: processes (``<= 1``: in-process).
      split_metadata: extra keys for this split's section (seed, protocol, source, command...).
      top_metadata: keys for the top level (e.g. ``{"stage": 1}``); a different ``stage`` already
        recorded there is an error.
      preskipped: ``(item_id, reason)`` found before generation (e.g. unreadable directories),
        listed with the skipped items.
      chunk_size: items per task sent to a worker.
      log: progress/warning printer; progress every ``progress_interval_s`` seconds.
      overwrite: regenerate a split that ``metadata.json`` records as complete (otherwise
        refused before anything is touched); the complete split stays readable until the new
        one is written, and stays as it was where the new one fails or is empty.
      check: ``check(metadata)``, called with the folder's ``metadata.json`` (a dict) under its
        lock before the split is marked and again before the swap; raises to refuse the split
        (what other splits being written meanwhile record: e.g. the hold-out's fraction).
      final_metadata: ``final_metadata() -> dict`` of keys known once every item is generated
        (e.g. counts made while generating), merged into the section.
    Returns:
      The split's metadata section (also written to ``metadata.json``).
    Raises:
      ValueError: no work items, bad ``num_shards``/``split``, every item skipped, or
        ``output_dir`` holds a ``metadata.json`` this project did not write
        (:func:`stnh_tf.data.metadata.read_metadata_file`; checked before anything is written),
        or files named like the split's shards that its ``metadata.json`` does not list; what
        ``check`` raises.
      OSError: ``output_dir`` not writable, or a write failed (the message names the file and
        the cause: a full disk, a file size limit).
      FileExistsError: the split is complete and ``overwrite`` is off, or another process is
        writing it (:func:`stnh_tf.data.metadata.split_lock`).
    """
    check_split_name(split)
    if num_items is None:
        num_items = len(work_items)
    if num_items <= 0:
        raise ValueError(f"no work items for split {split!r}: nothing to write.")
    if num_shards < 1:
        raise ValueError(f"num_shards must be >= 1; received {num_shards}.")
    output_dir = check_output_dir(output_dir)
    read_metadata_file(output_dir)  # a metadata.json that is not ours: refused before the lock
    with split_lock(output_dir, split):
        return _write_split(output_dir, split, work_items, worker_fn, num_shards=num_shards,
                            num_items=num_items, num_workers=num_workers,
                            split_metadata=split_metadata, top_metadata=top_metadata,
                            preskipped=preskipped, chunk_size=chunk_size, log=log,
                            progress_interval_s=progress_interval_s, overwrite=overwrite,
                            check=check, final_metadata=final_metadata)


def _write_split(output_dir, split, work_items, worker_fn, *, num_shards, num_items, num_workers,
                 split_metadata, top_metadata, preskipped, chunk_size, log, progress_interval_s,
                 overwrite, check, final_metadata) -> dict:
    """:func:`write_sharded` once its arguments are checked, holding the split's lock: no other
    writer of the split runs, so temporary shards left in the folder are stale ones."""
    existing = read_metadata_file(output_dir).get("splits", {}).get(split, {})
    if existing.get("status") == "complete" and not overwrite:
        raise FileExistsError(
            f"{output_dir} already holds a complete {split!r} split ({existing.get('num_samples')} "
            "samples); pass --overwrite to regenerate it (it stays readable until the new one "
            "is written).")
    names = [shard_name(split, k, num_shards) for k in range(num_shards)]
    earlier = ([x.get("file") for x in existing.get("shards", [])]  # (and a cut-short run's)
               + existing.get("replacing", []) + existing.get("writing", []))
    if foreign := _foreign_shards(output_dir, split, earlier):  # (a user's: not written over)
        raise ValueError(f"{output_dir} holds files named like the {split!r} split's shards "
                         f"({foreign[:3]}) that its {METADATA_FILE} does not list: they are not "
                         "written over; move them aside, or write to another --output_dir.")
    top = {"feature_spec": features.spec_as_dict(), **(top_metadata or {})}
    meta_path = os.path.join(output_dir, METADATA_FILE)
    marker = {**(split_metadata or {}), "status": "incomplete", "started_pid": os.getpid(),
              "replacing": earlier,  # (kept: a later run removes them if this one is cut short)
              "writing": names}
    with _naming_write_errors(meta_path, split):  # (an earlier complete split stays readable)
        update_metadata(output_dir, split,
                        None if existing.get("status") == "complete" else marker, top, check)
    if existing:  # (temporary files of this split's earlier runs; none of a user's)
        for stale in glob.glob(os.path.join(output_dir,
                                            f"{glob.escape(split)}-*.tfrecord.tmp-*")):
            os.remove(stale)

    import tensorflow as tf  # the parent writes; workers never import TensorFlow

    shards = [{"file": n, "num_samples": 0, "num_bytes": 0} for n in names]
    skipped = [{"item_id": i, "reason": r} for i, r in preskipped]
    for entry in skipped:
        log(f"[{split}] skipped {entry['item_id']}: {entry['reason']}")
    progress = _Progress(split, num_items, log, progress_interval_s)
    t0 = time.perf_counter()
    writer, current = None, -1
    temps = [os.path.join(output_dir, f"{n}.tmp-{os.getpid()}") for n in names]

    def open_shard(k):
        nonlocal writer, current
        current = k
        with _naming_write_errors(os.path.join(output_dir, names[k]), split):
            writer = tf.io.TFRecordWriter(temps[k])

    def close_shard():
        nonlocal writer
        with _naming_write_errors(os.path.join(output_dir, names[current]), split):
            writer.close()
            _fsync_path(temps[current])
        shards[current]["num_bytes"] = os.path.getsize(temps[current])
        writer = None

    results = _ordered_results(work_items, worker_fn, num_workers, chunk_size)
    try:
        position = 0
        for item, records, reason in results:
            k = shard_of(position, num_items, num_shards)
            position += 1
            while current < k:
                if writer is not None:
                    close_shard()
                open_shard(current + 1)
            if reason is not None:
                skipped.append({"item_id": item.item_id, "reason": reason})
                log(f"[{split}] skipped {item.item_id}: {reason}")
                progress.update(0, True)
                continue
            with _naming_write_errors(os.path.join(output_dir, names[k]), split):
                for rec in records:
                    writer.write(rec)
            shards[k]["num_samples"] += len(records)
            progress.update(len(records), False)
        if position != num_items:
            raise ValueError(f"work_items yielded {position} items, num_items said {num_items}.")
        while current < num_shards - 1:
            if writer is not None:
                close_shard()
            open_shard(current + 1)
        close_shard()
    except BaseException:
        results.close()  # stops the worker pool now
        if writer is not None:
            with contextlib.suppress(Exception):
                writer.close()
        _remove_temporary(temps)
        raise
    wall = time.perf_counter() - t0
    num_samples = sum(s["num_samples"] for s in shards)
    num_bytes = sum(s["num_bytes"] for s in shards)
    if not num_samples and existing.get("status") == "complete":
        _remove_temporary(temps)
        reasons = "; ".join(f"{s['item_id']}: {s['reason']}" for s in skipped[:5])
        raise ValueError(f"every item of split {split!r} was skipped: nothing written, the "
                         f"earlier complete split is kept (first reasons: {reasons}).")
    section = dict(split_metadata or {})
    section.update(**(final_metadata() if final_metadata else {}))
    section.update(
        status="complete" if num_samples else "empty",
        num_items=num_items,
        num_items_used=num_items - progress.skipped,
        num_items_skipped=progress.skipped,
        num_preskipped=len(skipped) - progress.skipped,
        skipped=skipped,
        num_samples=num_samples,
        num_shards=num_shards,
        shards=shards,
        num_bytes=num_bytes,
        bytes_per_sample=round(num_bytes / num_samples, 1) if num_samples else None,
        num_workers=num_workers,
        generation_wall_s=round(wall, 3),
        samples_per_s=round(num_samples / wall, 1) if wall > 0 else None,
        finished_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    )
    _swap_in(output_dir, split, temps, names, existing, marker, top, check)
    with _naming_write_errors(meta_path, split):
        update_metadata(output_dir, split, section, top)
    log(f"[{split}] wrote {num_samples} samples from {section['num_items_used']} items "
        f"({len(skipped)} skipped) into {num_shards} shards, {num_bytes / 2 ** 20:.1f} MiB, "
        f"{wall:.1f} s ({section['samples_per_s']} samples/s) -> {output_dir}")
    if not num_samples:
        reasons = "; ".join(f"{s['item_id']}: {s['reason']}" for s in skipped[:5])
        raise ValueError(f"every item of split {split!r} was skipped, nothing written "
                         f"(first reasons: {reasons}).")
    return section
