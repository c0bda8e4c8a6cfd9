r"""Keras ``PyDataset``\ s of generated pairs (NumPy/OpenCV only, no TensorFlow): ``model.fit`` on
pairs made on the fly from images (:class:`PairSequence`, :class:`PairStream`) or served from
arrays made once in memory (:class:`ArraySequence`, :class:`ArrayStream`).

Batches are ``(x, y, w)`` NumPy arrays with the structure of
:func:`stnh_tf.data.tfrecords.load_split`'s (TFRecords); the pairs are those of
:class:`stnh_tf.data.batches.PairBatches` (the same samples as ``data_prep.make_dataset``), so
training can run under the JAX backend without TFRecords.

Which one: :class:`PairSequence` for one pass over a fixed set (indexable, shuffled per seed);
:class:`PairStream` for an endless training stream positioned at a step (worker processes,
``fresh_pairs``); :class:`ArrayStream` for the same stream from pairs held in memory;
:class:`ArraySequence` for arrays served in stored order (validation).
"""

from __future__ import annotations

import keras

from stnh_tf.data.batches import PairBatches, generator_pool, model_batch, step_batch_async
from stnh_tf.data.pools import pool_result, stop_pool


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
    ``PairStream(...)[i]``, without generating anything after the start. A share of the batches
    (``batches.set_share``) serves that share's rows of every batch."""

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
        ids = self._order[1][i * size:(i + 1) * size][self.batches.share_slice()]
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

    ``label_fraction``, ``unlabeled_images`` and ``drop_unlabeled`` choose the samples without
    ground truth (``h_mask`` 0, ``h_bar`` zeroed), as in :class:`PairBatches`.
    """

    def __init__(self, images, batch_size: int = 64, *, samples_per_image: int = 3, seed: int = 0,
                 start_step: int = 0, fresh_pairs: bool = False, mapper=None, max_images: int = 0,
                 workers: int = 0, prefetch: int = 0, photometric: bool = False,
                 label_fraction: float = 1.0, unlabeled_images=None,
                 drop_unlabeled: bool = False):
        super().__init__()
        if workers < 0 or prefetch < 0:
            raise ValueError(f"workers and prefetch must be >= 0; received {workers}, {prefetch}.")
        self.batches = PairBatches(images, batch_size, samples_per_image=samples_per_image,
                                   seed=seed, shuffle=True, drop_remainder=True,
                                   max_images=max_images, cache_images=True,
                                   photometric=photometric, label_fraction=label_fraction,
                                   unlabeled_images=unlabeled_images,
                                   drop_unlabeled=drop_unlabeled)
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
        return pool_result(self._pool, self._pending.pop(step))

    def close(self, timeout: float = 60.0):
        """Stop the worker processes (a later item starts new ones).

        The batches in flight are let finish first; only if they take longer than ``timeout``
        seconds are the workers killed (:func:`~stnh_tf.data.pools.stop_pool`)."""
        pool, self._pool, self._pending = self._pool, None, {}
        if pool is None:
            return
        submitted, self._submitted = self._submitted, []
        stop_pool(pool, submitted, timeout)

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown
            pass

    def __getstate__(self):
        state = self.__dict__.copy()
        state.update(_pool=None, _pending={}, _next=0, _submitted=[])
        return state
