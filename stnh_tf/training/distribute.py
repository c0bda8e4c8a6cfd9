"""Data-parallel training on several processes (local workers or hosts): ``keras.distribution``
on the JAX backend, chosen by measurement (docs/scale.md: ``tf.distribute``'s
``MultiWorkerMirroredStrategy`` fails inside Keras 3.15's ``model.fit``).

A run with ``strategy="data_parallel"`` (JAX backend) trains under
``keras.distribution.DataParallel`` over every device of every process. With
``num_processes`` N > 1, N copies of the same command, differing only in ``process_id``
(0..N-1), join at ``coordinator_address`` (``host:port`` of process 0, the chief) through
``keras.distribution.initialize`` (``jax.distributed``). The contract:

* **Batch.** ``batch_size`` is the global batch; process k feeds rows
  ``[k b, (k + 1) b)`` of every global batch, ``b = batch_size / N`` (:func:`share_rows`), and the
  devices of all processes compute one step on the ``batch_size`` rows together (the gradient is
  the mean over the global batch, masks included: the loss is reduced over the global array).
* **Data shares** (:func:`train_stream`). Generated pairs (``image_dir``): each process generates
  only its rows of each global batch (the single-process stream's permutation and per-pair
  seeds), so the processes together see the pairs of a single-process run, in its order, each
  once per data epoch. TFRecords (``data_dir``): by file when the train split's shard count is a
  multiple of N (process k reads shards k, k + N, ... with its own seeded shuffle:
  :func:`stnh_tf.data.tfrecords.share_policy`), else by data (every process reads the
  single-process stream and parses only its rows of each batch). A ``stream_fn`` given to
  :func:`~stnh_tf.training.loop.train`: its global batches, each process keeping its rows.
* **Writes.** Only the chief (process 0) writes ``model_dir`` (lock, ``config.json``,
  checkpoints, TensorBoard logs, ``model.keras``, ``result.json``); the other processes write
  nothing there, and read no checkpoint: the chief loads the checkpoint (or ``init_from``) and
  :func:`load_state` sends every model and optimizer variable and the step to the others, so
  ``model_dir`` need not be on a shared filesystem.
* **Logs.** Every Python log line of process k of N starts with ``[worker k/N]``
  (:func:`stnh_tf.training.worker_log.prefix_logs`).
* **A lost process.** Each process beats every second (:mod:`stnh_tf.training.watchdog`); when
  one is killed, crashes or is cut off, each of the others logs one line 20 s after its last
  beat, naming it, the chief's last checkpoint and the command that resumes, and ends with exit
  status 75. The chief's death ends the others within a second, by JAX (its distributed service
  is gone), before any line.
* **Resume.** Restarting all of them with the same command continues from the chief's last
  checkpoint with the same final weights.
* **Stopping.** A non-finite loss stops every process at the same step (the loss is global);
  the time limit is read on the chief's clock and sent to all at each epoch end
  (:class:`SyncStop`).
"""

from __future__ import annotations

import contextlib
import dataclasses

import keras
import numpy as np

from stnh_tf.training import watchdog, worker_log
from stnh_tf.training.config import TrainConfig

CHIEF = watchdog.CHIEF  # 0
"""The process that writes the run's folder and whose checkpoint, clock and start decide."""


@dataclasses.dataclass(frozen=True)
class Cluster:
    """This process's place in a run: ``num_processes`` processes, this one ``process_id``;
    ``data_parallel``: under ``keras.distribution.DataParallel`` (else the run's own
    strategy)."""

    num_processes: int = 1
    process_id: int = 0
    data_parallel: bool = False

    @property
    def is_chief(self) -> bool:
        """Whether this process writes ``model_dir`` (process :data:`CHIEF`)."""
        return self.process_id == CHIEF

    @property
    def multi(self) -> bool:
        """Whether the run has more than one process."""
        return self.num_processes > 1

    @property
    def share(self) -> tuple:
        """``(index, count)``: this process's share of every global batch."""
        return self.process_id, self.num_processes


def cluster_of(cfg: TrainConfig) -> Cluster:
    """The :class:`Cluster` that ``cfg``'s fields describe (no check; :meth:`TrainConfig.validate`
    checks them)."""
    return Cluster(int(cfg.num_processes), int(cfg.process_id), cfg.strategy == "data_parallel")


def share_rows(rows: int, index: int, count: int, multiple: int | None = None) -> slice:
    """Process ``index`` of ``count``'s rows of a batch of ``rows``: the ``index``-th of ``count``
    equal blocks of its first ``rows // multiple * multiple`` rows (``multiple``, default
    ``count``: the global device count, over which the blocks' union is split evenly; rows past
    it are dropped: at most ``multiple - 1``, only in a partial last validation batch).

    >>> share_rows(8, 1, 2), share_rows(5, 1, 2, multiple=2)
    (slice(4, 8, None), slice(2, 4, None))

    Raises:
      ValueError: ``count`` < 1, ``index`` outside ``[0, count)``, or ``multiple`` not a
        multiple of ``count``.
    """
    multiple = multiple or count
    if count < 1 or not 0 <= index < count or multiple < 1 or multiple % count:
        raise ValueError(f"need 0 <= index < count and multiple a multiple of count; received "
                         f"index={index}, count={count}, multiple={multiple}.")
    part = rows // multiple * multiple // count
    return slice(index * part, (index + 1) * part)


def check(cfg: TrainConfig) -> None:
    """The backend's part of ``cfg``'s distribution (run before ``model_dir`` is touched):
    ``strategy="data_parallel"`` needs the JAX backend.

    Raises:
      ValueError: naming the backend and what to do.
    """
    if cfg.strategy == "data_parallel" and keras.backend.backend() != "jax":
        raise ValueError(
            f"strategy='data_parallel' is keras.distribution on the JAX backend; this is "
            f"{keras.backend.backend()!r}: run with KERAS_BACKEND=jax (TensorFlow's "
            "MultiWorkerMirroredStrategy fails inside Keras 3's model.fit: docs/scale.md).")


_JOINED = None  # (coordinator_address, num_processes, process_id) of keras.distribution.initialize


def join(cfg: TrainConfig) -> Cluster:
    """This process's :class:`Cluster`; with ``num_processes`` > 1, first joins the others at
    ``coordinator_address`` (``keras.distribution.initialize``; once a process: before any JAX
    computation, and a later call must name the same cluster). Returns at once for other
    strategies. On joining, this process's log lines get their ``[worker k/N]`` prefix
    (:func:`stnh_tf.training.worker_log.prefix_logs`) and its watchdog starts
    (:func:`stnh_tf.training.watchdog.watch`: a lost process ends the others with one line saying
    how to resume).

    Raises:
      ValueError: ``cfg`` is not valid (:meth:`TrainConfig.validate`), another backend
        (:func:`check`), or JAX sees another process count or id than ``cfg`` names.
      RuntimeError: this process joined another cluster before.
    """
    global _JOINED
    cluster = cluster_of(cfg)
    if not cluster.data_parallel:
        return cluster
    cfg.validate()
    check(cfg)
    import jax

    if cluster.multi:
        key = (cfg.coordinator_address, cluster.num_processes, cluster.process_id)
        if _JOINED is None:
            worker_log.prefix_logs(cluster.num_processes, cluster.process_id)
            keras.distribution.initialize(cfg.coordinator_address, cluster.num_processes,
                                          cluster.process_id)
            _JOINED = key
            watchdog.watch(cluster.num_processes, cluster.process_id, cfg.model_dir)
        elif _JOINED != key:
            raise RuntimeError(f"this process joined the cluster {_JOINED} (coordinator, "
                               f"processes, id) before; it cannot join {key}.")
    if (jax.process_count(), jax.process_index()) != cluster.share[::-1]:
        raise ValueError(f"JAX runs {jax.process_count()} processes, this one "
                         f"{jax.process_index()}; the run names num_processes="
                         f"{cluster.num_processes}, process_id={cluster.process_id}.")
    return cluster


def activate(cluster: Cluster, batch_size: int) -> None:
    """Set ``keras.distribution.DataParallel`` over every device of every process as the global
    distribution (for :func:`deactivate` to unset), with each process feeding its own rows
    (``auto_shard_dataset=False``: :func:`train_stream` shards). No-op unless
    ``cluster.data_parallel``.

    Raises:
      ValueError: ``batch_size`` is not a multiple of the device count.
    """
    if not cluster.data_parallel:
        return
    devices = keras.distribution.list_devices()
    if batch_size % len(devices):
        raise ValueError(f"batch_size {batch_size} must be a multiple of the {len(devices)} "
                         f"devices of the {cluster.num_processes} processes (each computes an "
                         "equal part of the global batch).")
    keras.distribution.set_distribution(
        keras.distribution.DataParallel(devices=devices, auto_shard_dataset=False))


def deactivate(cluster: Cluster) -> None:
    """Unset what :func:`activate` set."""
    if cluster.data_parallel:
        keras.distribution.set_distribution(None)


@contextlib.contextmanager
def local_only(cluster: Cluster):
    """Run what one process does alone (the chief's saving) without the global distribution,
    restored after: Keras' saving makes throw-away variables (a reference ``Optimizer``), whose
    creation under a multi-process distribution is a collective that the other processes never
    join (measured: the chief's first checkpoint hung). No-op on a single process."""
    if not cluster.multi:
        yield
        return
    previous = keras.distribution.distribution()
    keras.distribution.set_distribution(None)
    try:
        yield
    finally:
        keras.distribution.set_distribution(previous)


def device_count(cluster: Cluster) -> int:
    """The devices the global batch is split over (1 unless ``cluster.data_parallel``)."""
    if not cluster.data_parallel:
        return 1
    return len(keras.distribution.list_devices())


def broadcast(cluster: Cluster, tree):
    """The chief's value of ``tree`` (NumPy arrays and scalars, nested), on every process (a
    collective: every process calls it at the same point). Single process: ``tree`` as NumPy."""
    if not cluster.multi:
        return tree
    from jax.experimental import multihost_utils

    return multihost_utils.broadcast_one_to_all(tree, is_source=cluster.is_chief)


def report_start(cluster: Cluster, ok: bool) -> None:
    """Tell every process whether the chief prepared ``model_dir`` (called by all processes after
    the chief's attempt; ``ok`` is read on the chief).

    Raises:
      RuntimeError: on the other processes, when the chief failed (its own error is its).
    """
    if not cluster.multi:
        return
    if not bool(broadcast(cluster, np.int32(ok))) and not cluster.is_chief:
        raise RuntimeError("the chief (process 0) could not start the run in model_dir: its "
                           "error says why.")


def _state_variables(model) -> list:
    """The model's variables, then its optimizer's (built here if it is not), each once."""
    if not model.optimizer.built:
        model.optimizer.build(model.trainable_variables)
    seen, out = set(), []
    for v in [*model.variables, *model.optimizer.variables]:
        if id(v) not in seen:
            seen.add(id(v))
            out.append(v)
    return out


def load_state(cluster: Cluster, model, load, build) -> int:
    """Load the run's start into ``model`` (compiled) on every process and return its step:
    ``load(model) -> step`` itself on a single process. On several, the chief alone reads (its
    checkpoint or ``init_from``: ``load``) into a model of its own, ``build()``, made outside the
    distribution (:func:`local_only`) and set to ``model``'s state first (so that what ``load``
    leaves alone, e.g. the weights ``init_from`` does not copy, stays the run's), and every model
    and optimizer variable (the optimizer built on every process) and the step are sent from it
    to all
    (:func:`broadcast`), which assign them together. The chief cannot assign into the
    distributed model alone: putting a value on a sharding that spans processes is a collective
    (JAX checks that every process gives the same value; measured: the chief's lone
    ``load_weights`` hung the resumed run).

    Raises:
      ValueError: the chief's model holds other variables than this one's.
    """
    if not cluster.multi:
        return int(load(model))
    targets = _state_variables(model)
    step, values = 0, [np.zeros(v.shape, keras.backend.standardize_dtype(v.dtype))
                       for v in targets]
    if cluster.is_chief:
        with local_only(cluster):
            local = build()
            own = _state_variables(local)
            shapes = ([tuple(v.shape) for v in own], [tuple(v.shape) for v in targets])
            if shapes[0] != shapes[1]:
                raise ValueError(f"build() makes the variables {shapes[0]}; the run's are "
                                 f"{shapes[1]}.")
            for v, w in zip(own, targets):  # the run's own start (initial weights, RNG states)
                v.assign(np.asarray(keras.ops.convert_to_numpy(w)))
            step = int(load(local))
            values = [np.asarray(keras.ops.convert_to_numpy(v)) for v in own]
    step, values = broadcast(cluster, (np.int64(step), values))
    for v, value in zip(targets, values):
        v.assign(np.asarray(value))
    return int(step)


def train_stream(cluster: Cluster, cfg: TrainConfig, start_step: int, stream_fn):
    """This process's training stream at ``start_step`` (see the module's data shares):
    ``stream_fn(cfg, "train", start_step)`` itself on a single process; on several, the built-in
    streams (:func:`stnh_tf.training.streams.generated_stream`,
    :func:`~stnh_tf.training.streams.training_stream`) made to produce this process's share
    alone, any other ``stream_fn``'s global batches cut to this process's rows
    (:func:`take_rows`)."""
    from stnh_tf.training import streams

    if not cluster.multi:
        return stream_fn(cfg, "train", start_step)
    if stream_fn is streams.generated_stream:
        stream = stream_fn(cfg, "train", start_step)
        stream.batches.set_share(*cluster.share)
        return stream
    if stream_fn is streams.training_stream:
        return stream_fn(cfg, "train", start_step, share=cluster.share)
    return take_rows(stream_fn(cfg, "train", start_step), cluster)


def validation_share(cluster: Cluster, dataset, steps):
    """``(dataset, steps)`` of this process's rows of the validation batches (:func:`take_rows`
    with the device count as ``multiple``: a partial last batch loses at most ``devices - 1``
    rows, and is left out if fewer rows than devices remain). Unchanged unless
    ``cluster.data_parallel``; ``steps`` None for a ``tf.data`` dataset (read to its end)."""
    if dataset is None or not cluster.data_parallel:
        return dataset, steps
    shared = take_rows(dataset, cluster, device_count(cluster))
    return shared, (None if hasattr(shared, "element_spec") else len(shared))


def take_rows(dataset, cluster: Cluster, multiple: int | None = None):
    """``dataset`` (a ``tf.data.Dataset`` or ``keras.utils.PyDataset`` of batches, any nesting
    of arrays with the batch first) with each batch cut to this process's rows
    (:func:`share_rows`; ``multiple`` defaults to the process count); batches left with no row
    are dropped."""
    multiple = multiple or cluster.num_processes
    index, count = cluster.share
    if hasattr(dataset, "element_spec"):  # tf.data
        import tensorflow as tf

        def rows(batch):
            n = tf.shape(tf.nest.flatten(batch)[0])[0]
            part = n // multiple * multiple // count
            return tf.nest.map_structure(lambda t: t[index * part:(index + 1) * part], batch)

        def nonempty(*batch):
            return tf.shape(tf.nest.flatten(batch)[0])[0] >= multiple

        cut = dataset.filter(nonempty).map(lambda *b: rows(b if len(b) > 1 else b[0]))
        return cut
    return RowShare(dataset, index, count, multiple)


def _rows_of(batch) -> int:
    return int(np.shape(keras.tree.flatten(batch)[0])[0])


class RowShare(keras.utils.PyDataset):
    """A ``PyDataset`` of batches cut to one process's rows (:func:`take_rows`). Its length is
    the wrapped one's, less a last batch with fewer rows than ``multiple``; ``close()`` is passed
    on."""

    def __init__(self, dataset, index: int, count: int, multiple: int):
        super().__init__()
        self.dataset, self.index, self.count, self.multiple = dataset, index, count, multiple
        n = dataset.num_batches
        if n and _rows_of(dataset[n - 1]) < multiple:
            n -= 1
        self._num_batches = n

    @property
    def num_batches(self):
        return self._num_batches

    def __len__(self):
        return self._num_batches

    def __getitem__(self, i):
        batch = self.dataset[i]
        cut = share_rows(_rows_of(batch), self.index, self.count, self.multiple)
        return keras.tree.map_structure(lambda a: a[cut], batch)

    def close(self):
        if hasattr(self.dataset, "close"):
            self.dataset.close()


class SyncStop(keras.callbacks.Callback):
    """At every epoch end, every process takes the chief's decision to stop (the time limit, read
    on the chief's clock); ``limit`` (a :class:`~stnh_tf.training.callbacks.TimeLimit`, or None)
    then records the step on every process. Runs after every other callback."""

    def __init__(self, cluster: Cluster, limit=None):
        super().__init__()
        self.cluster, self.limit = cluster, limit

    def on_epoch_end(self, epoch, logs=None):
        stop = bool(broadcast(self.cluster, np.int32(bool(self.model.stop_training))))
        self.model.stop_training = stop
        if self.limit is not None:
            step = int(keras.ops.convert_to_numpy(self.model.optimizer.iterations))
            self.limit.stopped_step = step if stop else None


class ChiefCallback(keras.callbacks.Callback):
    """``callback`` (the chief's checkpoint) with its epoch ends run under :func:`local_only`."""

    def __init__(self, cluster: Cluster, callback):
        super().__init__()
        self.cluster, self.callback = cluster, callback

    def set_model(self, model):
        super().set_model(model)
        self.callback.set_model(model)

    def set_params(self, params):
        super().set_params(params)
        self.callback.set_params(params)

    def on_epoch_end(self, epoch, logs=None):
        with local_only(self.cluster):
            self.callback.on_epoch_end(epoch, logs)


def chief_callback(cluster: Cluster, callback):
    """``callback`` for the chief alone, on several processes wrapped so that its epoch ends
    (where the checkpoint is saved) run under :func:`local_only`; itself on one."""
    return ChiefCallback(cluster, callback) if cluster.multi else callback


def callbacks(cluster: Cluster, limit=None) -> list:
    """The callbacks a run on ``cluster`` adds after its own: :class:`SyncStop` on several
    processes, none on one."""
    return [SyncStop(cluster, limit)] if cluster.multi else []
