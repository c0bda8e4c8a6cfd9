"""Input pipelines: TFRecord datasets for ``model.fit`` and evaluation, and a TF-free generator.

Datasets are written by ``python -m data_prep.make_dataset`` (spec: :mod:`stnh_tf.features`).
A dataset directory holds ``{split}-NNNNN-of-MMMMM.tfrecord`` shards and ``metadata.json``
(``{"stage": k, "feature_spec": ..., "splits": {split: {...}}}``); the readers trust only the
shards the metadata lists for a split whose ``status`` is ``"complete"``.

Batches for training are ``(x, y, w)``::

    x = {"patch_a": float32 [B, 128, 128, 1] in [0, 1], "patch_b": same}
    y = {"h_bar": float32 [B, 8], "patch_a_warp": float32 [B, 128, 128, 1] in [0, 1]}
    w = {"h_bar": float32 [B] (= h_mask), "patch_a_warp": float32 [B] (ones)}

where ``patch_a_warp`` is the stored ``patch_a_t`` (``patch_a`` warped by the true ``H_ba``:
``patch_a_t(p) = patch_a(H_ba @ p)``, zero outside), the target of the photometric loss.

TensorFlow is imported only inside the TFRecord functions; :class:`PairSequence` (and
:class:`PairBatches`) generate the same samples with NumPy/OpenCV only, so training can also run
under the JAX backend without TFRecords.
"""

from __future__ import annotations

import json
import logging
import os
import time

import keras
import numpy as np

from stnh_tf import features, pixels
from stnh_tf.paths import inside
from stnh_tf.batches import (PairBatches, generator_pool, materialize, model_batch,  # noqa: F401
                             numpy_model_batch, stack_samples, step_batch_async)
from stnh_tf.sources import (ImageDecodeError, SourceError, bundled_image_files,  # noqa: F401
                             bundled_images, list_image_files, load_gray_320x240,
                             scan_image_folder)

METADATA_FILE = "metadata.json"
MODEL_FIELDS = ("patch_a", "patch_b", "patch_a_t", "h_bar", "h_mask")
"""The fields :func:`load_split` parses (context_a and the rest are skipped)."""

_log = logging.getLogger(__name__)


class ShardError(OSError):
    """A missing, truncated or corrupted shard; the message names the file."""


# ------------------------------------------------------------------------------------------------
# Metadata and shard lists
# ------------------------------------------------------------------------------------------------
def read_metadata(data_dir: str) -> dict:
    """The parsed ``metadata.json`` of a dataset directory.

    Raises:
      FileNotFoundError: no ``metadata.json`` there (message names the path).
      ValueError: not valid JSON / not a dataset's metadata (message names the path).
    """
    path = os.path.join(data_dir, METADATA_FILE)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no dataset metadata at {path!r}; generate the dataset with "
                                "python -m data_prep.make_dataset --output_dir=...")
    try:
        with open(path) as f:
            meta = json.load(f)
    except ValueError as e:
        raise ValueError(f"{path!r} is not valid JSON: {e}") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("splits"), dict):
        raise ValueError(f"{path!r} is not a stnh-tf dataset metadata file (no 'splits' object).")
    return meta


def has_split(data_dir: str, split: str) -> bool:
    """Whether ``data_dir`` holds a complete ``split``."""
    try:
        return read_metadata(data_dir)["splits"].get(split, {}).get("status") == "complete"
    except (FileNotFoundError, ValueError):
        return False


def split_info(data_dir: str, split: str) -> dict:
    """The ``metadata.json`` section of ``split`` (counts, seed, protocol, shards, skipped).

    Raises:
      ValueError: the split is missing or was not written to completion.
    """
    meta = read_metadata(data_dir)
    info = meta["splits"].get(split)
    path = os.path.join(data_dir, METADATA_FILE)
    if info is None:
        raise ValueError(f"split {split!r} not in {path!r} (has: {sorted(meta['splits'])}).")
    if info.get("status") != "complete":
        raise ValueError(f"split {split!r} in {path!r} has status {info.get('status')!r}: its "
                         "generation did not finish; re-run the same make_dataset command.")
    return info


def shard_paths(data_dir: str, split: str, verify: str = "size") -> list:
    """Paths of ``split``'s shards, in order, as listed in ``metadata.json``.

    Args:
      verify: ``"none"``; ``"size"`` (default, cheap: each shard exists with the recorded byte
        count, which catches truncation); ``"full"`` (also reads every record, checking TFRecord
        CRCs and record counts).
    Raises:
      ShardError: a missing, truncated or corrupted shard (naming the file).
      ValueError: a shard's ``file`` is not a path inside ``data_dir`` (:func:`paths.inside`).
    """
    if verify not in ("none", "size", "full"):
        raise ValueError(f"verify must be 'none', 'size' or 'full'; received {verify!r}.")
    info = split_info(data_dir, split)
    paths = []
    for shard in info["shards"]:
        path = inside(data_dir, shard.get("file"), f"{os.path.join(data_dir, METADATA_FILE)!r}, "
                      f"a shard of split {split!r}")
        if verify != "none":
            if not os.path.isfile(path):
                raise ShardError(f"shard {path!r} listed in metadata.json is missing.")
            size = os.path.getsize(path)
            if size != shard["num_bytes"]:
                raise ShardError(f"shard {path!r} is truncated or corrupted: {size} bytes, "
                                 f"metadata.json records {shard['num_bytes']}.")
        paths.append(path)
    if verify == "full":
        for path, shard in zip(paths, info["shards"]):
            n = sum(1 for _ in _iter_records(path))
            if n != shard["num_samples"]:
                raise ShardError(f"shard {path!r} holds {n} records, metadata.json records "
                                 f"{shard['num_samples']}.")
    return paths


def verify_split(data_dir: str, split: str) -> int:
    """Read every record of ``split`` (CRC-checked); returns the sample count.

    Raises:
      ShardError: naming the first bad shard.
    """
    shard_paths(data_dir, split, verify="full")
    return split_info(data_dir, split)["num_samples"]


def _iter_records(path: str, batch: int = 0):
    """Serialized records (or batches of them) of one shard; errors re-raised naming ``path``."""
    import tensorflow as tf

    ds = tf.data.TFRecordDataset(path, buffer_size=4 << 20)
    if batch:
        ds = ds.batch(batch)
    it = iter(ds)
    while True:
        try:
            yield next(it)
        except StopIteration:
            return
        except (tf.errors.DataLossError, tf.errors.OutOfRangeError,
                tf.errors.InvalidArgumentError) as e:
            raise ShardError(f"shard {path!r} is corrupted or truncated: {e.message}") from None


# ------------------------------------------------------------------------------------------------
# tf.data pipelines
# ------------------------------------------------------------------------------------------------
def to_model_batch(parsed: dict):
    """Parsed fields (uint8 patches ``[..., 128, 128]``) -> ``(x, y, w)`` of float32 tensors."""
    import tensorflow as tf

    def unit(t):
        return tf.cast(t, tf.float32)[..., None] / 255.0

    x = {"patch_a": unit(parsed["patch_a"]), "patch_b": unit(parsed["patch_b"])}
    y = {"h_bar": parsed["h_bar"], "patch_a_warp": unit(parsed["patch_a_t"])}
    w = {"h_bar": parsed["h_mask"], "patch_a_warp": tf.ones_like(parsed["h_mask"])}
    return x, y, w


def load_raw(data_dir: str, split: str, fields=None, verify: str = "size"):
    """``tf.data.Dataset`` of parsed, unbatched samples in stored (index) order.

    Each element is a dict (all of :data:`features.FEATURE_NAMES`, or ``fields``) with
    ``patch_*`` uint8 ``[128, 128]``, ``context_a`` uint8 ``[192, 192]``, ``h_bar`` float32
    ``[8]``, ``h_ba``/``h_prev`` float32 ``[3, 3]``, ``h_mask`` float32 ``[]``, ``square_xy``
    int64 ``[2]``, ``image_id`` string ``[]``, ``index`` int64 ``[]``.
    """
    import tensorflow as tf

    paths = shard_paths(data_dir, split, verify)
    names = tuple(features.FEATURE_NAMES if fields is None else fields)
    ds = tf.data.TFRecordDataset(paths, buffer_size=4 << 20)
    return ds.map(lambda r: features.parse_examples(r, names),
                  num_parallel_calls=tf.data.AUTOTUNE, deterministic=True)


def load_split(data_dir: str, split: str, batch_size: int, shuffle: bool = True, seed: int = 0,
               repeat: bool = True, drop_remainder: bool = True, shuffle_buffer: int = 1024,
               cycle_length: int = 8, verify: str = "size", skip_batches: int = 0):
    """The training/validation stream: ``tf.data.Dataset`` of ``(x, y, w)`` batches (see module).

    Shards are read interleaved (``cycle_length`` at a time, deterministic), records shuffled
    with a seeded buffer (``shuffle_buffer`` serialized records, ~86 KB each), batched, parsed in
    parallel (only :data:`MODEL_FIELDS`), and prefetched. The order is a function of ``seed``
    alone, so a resumed run starts at the same position with ``skip_batches=n``: the first ``n``
    batches are still read and shuffled (the shuffle buffer's state depends on them) but not
    parsed. With ``shuffle`` the shard order is also reshuffled (seeded) every pass.

    Raises:
      ValueError / FileNotFoundError: missing or incomplete split; fewer samples than one batch
        with ``drop_remainder``.
      ShardError: missing or truncated shard (``verify="size"``), corrupted (``verify="full"``).
    """
    import tensorflow as tf

    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1; received {batch_size}.")
    info = split_info(data_dir, split)
    if drop_remainder and info["num_samples"] < batch_size:
        raise ValueError(f"split {split!r} of {data_dir!r} has {info['num_samples']} samples, "
                         f"fewer than one batch of {batch_size}.")
    paths = shard_paths(data_dir, split, verify)
    files = tf.data.Dataset.from_tensor_slices(paths)
    if shuffle:
        files = files.shuffle(len(paths), seed=seed, reshuffle_each_iteration=True)
    if repeat:
        files = files.repeat()
    ds = files.interleave(lambda p: tf.data.TFRecordDataset(p, buffer_size=4 << 20),
                          cycle_length=max(1, min(cycle_length, len(paths))), block_length=1,
                          num_parallel_calls=tf.data.AUTOTUNE, deterministic=True)
    if shuffle:
        ds = ds.shuffle(shuffle_buffer, seed=seed, reshuffle_each_iteration=True)
    ds = ds.batch(batch_size, drop_remainder=drop_remainder)
    if skip_batches:
        ds = ds.skip(skip_batches)
    ds = ds.map(lambda r: to_model_batch(features.parse_examples(r, MODEL_FIELDS)),
                num_parallel_calls=tf.data.AUTOTUNE, deterministic=True)
    options = tf.data.Options()
    options.deterministic = True
    return ds.with_options(options).prefetch(tf.data.AUTOTUNE)


def load_arrays(data_dir: str, split: str, max_samples=None, verify: str = "size") -> dict:
    """The first ``max_samples`` samples (all by default) as NumPy arrays, for evaluation.

    Returns:
      ``patch_a``, ``patch_b``, ``patch_a_t``: float32 ``[N, 128, 128, 1]`` in [0, 1];
      ``context_a`` uint8 ``[N, 192, 192]``; ``h_bar`` float32 ``[N, 8]``; ``h_ba``, ``h_prev``
      float64 ``[N, 3, 3]``; ``h_mask`` float32 ``[N]``; ``square_xy`` int64 ``[N, 2]``;
      ``image_id`` str ``[N]``; ``index`` int64 ``[N]``.
    Raises:
      ShardError: a missing, truncated or corrupted shard (naming the file).
    """
    parts = {n: [] for n in features.FEATURE_NAMES}
    count = 0
    for path in shard_paths(data_dir, split, verify):
        if max_samples is not None and count >= max_samples:
            break
        for records in _iter_records(path, batch=256):
            parsed = features.parse_examples(records)
            for n in features.FEATURE_NAMES:
                parts[n].append(parsed[n].numpy())
            count += int(records.shape[0])
            if max_samples is not None and count >= max_samples:
                break
    out = {n: (np.concatenate(v) if v else None) for n, v in parts.items()}
    if out["index"] is None:
        return _empty_arrays()
    n = len(out["index"]) if max_samples is None else min(max_samples, len(out["index"]))
    out = {k: v[:n] for k, v in out.items()}
    for name in ("patch_a", "patch_b", "patch_a_t"):
        out[name] = pixels.to_unit(out[name])[..., None]
    out["h_ba"] = out["h_ba"].astype(np.float64)
    out["h_prev"] = out["h_prev"].astype(np.float64)
    out["image_id"] = np.array([s.decode("utf-8") for s in out["image_id"]], dtype=str)
    return out


def _empty_arrays() -> dict:
    s, c = features.S, features.CONTEXT_SIZE
    return {"patch_a": np.zeros((0, s, s, 1), np.float32),
            "patch_b": np.zeros((0, s, s, 1), np.float32),
            "patch_a_t": np.zeros((0, s, s, 1), np.float32),
            "context_a": np.zeros((0, c, c), np.uint8), "h_bar": np.zeros((0, 8), np.float32),
            "h_ba": np.zeros((0, 3, 3)), "h_prev": np.zeros((0, 3, 3)),
            "h_mask": np.zeros((0,), np.float32), "square_xy": np.zeros((0, 2), np.int64),
            "image_id": np.zeros((0,), str), "index": np.zeros((0,), np.int64)}


# ------------------------------------------------------------------------------------------------
# TF-free on-the-fly generation
# ------------------------------------------------------------------------------------------------
class PairSequence(keras.utils.PyDataset):
    """:class:`PairBatches` as a ``keras.utils.PyDataset``: ``model.fit(PairSequence(...))``.

    Same arguments as :class:`PairBatches`, plus PyDataset's ``workers``,
    ``use_multiprocessing`` and ``max_queue_size``. Batches are ``(x, y, w)`` NumPy arrays with
    :func:`load_split`'s structure; batch ``i`` depends only on ``(seed, i)``. Imports no
    TensorFlow (under the JAX backend, training needs neither TFRecords nor TensorFlow).
    """

    def __init__(self, images="bundled", batch_size: int = 64, *, samples_per_image: int = 3,
                 seed: int = 0, shuffle: bool = True, drop_remainder: bool = True,
                 max_images: int = 0, cache_images: bool = True, mapper=None, workers: int = 1,
                 use_multiprocessing: bool = False, max_queue_size: int = 10,
                 photometric: bool = False):
        super().__init__(workers=workers, use_multiprocessing=use_multiprocessing,
                         max_queue_size=max_queue_size)
        self.batches = PairBatches(images, batch_size, samples_per_image=samples_per_image,
                                   seed=seed, shuffle=shuffle, drop_remainder=drop_remainder,
                                   max_images=max_images, cache_images=cache_images,
                                   photometric=photometric)
        self.mapper = mapper

    def __len__(self) -> int:
        return len(self.batches)

    def __getitem__(self, index: int):
        batch = self.batches.batch(index)
        return self.mapper(*batch) if self.mapper is not None else batch


class ArraySequence(keras.utils.PyDataset):
    """Compact arrays (:func:`stack_samples`' form) served in stored order, ``batch_size`` pairs
    a batch (the last one partial): e.g. fixed validation pairs made in memory."""

    def __init__(self, arrays: dict, batch_size: int, mapper=None):
        super().__init__()
        self.arrays, self.batch_size, self.mapper = arrays, int(batch_size), mapper

    def __len__(self) -> int:
        return -(-len(self.arrays["patch_a"]) // self.batch_size)

    def __getitem__(self, index: int):
        if not 0 <= index < len(self):
            raise IndexError(f"batch {index} out of range [0, {len(self)}).")
        rows = slice(index * self.batch_size, (index + 1) * self.batch_size)
        batch = model_batch({k: v[rows] for k, v in self.arrays.items()})
        return self.mapper(*batch) if self.mapper is not None else batch


class ArrayStream(keras.utils.PyDataset):
    """:class:`PairStream` without ``fresh_pairs``, served from :func:`materialize`'s arrays in
    this process: item ``i`` is the same batch (same samples, same order) as
    ``PairStream(...)[i]``, without generating anything after the start."""

    def __init__(self, arrays: dict, batches: PairBatches, *, start_step: int = 0, mapper=None):
        super().__init__()
        if len(arrays["patch_a"]) != batches.num_samples:
            raise ValueError(f"arrays hold {len(arrays['patch_a'])} samples; batches has "
                             f"{batches.num_samples}.")
        self.arrays, self.batches = arrays, batches
        self.start_step, self.mapper = int(start_step), mapper
        self._order = (0, batches.epoch_order(0))

    @property
    def num_batches(self):
        return None

    def __getitem__(self, index: int):
        epoch, i = divmod(self.start_step + int(index), len(self.batches))
        if self._order[0] != epoch:
            self._order = (epoch, self.batches.epoch_order(epoch))
        size = self.batches.batch_size
        ids = self._order[1][i * size:(i + 1) * size]
        batch = model_batch({k: v[ids] for k, v in self.arrays.items()})
        return self.mapper(*batch) if self.mapper is not None else batch


class PairStream(keras.utils.PyDataset):
    """Endless training stream of :class:`PairBatches` for ``model.fit(..., steps_per_epoch=k)``.

    Item ``i`` is global step ``start_step + i``: batch ``step % n`` of data epoch ``step // n``
    (``n = len(batches)``), so a resumed run given ``start_step`` sees exactly the batches an
    uninterrupted run would have seen. Every data epoch is a new seeded permutation; with
    ``fresh_pairs`` it also draws new squares and perturbations (epoch 0 is make_dataset's set),
    else it repeats the fixed set of ``len(images) * samples_per_image`` pairs, like training on
    the TFRecords. ``mapper(x, y, w)`` maps batches onto the model's outputs (NumPy).

    With ``workers > 0`` the stream owns a pool of that many generator processes
    (:func:`generator_pool`), started at the first item and kept for the stream's life, that
    works ``prefetch`` steps ahead of the last item read (default ``2 * workers``) and sends back
    uint8 batches. Keras itself reads the items in order in its own process, so its per-epoch
    enqueuer (a new process pool every ``fit`` epoch, float batches pickled back) is not used.
    Reading out of order is allowed (it restarts the look-ahead there). ``close()`` stops the
    workers (also done when the stream is garbage-collected).
    """

    def __init__(self, images, batch_size: int = 64, *, samples_per_image: int = 3, seed: int = 0,
                 start_step: int = 0, fresh_pairs: bool = False, mapper=None, max_images: int = 0,
                 workers: int = 0, prefetch: int = 0, photometric: bool = False):
        super().__init__()
        if workers < 0 or prefetch < 0:
            raise ValueError(f"workers and prefetch must be >= 0; received {workers}, {prefetch}.")
        self.batches = PairBatches(images, batch_size, samples_per_image=samples_per_image,
                                   seed=seed, shuffle=True, drop_remainder=True,
                                   max_images=max_images, cache_images=True,
                                   photometric=photometric)
        self.start_step, self.fresh_pairs, self.mapper = int(start_step), bool(fresh_pairs), mapper
        self.num_workers = int(workers)
        self.prefetch = int(prefetch) or 2 * self.num_workers
        self._pool, self._pending, self._next, self._submitted = None, {}, 0, []

    @property
    def num_batches(self):
        return None  # endless: Keras keeps counting indices across epochs

    def __getitem__(self, index: int):
        step = self.start_step + int(index)
        if self.num_workers == 0:
            stacked = self.batches.step_batch(step, self.fresh_pairs)
        else:
            stacked = self._from_workers(step)
        batch = model_batch(stacked)
        return self.mapper(*batch) if self.mapper is not None else batch

    def _from_workers(self, step: int) -> dict:
        if self._pool is None:
            self._pool = generator_pool(self.batches, self.num_workers)
        if step not in self._pending:  # first read, or out of order: look ahead from here
            self._pending, self._next = {}, step
        for old in [s for s in self._pending if s < step]:
            del self._pending[old]
        while self._next < step + max(self.prefetch, 1):
            self._pending[self._next] = step_batch_async(self._pool, self._next, self.fresh_pairs)
            self._submitted.append(self._pending[self._next])
            self._next += 1
        self._submitted = [r for r in self._submitted if not r.ready()]
        return self._pending.pop(step).get()

    def close(self, timeout: float = 60.0):
        """Stop the worker processes (a later item starts new ones).

        The batches in flight are let finish first (``Pool.terminate`` while a worker sends a
        batch back can hang the pool's result thread); only if they take longer than ``timeout``
        seconds are the workers killed."""
        pool, self._pool, self._pending = self._pool, None, {}
        if pool is None:
            return
        pool.close()
        deadline = time.monotonic() + timeout
        for result in self._submitted:
            result.wait(max(deadline - time.monotonic(), 0.0))
        if all(r.ready() for r in self._submitted):
            pool.join()
        else:
            pool.terminate()
        self._submitted = []

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown
            pass

    def __getstate__(self):
        state = self.__dict__.copy()
        state.update(_pool=None, _pending={}, _next=0, _submitted=[])
        return state
