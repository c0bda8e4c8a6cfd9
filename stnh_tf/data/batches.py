r"""Stage-1 training batches generated on the fly from images, and their worker processes.

NumPy / OpenCV only (no TensorFlow, no Keras): generator worker processes import this module and
never start a deep-learning backend. :mod:`stnh_tf.data.pair_datasets` wraps these pieces in Keras
``PyDataset``\ s (``PairSequence``, ``PairStream``, ``ArrayStream``, ``ArraySequence``).

Batches are ``(x, y, w)`` with :func:`stnh_tf.data.tfrecords.load_split`'s structure and values, or
the compact form of :func:`stack_samples` (uint8 patches: what workers send back and what
:func:`materialize` keeps in memory, 48 KB a pair), which :func:`model_batch` turns into floats.
"""

from __future__ import annotations

import logging
import os
import signal

import numpy as np

from stnh_tf import pixels
from stnh_tf.data import labels, pairs, sources
from stnh_tf.data.folder_counts import FolderCounts
from stnh_tf.data.pools import main_not_rerun, mark_workers, pool_result, stop_pool
from stnh_tf.data.bundled_photos import bundled_image_files
from stnh_tf.data.sources import ImageDecodeError, SourceError, scan_image_folders

_log = logging.getLogger(__name__)


def numpy_model_batch(samples: list):
    """Sample dicts (:func:`pairs.make_pair` + ``h_mask``) -> ``(x, y, w)`` of NumPy arrays,
    the same structure and values as :func:`to_model_batch`."""
    return model_batch(stack_samples(samples))


def stack_samples(samples: list, context: bool = False) -> dict:
    """Sample dicts -> the compact batch :func:`model_batch` takes: ``patch_a``, ``patch_b``,
    ``patch_a_t`` uint8 ``[B, 128, 128]``, ``h_bar`` float32 ``[B, 8]``, ``h_mask`` float32
    ``[B]`` (a quarter of the float batch's bytes: what worker processes send back). With
    ``context`` also ``context_a`` uint8 ``[B, 192, 192]`` and ``h_ba`` float64 ``[B, 3, 3]``,
    what later stages' pairs are made from (:func:`stnh_tf.hierarchy.next_stage_arrays`)."""
    out = {n: np.stack([s[n] for s in samples]) for n in ("patch_a", "patch_b", "patch_a_t")}
    out["h_bar"] = np.stack([s["h_bar"] for s in samples]).astype(np.float32)
    out["h_mask"] = np.array([s.get("h_mask", 1.0) for s in samples], np.float32)
    if context:
        out["context_a"] = np.stack([s["context_a"] for s in samples])
        out["h_ba"] = np.stack([s["h_ba"] for s in samples]).astype(np.float64)
    return out


def model_batch(stacked: dict):
    """:func:`stack_samples`'s compact batch -> ``(x, y, w)`` float32 (see the module docstring)."""
    def unit(name):
        return pixels.to_unit(stacked[name][..., None])

    h_mask = stacked["h_mask"]
    x = {"patch_a": unit("patch_a"), "patch_b": unit("patch_b")}
    y = {"h_bar": stacked["h_bar"], "patch_a_warp": unit("patch_a_t")}
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
        a list of folders (:func:`sources.scan_image_folders`); a list of image paths; or a list
        of ``(image_id, path | encoded bytes | array)``.
      batch_size: samples per batch.
      samples_per_image: squares per image (paper: 3).
      seed: as ``make_dataset --seed``.
      shuffle: permute samples (seeded); else stored order.
      drop_remainder: drop the last partial batch.
      max_images: use only the first N images (0 = all), as ``make_dataset --max_images``.
      cache_images: decode every image once at construction (unusable ones are dropped and
        listed in ``self.skipped`` with reasons); else decode on demand (errors then raise).
      photometric: change patch_b photometrically (:class:`pairs.PhotometricChange`, not the
        paper's); the geometry of every sample is the same as without.
      label_fraction: the share of ``images``' samples that keep their ground truth
        (:mod:`stnh_tf.data.labels`, drawn from ``seed`` and the sample's ``index``); the
        others have ``h_mask`` 0 and ``h_bar`` zeroed (1: every sample labeled).
      unlabeled_images: images in any form ``images`` takes (None: none) whose samples are
        added to the set, ``samples_per_image`` each, always unlabeled (``h_mask`` 0, ``h_bar``
        zeroed). They come after ``images``' samples in stored order; their image indices
        continue after ``images``' largest (so ``images``' samples are unchanged, and every
        ``index`` unique); an image path also in ``images`` is left out here.
      drop_unlabeled: the set is the labeled samples alone (stored order kept; sample ``s`` is
        the ``s``-th labeled one): ``label_fraction`` F then trains on F of the data.
    """

    def __init__(self, images="bundled", batch_size: int = 64, *, samples_per_image: int = 3,
                 seed: int = 0, shuffle: bool = True, drop_remainder: bool = True,
                 max_images: int = 0, cache_images: bool = True, photometric: bool = False,
                 label_fraction: float = 1.0, unlabeled_images=None,
                 drop_unlabeled: bool = False):
        self.protocol = pairs.Protocol(
            samples_per_image=samples_per_image,
            photometric=pairs.PhotometricChange() if photometric else None)
        self.batch_size, self.seed = int(batch_size), int(seed)
        self.shuffle, self.drop_remainder = shuffle, drop_remainder
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1; received {batch_size}.")
        entries, listing = _image_entries(images, max_images)
        self.unlabeled_from = max((e[0] for e in entries), default=-1) + 1
        if unlabeled_images is not None:
            entries = entries + _unlabeled_entries(unlabeled_images, entries,
                                                   self.unlabeled_from)
        self.label_fraction = float(label_fraction)
        labels.threshold(self.label_fraction)  # raises for a fraction outside [0, 1]
        self.skipped = list(listing.unreadable) if listing else []  # (links outside a folder)
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
            if listing is not None:
                _log.info("%s", FolderCounts.of(len(entries), [r for _, r in self.skipped],
                                                listing, max_images).line())
        if not entries:
            raise SourceError(f"no usable images in {images!r}.")
        self.entries = entries
        spi = samples_per_image
        indices = (np.repeat([e[0] for e in entries], spi) * spi
                   + np.tile(np.arange(spi), len(entries)))
        self.labeled = ((indices < self.unlabeled_from * spi)
                        & labels.labeled(self.seed, indices, self.label_fraction))
        # Stored-order sample numbers of the set (None: all of them).
        self.sample_ids = np.flatnonzero(self.labeled) if drop_unlabeled else None
        self.num_samples = len(entries) * spi if self.sample_ids is None else len(self.sample_ids)
        if drop_remainder and self.num_samples < self.batch_size:
            kept = " labeled" if drop_unlabeled else ""
            raise ValueError(f"{self.num_samples}{kept} samples, fewer than one batch of "
                             f"{batch_size}.")
        self.order = (np.random.default_rng([self.seed, 0, 0x5348]).permutation(self.num_samples)
                      if shuffle else np.arange(self.num_samples))
        self._params_cache, self._params_epoch = {}, None
        self.share = (0, 1)  # (index, count): set_share

    def set_share(self, index: int, count: int) -> "PairBatches":
        """Make every batch the ``index``-th of ``count`` equal row blocks of the global batch of
        ``batch_size`` (process ``index`` of ``count`` in data-parallel training:
        :mod:`stnh_tf.training.distribute`). Batch indices, epochs and the sample order stay the
        global stream's, so the ``count`` shares of batch ``i`` are together batch ``i`` of the
        whole stream, each pair generated by one share alone. ``(0, 1)``: the whole batch
        (the default). Returns ``self``.

        Raises:
          ValueError: ``index`` outside ``[0, count)``, ``batch_size`` not a multiple of
            ``count``, or ``count`` > 1 without ``drop_remainder``.
        """
        if not 0 <= index < count or self.batch_size % count or (count > 1
                                                                and not self.drop_remainder):
            raise ValueError(f"a share (index {index} of {count}) needs 0 <= index < count, "
                             f"batch_size ({self.batch_size}) a multiple of count, and "
                             "drop_remainder.")
        self.share = (int(index), int(count))
        return self

    def share_slice(self) -> slice:
        """This share's rows of a global batch (:meth:`set_share`)."""
        index, count = self.share
        part = self.batch_size // count
        return slice(index * part, (index + 1) * part)

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
        ``default_rng([seed, image_index, epoch])``); epoch 0 is make_dataset's sample. An
        unlabeled sample (``label_fraction``, ``unlabeled_images``) has ``h_mask`` 0 and
        ``h_bar`` zeros: its ``H_bar`` never leaves this method."""
        g = int(s) if self.sample_ids is None else int(self.sample_ids[s])
        pos, k = divmod(g, self.protocol.samples_per_image)
        index, image_id, _ = self.entries[pos]
        out = pairs.make_pair(self._image(pos), self._params(pos, epoch)[k], self.protocol)
        out.update(h_prev=np.eye(3), h_mask=np.float32(1.0), image_id=image_id,
                   index=np.int64(index * self.protocol.samples_per_image + k))
        if not self.labeled[g]:
            out.update(h_mask=np.float32(0.0), h_bar=np.zeros_like(out["h_bar"]))
        return out

    def _params(self, pos: int, epoch: int) -> list:
        """The ``samples_per_image`` parameter draws of image ``pos`` in ``epoch``, memoized for
        the current epoch (drawing them all for every sample costs O(samples_per_image) a
        sample)."""
        if self._params_epoch != epoch:
            self._params_cache, self._params_epoch = {}, epoch
        params = self._params_cache.get(pos)
        if params is None:
            index = self.entries[pos][0]
            rng = (pairs.image_rng(self.seed, index) if epoch == 0 else
                   np.random.default_rng([self.seed, int(index), int(epoch)]))
            params = self._params_cache[pos] = pairs.draw_params(rng, self.protocol)
        return params

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
        return model_batch(self.stacked_batch(i, epoch, fresh))

    def stacked_batch(self, i: int, epoch: int = 0, fresh: bool = False) -> dict:
        """:meth:`batch` in :func:`stack_samples`'s compact form (uint8 patches)."""
        if not 0 <= i < len(self):
            raise IndexError(f"batch {i} out of range [0, {len(self)}).")
        ids = self.epoch_order(epoch)[i * self.batch_size:(i + 1) * self.batch_size]
        ids = ids[self.share_slice()]  # this share's rows of the global batch (set_share)
        return stack_samples([self.sample(s, epoch if fresh else 0) for s in ids])

    def step_batch(self, step: int, fresh: bool = False) -> dict:
        """Global training step ``step`` of an endless stream: compact batch ``step % len(self)``
        of data epoch ``step // len(self)``."""
        epoch, i = divmod(int(step), len(self))
        return self.stacked_batch(i, epoch, fresh)


def _unlabeled_entries(images, labeled_entries: list, first_index: int) -> list:
    """:func:`_image_entries` of ``images`` with image indices from ``first_index`` on, ids
    prefixed ``unlabeled:``, less the image paths ``labeled_entries`` already hold.

    Raises:
      SourceError: ``images`` lists no image, or none that ``labeled_entries`` lacks.
    """
    entries = _image_entries(images)[0]
    if not entries:
        raise SourceError(f"no images in the unlabeled image source {images!r}.")

    def path(payload):
        return os.path.realpath(payload) if isinstance(payload, (str, os.PathLike)) else None

    taken = {path(p) for _, _, p in labeled_entries} - {None}
    left = [(first_index + i, f"unlabeled:{image_id}", p) for i, image_id, p in entries
            if path(p) not in taken]
    if not left:  # (the run's config would name a source that added nothing)
        raise SourceError(f"every image of the unlabeled image source {images!r} is among the "
                          "labeled images: it adds no unlabeled pair.")
    return left


def _image_entries(images, max_images: int = 0) -> tuple:
    """``([(image_index, image_id, payload)], listing)`` from the accepted ``images`` forms, the
    first ``max_images`` (0: all); ``listing``: the folders' :class:`sources.FolderListing`
    (None for other forms)."""
    if isinstance(images, str) and images == "bundled":
        out = [(i, image_id, p) for i, (image_id, p) in enumerate(bundled_image_files())]
        return (out[:max_images] if max_images > 0 else out), None
    one_folder = isinstance(images, (str, os.PathLike))  # (SourceError if not a folder)
    images = [os.fspath(images)] if one_folder else list(images)
    if one_folder or images and all(isinstance(x, (str, os.PathLike)) and os.path.isdir(x)
                                    for x in images):
        listing = scan_image_folders([os.fspath(x) for x in images], max_images)
        return [(i, listing.image_id(p), p) for i, p in enumerate(listing.files)], listing
    out = []
    for i, item in enumerate(images):
        if isinstance(item, tuple) and len(item) == 2:
            out.append((i, str(item[0]), item[1]))
        else:
            out.append((i, os.fspath(item), os.fspath(item)))
    return (out[:max_images] if max_images > 0 else out), None


# ------------------------------------------------------------------------------------------------
# Generator worker processes
# ------------------------------------------------------------------------------------------------
_WORKER_BATCHES = None


def _init_worker(batches: PairBatches):
    """Pool initializer: keep this process's copy of ``batches`` (sent once per worker, not per
    task) and run OpenCV single-threaded, so N workers do not each start one OpenCV thread per
    core (the workers gain nothing from OpenCV's threads: BENCHMARKS.md, "CPU-budget
    single-stage models trained on the H100"). Ctrl-C, which a terminal sends to every process
    of the group, is ignored: the parent handles it (a training run stops after its step and
    saves it) and ends the pool; interrupted, the workers printed tracebacks and left the
    parent waiting a minute for their batches."""
    global _WORKER_BATCHES
    import cv2

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    cv2.setNumThreads(1)
    _WORKER_BATCHES = batches


def _samples(batches: PairBatches, task) -> dict:
    start, stop, context = task
    return stack_samples([batches.sample(s) for s in range(start, stop)], context)


def _worker_samples(task) -> dict:
    return _samples(_WORKER_BATCHES, task)


def _worker_step(step: int, fresh: bool) -> dict:
    return _WORKER_BATCHES.step_batch(step, fresh)


def generator_pool(batches: PairBatches, workers: int):
    """A pool of ``workers`` processes, each holding a copy of ``batches``.

    Processes come from a ``forkserver`` (never a fork of this process, whose backend may already
    run threads) and import only NumPy, OpenCV and this module, also when the caller is a binary
    whose ``__main__`` imports a backend. Stop it with :func:`~stnh_tf.data.pools.stop_pool`."""
    import multiprocessing

    if workers < 1:
        raise ValueError(f"workers must be >= 1; received {workers}.")
    with main_not_rerun():  # Pool starts all its processes before returning
        return mark_workers(multiprocessing.get_context("forkserver").Pool(
            workers, initializer=_init_worker, initargs=(batches,)))


def step_batch_async(pool, step: int, fresh: bool = False):
    """Ask ``pool`` (:func:`generator_pool`) for :meth:`PairBatches.step_batch`; returns an
    ``AsyncResult`` whose ``get()`` is the compact batch."""
    return pool.apply_async(_worker_step, (int(step), bool(fresh)))


def stored_arrays(batches: PairBatches, workers: int = 0) -> dict:
    """Every sample of ``batches`` (epoch 0, stored order), made in memory without TensorFlow, in
    the form :func:`stnh_tf.data.tfrecords.load_arrays` reads back from the TFRecords that
    ``make_dataset`` writes of the same images, seed and protocol (for evaluation; 260 KB a pair).

    Returns:
      ``patch_a``, ``patch_b``, ``patch_a_t``: float32 ``[N, 128, 128, 1]`` in [0, 1];
      ``context_a`` uint8 ``[N, 192, 192]``; ``h_bar`` float32 ``[N, 8]``; ``h_ba`` float64
      ``[N, 3, 3]``, rounded to float32 as the records store it; ``h_prev`` the identity, float64
      ``[N, 3, 3]``; ``h_mask`` float32 ``[N]``.
    """
    out = materialize(batches, workers, context=True)
    for name in ("patch_a", "patch_b", "patch_a_t"):
        out[name] = pixels.to_unit(out[name])[..., None]
    out["h_ba"] = out["h_ba"].astype(np.float32).astype(np.float64)
    out["h_prev"] = np.broadcast_to(np.eye(3), out["h_ba"].shape).copy()
    return out


def materialize(batches: PairBatches, workers: int = 0, chunk: int = 256,
                context: bool = False) -> dict:
    """Every sample of ``batches`` (epoch 0, stored order: sample ``s`` at row ``s``) in
    :func:`stack_samples`'s compact form (uint8 patches, 48 KB a pair; with ``context`` also
    ``context_a`` and ``h_ba``, 84 KB), generated in ``workers`` processes (0: this process)
    straight into preallocated arrays. The fixed set of ``len(images) * samples_per_image``
    pairs then trains from memory (:class:`stnh_tf.data.pair_datasets.ArrayStream`)."""
    n = batches.num_samples
    for _, arrays in materialize_slices(batches, workers, max(n, 1), chunk=chunk,
                                        context=context):
        return arrays


def materialize_slices(batches: PairBatches, workers: int = 0, slice_size: int = 8192,
                       chunk: int = 256, context: bool = False):
    """:func:`materialize`'s samples as consecutive slices: yields ``(start, arrays)`` with
    ``arrays`` the compact form of samples ``start .. start + len(arrays["patch_b"])``, each slice
    ``slice_size`` samples (rounded up to a multiple of ``chunk``; the last may be shorter), so a
    caller that keeps only part of each (e.g. the stage-k re-making, which drops ``context_a``)
    never holds the whole set with context. One pool of ``workers`` processes serves every slice
    and works at most ``2 * workers`` chunks ahead of the chunk being read, so a slow consumer
    does not make the pending results pile up in memory. The pool stops when the generator ends
    or is closed: a caller that stops early closes it (``contextlib.closing``).

    Raises:
      ValueError: ``slice_size`` or ``chunk`` below 1.
    """
    if slice_size < 1 or chunk < 1:
        raise ValueError(f"slice_size and chunk must be >= 1; received {slice_size}, {chunk}.")
    n = batches.num_samples
    per_slice = -(-slice_size // chunk) * chunk
    tasks = [(a, min(a + chunk, n), context) for a in range(0, n, chunk)]
    parts = _parts(batches, workers, tasks)
    out, start = None, 0
    try:
        for (a, b, _), part in zip(tasks, parts):
            if out is None:
                out = {k: np.empty((min(per_slice, n - start),) + v.shape[1:], v.dtype)
                       for k, v in part.items()}
            for k, v in part.items():
                out[k][a - start:b - start] = v
            if b - start == len(out["patch_b"]):
                yield start, out
                out, start = None, b
    finally:
        parts.close()  # the pool's processes stop here, not when the generator is collected


def _parts(batches: PairBatches, workers: int, tasks: list):
    """:func:`_samples` of each task, in order: in this process, or in a :func:`generator_pool`
    with at most ``2 * workers`` tasks pending (``Pool.imap`` would queue every finished result,
    however far ahead of the reader)."""
    import collections

    if workers <= 0:
        for task in tasks:
            yield _samples(batches, task)
        return
    pool = generator_pool(batches, workers)
    pending, todo = collections.deque(), iter(tasks)
    try:
        for task in todo:
            pending.append(pool.apply_async(_worker_samples, (task,)))
            if len(pending) >= 2 * workers:
                break
        while pending:
            part = pool_result(pool, pending[0])
            pending.popleft()
            task = next(todo, None)
            if task is not None:
                pending.append(pool.apply_async(_worker_samples, (task,)))
            yield part
    finally:  # closed early, or a worker raised: the tasks in flight finish before the pool stops
        stop_pool(pool, pending)
