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

import keras
import numpy as np

from stnh_tf import features, pairs, sources
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
    """
    if verify not in ("none", "size", "full"):
        raise ValueError(f"verify must be 'none', 'size' or 'full'; received {verify!r}.")
    info = split_info(data_dir, split)
    paths = []
    for shard in info["shards"]:
        path = os.path.join(data_dir, shard["file"])
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
               cycle_length: int = 8, verify: str = "size"):
    """The training/validation stream: ``tf.data.Dataset`` of ``(x, y, w)`` batches (see module).

    Shards are read interleaved (``cycle_length`` at a time, deterministic), records shuffled
    with a seeded buffer (``shuffle_buffer`` serialized records, ~86 KB each), batched, parsed in
    parallel (only :data:`MODEL_FIELDS`), and prefetched. The order is a function of ``seed``
    alone, so a resumed run can ``.skip(n)`` to the same position. With ``shuffle`` the shard
    order is also reshuffled (seeded) every pass.

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
        out[name] = (out[name].astype(np.float32) / 255.0)[..., None]
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
def numpy_model_batch(samples: list):
    """Sample dicts (:func:`pairs.make_pair` + ``h_mask``) -> ``(x, y, w)`` of NumPy arrays,
    the same structure and values as :func:`to_model_batch`."""
    def unit(name):
        stacked = np.stack([s[name] for s in samples]).astype(np.float32)
        return (stacked / np.float32(255.0))[..., None]

    h_mask = np.array([s.get("h_mask", 1.0) for s in samples], np.float32)
    x = {"patch_a": unit("patch_a"), "patch_b": unit("patch_b")}
    y = {"h_bar": np.stack([s["h_bar"] for s in samples]).astype(np.float32),
         "patch_a_warp": unit("patch_a_t")}
    w = {"h_bar": h_mask, "patch_a_warp": np.ones_like(h_mask)}
    return x, y, w


class PairBatches:
    """Stage-1 samples generated on the fly from images, batched; NumPy/OpenCV only.

    Sample ``s`` is sample ``k = s % samples_per_image`` of image ``s // samples_per_image``
    (counting usable images), generated exactly as ``make_dataset`` does (RNG
    ``default_rng([seed, image_index])`` with ``image_index`` the image's position in the given
    list), so the same images, seed and protocol give the same samples as the TFRecords.
    Batch ``i`` depends only on ``(seed, i)``; with ``shuffle`` the sample order is one fixed,
    seeded permutation.

    Args:
      images: ``"bundled"``; a folder (every image file below it, sorted as make_dataset does);
        a list of paths; or a list of ``(image_id, path | encoded bytes | array)``.
      batch_size: samples per batch.
      samples_per_image: squares per image (paper: 3).
      seed: as ``make_dataset --seed``.
      shuffle: permute samples (seeded); else stored order.
      drop_remainder: drop the last partial batch.
      max_images: use only the first N images (0 = all), as ``make_dataset --max_images``.
      cache_images: decode every image once at construction (unusable ones are dropped and
        listed in ``self.skipped`` with reasons); else decode on demand (errors then raise).
    """

    def __init__(self, images="bundled", batch_size: int = 64, *, samples_per_image: int = 3,
                 seed: int = 0, shuffle: bool = True, drop_remainder: bool = True,
                 max_images: int = 0, cache_images: bool = True):
        self.protocol = pairs.Protocol(samples_per_image=samples_per_image)
        self.batch_size, self.seed = int(batch_size), int(seed)
        self.shuffle, self.drop_remainder = shuffle, drop_remainder
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1; received {batch_size}.")
        entries = _image_entries(images)
        if max_images > 0:
            entries = entries[:max_images]
        self.skipped = []
        self._cache = {}
        if cache_images:
            kept = []
            for index, image_id, payload in entries:
                try:
                    self._cache[index] = sources.as_gray_320x240(payload)
                    kept.append((index, image_id, payload))
                except ImageDecodeError as e:
                    self.skipped.append((image_id, str(e)))
                    _log.warning("PairBatches: skipped %s: %s", image_id, e)
            entries = kept
        if not entries:
            raise SourceError(f"no usable images in {images!r}.")
        self.entries = entries
        self.num_samples = len(entries) * samples_per_image
        if drop_remainder and self.num_samples < self.batch_size:
            raise ValueError(f"{self.num_samples} samples, fewer than one batch of {batch_size}.")
        self.order = (np.random.default_rng([self.seed, 0, 0x5348]).permutation(self.num_samples)
                      if shuffle else np.arange(self.num_samples))

    def __len__(self) -> int:
        if self.drop_remainder:
            return self.num_samples // self.batch_size
        return -(-self.num_samples // self.batch_size)

    def _image(self, pos: int) -> np.ndarray:
        index, _, payload = self.entries[pos]
        if index in self._cache:
            return self._cache[index]
        return sources.as_gray_320x240(payload)

    def sample(self, s: int, epoch: int = 0) -> dict:
        """Sample ``s`` (stored order) as a dict like one TFRecord example (uint8 patches).

        ``epoch > 0`` draws a fresh sample from the same image (RNG
        ``default_rng([seed, image_index, epoch])``); epoch 0 is make_dataset's sample."""
        pos, k = divmod(int(s), self.protocol.samples_per_image)
        index, image_id, _ = self.entries[pos]
        rng = (pairs.image_rng(self.seed, index) if epoch == 0 else
               np.random.default_rng([self.seed, int(index), int(epoch)]))
        params = pairs.draw_params(rng, self.protocol)[k]
        out = pairs.make_pair(self._image(pos), params, self.protocol)
        out.update(h_prev=np.eye(3), h_mask=np.float32(1.0), image_id=image_id,
                   index=np.int64(index * self.protocol.samples_per_image + k))
        return out

    def epoch_order(self, epoch: int) -> np.ndarray:
        """Sample order of ``epoch`` (epoch 0: ``self.order``; later epochs: a new seeded
        permutation when shuffling)."""
        if epoch == 0 or not self.shuffle:
            return self.order
        return np.random.default_rng([self.seed, int(epoch), 0x5348]).permutation(self.num_samples)

    def batch(self, i: int, epoch: int = 0, fresh: bool = False):
        """Batch ``i`` of ``epoch`` as ``(x, y, w)`` NumPy arrays (see the module docstring).

        ``fresh``: draw new squares and perturbations every epoch instead of repeating epoch 0's
        samples (on-the-fly training on an effectively unlimited set of pairs)."""
        if not 0 <= i < len(self):
            raise IndexError(f"batch {i} out of range [0, {len(self)}).")
        ids = self.epoch_order(epoch)[i * self.batch_size:(i + 1) * self.batch_size]
        return numpy_model_batch([self.sample(s, epoch if fresh else 0) for s in ids])


def _image_entries(images) -> list:
    """``[(image_index, image_id, payload)]`` from the accepted ``images`` forms."""
    if isinstance(images, str) and images == "bundled":
        return [(i, image_id, p) for i, (image_id, p) in enumerate(bundled_image_files())]
    if isinstance(images, (str, os.PathLike)):
        listing = scan_image_folder(os.fspath(images))
        return [(i, listing.image_id(p), p) for i, p in enumerate(listing.files)]
    out = []
    for i, item in enumerate(images):
        if isinstance(item, tuple) and len(item) == 2:
            out.append((i, str(item[0]), item[1]))
        else:
            out.append((i, os.fspath(item), os.fspath(item)))
    return out


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
                 use_multiprocessing: bool = False, max_queue_size: int = 10):
        super().__init__(workers=workers, use_multiprocessing=use_multiprocessing,
                         max_queue_size=max_queue_size)
        self.batches = PairBatches(images, batch_size, samples_per_image=samples_per_image,
                                   seed=seed, shuffle=shuffle, drop_remainder=drop_remainder,
                                   max_images=max_images, cache_images=cache_images)
        self.mapper = mapper

    def __len__(self) -> int:
        return len(self.batches)

    def __getitem__(self, index: int):
        batch = self.batches.batch(index)
        return self.mapper(*batch) if self.mapper is not None else batch


def _generate_samples(batches, start, stop):
    _limit_threads_in_worker()
    return numpy_model_batch([batches.sample(s) for s in range(start, stop)])


def materialize(batches: "PairBatches", workers: int = 0, chunk: int = 256) -> tuple:
    """Every sample of ``batches`` (epoch 0, stored order: sample ``s`` at row ``s``) as one
    ``(x, y, w)`` tuple of NumPy arrays, generated in ``workers`` processes (0: this process).
    The fixed set of ``len(images) * samples_per_image`` pairs then trains from memory
    (:class:`ArrayStream`; float32, 192 KB a pair)."""
    import functools

    bounds = [(a, min(a + chunk, batches.num_samples))
              for a in range(0, batches.num_samples, chunk)]
    if workers > 0:
        import multiprocessing

        with multiprocessing.get_context("forkserver").Pool(workers) as pool:
            parts = pool.starmap(functools.partial(_generate_samples, batches), bounds)
    else:
        parts = [_generate_samples(batches, a, b) for a, b in bounds]
    return tuple({k: np.concatenate([p[j][k] for p in parts]) for k in parts[0][j]}
                 for j in range(3))


class ArrayStream(keras.utils.PyDataset):
    """:class:`PairStream` without ``fresh_pairs``, served from :func:`materialize`'s arrays in
    this process: item ``i`` is the same batch (same samples, same order) as
    ``PairStream(...)[i]``, without generating anything after the start."""

    def __init__(self, arrays, batches: "PairBatches", *, start_step: int = 0, mapper=None):
        super().__init__()
        if len(arrays[0]["patch_a"]) != batches.num_samples:
            raise ValueError(f"arrays hold {len(arrays[0]['patch_a'])} samples; batches has "
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
        batch = tuple({k: v[ids] for k, v in part.items()} for part in self.arrays)
        return self.mapper(*batch) if self.mapper is not None else batch


_THREADS_LIMITED = False


def _limit_threads_in_worker():
    """In a generator worker process, run OpenCV single-threaded, so that N workers do not each
    start one OpenCV thread per core (on a 16-core host one process generated a batch in 130 ms
    with 1 thread and 137 ms with 16: the workers gain nothing from OpenCV's threads)."""
    global _THREADS_LIMITED
    if not _THREADS_LIMITED:
        import multiprocessing

        import cv2

        if multiprocessing.current_process().name != "MainProcess":
            cv2.setNumThreads(1)
        _THREADS_LIMITED = True


class PairStream(keras.utils.PyDataset):
    """Endless training stream of :class:`PairBatches` for ``model.fit(..., steps_per_epoch=k)``.

    Item ``i`` is global step ``start_step + i``: batch ``step % n`` of data epoch ``step // n``
    (``n = len(batches)``), so a resumed run given ``start_step`` sees exactly the batches an
    uninterrupted run would have seen. Every data epoch is a new seeded permutation; with
    ``fresh_pairs`` it also draws new squares and perturbations (epoch 0 is make_dataset's set),
    else it repeats the fixed set of ``len(images) * samples_per_image`` pairs, like training on
    the TFRecords. ``mapper(x, y, w)`` maps batches onto the model's outputs (NumPy). With
    ``workers > 1`` and ``use_multiprocessing`` the pairs are generated in worker processes.
    """

    def __init__(self, images, batch_size: int = 64, *, samples_per_image: int = 3, seed: int = 0,
                 start_step: int = 0, fresh_pairs: bool = False, mapper=None, max_images: int = 0,
                 workers: int = 1, use_multiprocessing: bool = False, max_queue_size: int = 10):
        super().__init__(workers=workers, use_multiprocessing=use_multiprocessing,
                         max_queue_size=max_queue_size)
        self.batches = PairBatches(images, batch_size, samples_per_image=samples_per_image,
                                   seed=seed, shuffle=True, drop_remainder=True,
                                   max_images=max_images, cache_images=True)
        self.start_step, self.fresh_pairs, self.mapper = int(start_step), bool(fresh_pairs), mapper

    @property
    def num_batches(self):
        return None  # endless: Keras keeps counting indices across epochs

    def __getitem__(self, index: int):
        _limit_threads_in_worker()
        epoch, i = divmod(self.start_step + int(index), len(self.batches))
        batch = self.batches.batch(i, epoch, fresh=self.fresh_pairs)
        return self.mapper(*batch) if self.mapper is not None else batch
