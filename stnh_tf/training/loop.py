"""Stage and sequence training: one implementation of the paper's recipe for every model kind.

``train(config)`` builds the model named by the config (single STN-Homography stage, sequence
model, or the HomographyNet baseline), compiles it with the paper's optimizer and losses, and fits
it on the TFRecord dataset in ``config.data_dir`` with:

* SGD, momentum 0.9, batch 64; learning rate rising linearly 0 -> 0.05 over ``warmup_steps``, then
  cosine decay to 0 over the remaining ``train_steps - warmup_steps`` (Keras' ``CosineDecay`` with
  ``warmup_target``): the paper's 1,000 + 90,000 steps by default. ``lr_schedule="step"`` is
  DeTone et al.'s schedule instead (the learning rate divided by 10 after each third of the
  steps), which the binaries preset for ``--model=homographynet``
  (:data:`stnh_tf.training.presets.MODEL_DEFAULTS`).
* Atomic periodic checkpoints (model + optimizer + RNG state) every ``checkpoint_every`` steps; a
  killed run restarted with the same command resumes at the last checkpoint, repositions the data
  stream at that step, and follows the same schedule to the same final step. A run stopped by its
  time limit, a SIGTERM or a SIGINT (Ctrl-C) saves the checkpoint of the step it stopped at
  (between two periodic ones if need be) and resumes from there the same way.
* TensorBoard scalars against the global step (both loss terms, learning rate, validation MACE)
  and console progress, every ``log_every`` steps and at least ten times a run.
* A non-finite loss, or non-finite weights at an epoch end (never checkpointed), stops training
  with an error naming the step and the last good checkpoint.
* ``strategy="mirrored"`` runs under ``tf.distribute.MirroredStrategy``; ``"data_parallel"``
  (JAX backend) under ``keras.distribution.DataParallel``, also on several processes
  (``num_processes``, ``process_id``, ``coordinator_address``), of which only the chief writes
  ``model_dir`` (:mod:`stnh_tf.training.distribute`).

Two data sources, same losses and schedule: the TFRecords in ``data_dir`` (TensorFlow backend), or
``image_dir``: stage-1 pairs generated on the fly from a folder of images by
:class:`stnh_tf.data.pair_datasets.PairStream` (NumPy/OpenCV in worker processes; any Keras backend,
e.g. JAX on a GPU machine without TensorFlow). ``image_dir`` with ``samples_per_image=N`` and
``seed=S`` gives exactly the pairs ``data_prep.make_dataset --samples_per_image=N --seed=S`` writes
(shuffled differently); ``fresh_pairs`` draws new pairs every data epoch instead. With ``in_memory``
the set is generated once (:func:`stnh_tf.training.streams.stage_pairs`), and stage k > 1 trains
from the folder too: its pairs are made in memory from the predictions of the ``prev_stages``
models, as make_stage_dataset makes them.

The pieces, one module per concern: :mod:`stnh_tf.training.config` (the fields and their checks),
:mod:`stnh_tf.training.model_kinds` (build, losses and targets of each model kind),
:mod:`stnh_tf.training.run_dir` (the run's folder and checkpoints),
:mod:`stnh_tf.training.streams` (inputs), :mod:`stnh_tf.training.callbacks` (non-finite guard,
progress, time limit), :mod:`stnh_tf.training.fit_calls` (the ``model.fit`` calls of a run),
:mod:`stnh_tf.training.precision` (mixed precision on this machine).
A run trained in chunks across machines: :mod:`stnh_tf.training.chunks`.
"""

from __future__ import annotations

import contextlib
import gc
import importlib.util
import math
import os
import signal
import time

import keras

from stnh_tf.paths import atomic_write_json, fsync_replace
from stnh_tf.provenance import machine_info
from stnh_tf.training import checkpoints, distribute, fit_calls, model_kinds, run_dir
from stnh_tf.training import streams as train_streams
from stnh_tf.training.callbacks import (NonFiniteGuard, ProgressLogger, StepScalars, TimeLimit,
                                        report_every, stop_on_signals)
from stnh_tf.training.config import OPTIMIZER_NAMES, TrainConfig, dtype_policy
from stnh_tf.training.precision import mixed_precision_warning


def _sgd(cfg, schedule, **common):
    return keras.optimizers.SGD(learning_rate=schedule, momentum=cfg.momentum, **common)


def _adam(cfg, schedule, **common):
    return keras.optimizers.Adam(learning_rate=schedule, **common)


def _adamw(cfg, schedule, **common):
    return keras.optimizers.AdamW(learning_rate=schedule, **common)


# The optimizers by name: ``f(cfg, schedule, weight_decay=..., global_clipnorm=...)``.
OPTIMIZERS = {"sgd": _sgd, "adam": _adam, "adamw": _adamw}
if sorted(OPTIMIZERS) != sorted(OPTIMIZER_NAMES):
    raise ImportError(f"training.OPTIMIZERS {sorted(OPTIMIZERS)} must match "
                      f"train_config.OPTIMIZER_NAMES {sorted(OPTIMIZER_NAMES)}.")


STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)
"""The signals that stop a run after its current step, that step's checkpoint saved: what
``timeout`` and ``kill`` send, and Ctrl-C (a second one acts as it did before: it interrupts)."""


class TrainingDiverged(RuntimeError):
    """Raised when the loss or the weights become non-finite."""


# ------------------------------------------------------------------------------------------------
# Pieces
# ------------------------------------------------------------------------------------------------
def step_boundaries(train_steps: int) -> list:
    """The last steps (0-based) of the first and second thirds of ``train_steps``:
    ``[T // 3 - 1, 2 T // 3 - 1]`` (``[29999, 59999]`` for DeTone et al.'s 90,000 iterations)."""
    return [train_steps // 3 - 1, 2 * train_steps // 3 - 1]


def learning_rate_schedule(cfg: TrainConfig):
    """The learning rate as a function of the 0-based step (Keras evaluates it at
    ``optimizer.iterations`` before each update, so update ``i`` uses ``lr(i)``).

    * ``lr_schedule="cosine"`` (the paper's): linear warm-up from 0 to ``learning_rate`` over
      ``warmup_steps``, then cosine decay to 0 over ``train_steps - warmup_steps`` (Keras' own
      ``CosineDecay``).
    * ``lr_schedule="step"`` (DeTone et al.'s): ``learning_rate`` for the first third of
      ``train_steps``, a tenth of it for the second, a hundredth for the last (Keras'
      ``PiecewiseConstantDecay`` at :func:`step_boundaries`; as Caffe's "step" policy,
      ``lr * 0.1 ** floor(i / (T / 3))``, for ``T`` a multiple of 3). No warm-up.
    """
    if cfg.lr_schedule == "step":
        lr = cfg.learning_rate
        return keras.optimizers.schedules.PiecewiseConstantDecay(
            step_boundaries(cfg.train_steps), [lr, lr / 10.0, lr / 100.0])
    return keras.optimizers.schedules.CosineDecay(
        initial_learning_rate=0.0 if cfg.warmup_steps else cfg.learning_rate,
        decay_steps=max(cfg.train_steps - cfg.warmup_steps, 1),
        alpha=0.0,
        warmup_target=cfg.learning_rate if cfg.warmup_steps else None,
        warmup_steps=cfg.warmup_steps,
    )


def build_optimizer(cfg: TrainConfig) -> keras.optimizers.Optimizer:
    """``cfg.optimizer`` (:data:`OPTIMIZERS`) on :func:`learning_rate_schedule`, with
    ``cfg.weight_decay`` (decoupled; Keras' ``weight_decay``) and ``cfg.clipnorm`` (Keras'
    ``global_clipnorm``). ``optimizer="adam"`` with a weight decay equals ``"adamw"``."""
    common = {"weight_decay": cfg.weight_decay or None,
              "global_clipnorm": cfg.clipnorm or None}
    if cfg.optimizer == "adamw":
        common["weight_decay"] = cfg.weight_decay  # AdamW's own default is 0.004, not 0
    return OPTIMIZERS[cfg.optimizer](cfg, learning_rate_schedule(cfg), **common)


def compile_model(model, cfg: TrainConfig):
    losses, loss_weights, metrics = model_kinds.loss_spec(cfg)
    optimizer = build_optimizer(cfg)
    model.compile(optimizer=optimizer, loss=losses, loss_weights=loss_weights,
                  weighted_metrics=metrics, steps_per_execution=cfg.steps_per_execution)
    return model


# ------------------------------------------------------------------------------------------------
# The run
# ------------------------------------------------------------------------------------------------


def check_start(cfg: TrainConfig, time_limit_s: float | None = None) -> None:
    """Every check of ``cfg``'s flags and data that can fail before training, run by
    :func:`train` before ``model_dir`` is touched, so that a bad flag never costs a finished run
    under ``--overwrite`` nor leaves files behind: the fields and ``time_limit_s``
    (:meth:`TrainConfig.validate`),
    the losses (:func:`loss_spec`), the backend's strategy; the dataset (a ``train`` split of
    this stage holding at least one batch, its shards and the validation split's present with
    their recorded sizes) or the image folders (at least one batch of pairs); the data of the
    label options (:func:`~stnh_tf.training.streams.check_labels`); the models that
    ``init_from`` and ``prev_stages`` name.

    Raises:
      ValueError / OSError (``FileNotFoundError``, ``data.ShardError``): naming the flag, folder
        or file.
    """
    from stnh_tf.data import batches
    from stnh_tf.data import tfrecords as data
    from stnh_tf.data import sources

    cfg.validate(time_limit_s=time_limit_s)
    model_kinds.loss_spec(cfg)
    distribute.check(cfg)  # data_parallel: the JAX backend
    if keras.backend.backend() != "tensorflow":
        _strategy(cfg)
    if cfg.image_dir:
        batches.PairBatches(sources.split_folders(cfg.image_dir), cfg.batch_size,
                         samples_per_image=cfg.samples_per_image, cache_images=False,
                         max_images=cfg.max_images)
        if cfg.val_samples and cfg.val_image_dir:
            batches.PairBatches(sources.split_folders(cfg.val_image_dir), cfg.batch_size,
                             shuffle=False, drop_remainder=False, cache_images=False)
    else:
        train_streams.check_dataset(cfg.data_dir, "train", cfg.stage)
        data.load_split(cfg.data_dir, "train", cfg.batch_size, shuffle=False, repeat=False)
        val_split = train_streams.validation_plan(cfg)[0]  # (a val_split named, not there)
        if val_split:
            data.shard_paths(cfg.data_dir, val_split)
    train_streams.check_labels(cfg)  # label_fraction, drop_unlabeled, unlabeled_image_dir
    resuming = os.path.isfile(os.path.join(cfg.model_dir, run_dir.CHECKPOINT_DIR,
                                            run_dir.CHECKPOINT_STATE)) and not run_dir.finished(
        cfg.model_dir, cfg.train_steps)  # (a resume reads no init_from)
    for d in (*(() if resuming else cfg.init_from), *cfg.prev_stages):
        path = run_dir.model_file(d)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"no trained model at {d} (looked for {path}); init_from and "
                                    "prev_stages name finished training runs.")


def _strategy(cfg):
    """The tf.distribute strategy (None on other backends, which run on their default device,
    and for ``data_parallel``: keras.distribution, :mod:`stnh_tf.training.distribute`)."""
    if cfg.strategy == "data_parallel":
        return None
    if keras.backend.backend() != "tensorflow":
        if cfg.strategy != "default":
            raise ValueError(f"strategy={cfg.strategy!r} needs the TensorFlow backend; this is "
                             f"{keras.backend.backend()!r}.")
        return None
    import tensorflow as tf

    if cfg.strategy == "mirrored":
        return tf.distribute.MirroredStrategy()
    return tf.distribute.get_strategy()


def _strategy_scope(cfg):
    strategy = _strategy(cfg)
    return strategy.scope() if strategy is not None else contextlib.nullcontext()


def _load_start(model, cfg: TrainConfig, ckpt_dir: str) -> int:
    """Load the latest checkpoint of ``ckpt_dir`` into the compiled ``model``, or on a fresh start
    (none there) ``cfg.init_from``'s weights; returns the checkpoint's step (0: fresh)."""
    start_step = checkpoints.load_checkpoint(model, ckpt_dir)
    if start_step == 0 and cfg.init_from:
        model_kinds.initialize_from(model, cfg.init_from)
    return start_step


def tensorboard_available() -> bool:
    """Keras' TensorBoard callback writes through TensorFlow's summary ops."""
    return importlib.util.find_spec("tensorflow") is not None


# ------------------------------------------------------------------------------------------------
# Data streams (on top of stnh_tf.data.tfrecords)
# ------------------------------------------------------------------------------------------------


def train(cfg: TrainConfig, overwrite: bool = False, printer=print, stream_fn=None,
          extra_callbacks=(), time_limit_s: float | None = None):
    """Train (or resume) the model described by ``cfg``. Returns a dict of final results: a
    finished run's (also written to ``model_dir/result.json``) has ``final_step``,
    ``wall_s_this_run`` (this call's, not an earlier session's), ``machine`` (the commit, machine
    and Keras backend of this process: :func:`stnh_tf.provenance.machine_info`) and ``history``.

    ``time_limit_s`` (None or 0: no limit; else a finite number > 0, checked with the fields):
    stop within one step of this many seconds after the call, after the step past which another
    as long would end beyond it (:class:`~stnh_tf.training.callbacks.TimeLimit`), and save the
    checkpoint of that step, between the ``checkpoint_every`` ones if need be. A SIGTERM or a
    SIGINT (Ctrl-C) while training stops the same way after the current step (on one process, in
    the main thread: :data:`STOP_SIGNALS`), so neither ``timeout`` nor Ctrl-C loses work. The
    result then has ``stopped_by`` (``"time limit"``, ``"SIGTERM"`` or ``"SIGINT"``; with the
    time limit also ``stopped_at_time_limit``) and no final model is written: the same call
    resumes the run from that step, its first ``fit`` call a short epoch to the next multiple of
    ``checkpoint_every`` (:func:`stnh_tf.training.fit_calls.calls`), and ends with the weights
    of an uninterrupted run. Several processes stop by the time limit alone, at an epoch end
    (the chief's decision, shared).

    ``stream_fn(cfg, split, start_step)`` may replace the TFRecord stream (tests, generators);
    ``extra_callbacks`` run after the built-in ones (checkpointing comes first).

    Every check of the flags and data (:func:`check_start`) runs before ``model_dir`` is touched
    (:func:`prepare_model_dir`); if a new run then fails before its first checkpoint, what it
    wrote is removed again. A corrupted shard met while training raises ``data.ShardError``
    naming the file. The run holds the lock of ``model_dir``
    (:class:`~stnh_tf.training.run_dir.RunLock`) from before :func:`prepare_model_dir` to its
    end: a second run there meanwhile is refused (``FileExistsError`` naming the folder) before
    it reads or deletes anything.

    With ``cfg.num_processes`` > 1 every process calls this with the same ``cfg`` but its
    ``process_id``: only process 0 takes the lock and writes ``model_dir``, every process trains
    on its share of each global batch and returns the same result
    (:mod:`stnh_tf.training.distribute`).
    """
    t_call = time.monotonic()
    cluster = distribute.join(cfg)  # first: before any JAX computation (metrics in check_start)
    check_start(cfg, time_limit_s)
    warning = mixed_precision_warning(cfg)
    if warning:
        printer(f"warning: {warning}")
    generated = bool(cfg.image_dir)
    stream_fn = stream_fn or (train_streams.generated_stream if generated
                              else train_streams.training_stream)
    made_dir = not os.path.exists(cfg.model_dir)
    lock, new_run, completed = None, False, False
    try:
        if cluster.is_chief:  # several processes: only the chief touches model_dir
            lock = run_dir.RunLock(cfg.model_dir)  # one run per folder, held to the end
            new_run = run_dir.prepare_model_dir(cfg, overwrite=overwrite)
    except BaseException:
        if lock is not None:
            lock.release()
        distribute.report_start(cluster, ok=False)
        raise
    train_ds = None
    try:  # (from here a failure puts a set-aside run back and releases the lock)
        distribute.report_start(cluster, ok=True)
        keras.utils.set_random_seed(cfg.seed)
        keras.mixed_precision.set_global_policy(dtype_policy(cfg.mixed_precision))
        distribute.activate(cluster, cfg.batch_size)
        with _strategy_scope(cfg):
            model = model_kinds.build_model(cfg)
            compile_model(model, cfg)
            ckpt_dir = os.path.join(cfg.model_dir, run_dir.CHECKPOINT_DIR)
            start_step = distribute.load_state(  # several processes: the chief's, sent to all
                cluster, model, lambda m: _load_start(m, cfg, ckpt_dir),
                lambda: compile_model(model_kinds.build_model(cfg), cfg))
        if start_step:
            printer(f"resuming {cfg.model_dir} from step {start_step}")
        if start_step >= cfg.train_steps:
            printer("checkpoint already at the final step")
        mapper = None if generated else model_kinds.targets_for(cfg)  # (tf.data streams)

        def stream_at(step):  # this process's share of the training stream, from ``step``
            stream = distribute.train_stream(cluster, cfg, step, stream_fn)
            return stream.map(mapper) if mapper is not None else stream

        train_ds = stream_at(start_step)
        val_ds = val_steps = None
        val_split, val_line = train_streams.validation_plan(cfg)
        if val_line:
            printer(val_line)
        if generated:
            if cfg.val_samples and cfg.val_image_dir:
                val_ds = train_streams.generated_validation(cfg)
                val_steps = len(val_ds)
        elif val_split:
            val_ds, val_steps = train_streams.validation_stream(cfg, val_split)
            val_ds = val_ds.map(mapper) if mapper is not None else val_ds
        val_ds, val_steps = distribute.validation_share(cluster, val_ds, val_steps)
        guard = NonFiniteGuard()
        every = report_every(cfg.log_every, cfg.train_steps)
        callbacks = [guard, ProgressLogger(every, cfg.train_steps, printer)]
        if cluster.is_chief:  # checkpoints and logs: the chief's alone
            callbacks.insert(1, distribute.chief_callback(
                cluster, checkpoints.AtomicCheckpoint(ckpt_dir, guard)))
            if tensorboard_available():
                callbacks.append(StepScalars(os.path.join(cfg.model_dir, run_dir.LOGS_DIR),
                                             every, cfg.train_steps))
            else:
                printer("TensorFlow is not installed: no TensorBoard logs (console progress only)")
        callbacks.extend(extra_callbacks)
        # The time limit and STOP_SIGNALS stop a run on one process after any step (its checkpoint
        # saved); several processes stop together at an epoch end (SyncStop), by the limit alone.
        limit = (TimeLimit(time_limit_s or None, start=t_call, per_step=not cluster.multi)
                 if time_limit_s or not cluster.multi else None)
        callbacks += [limit] if limit else []
        callbacks += distribute.callbacks(cluster, limit)  # the chief's stop decision, to all
        t0 = time.time()
        histories, stream_start = [], start_step  # the step of the stream's first item
        try:
            with stop_on_signals(None if cluster.multi else limit, STOP_SIGNALS):
                for step_0, first_epoch, epochs, steps in fit_calls.calls(
                        start_step, cfg.checkpoint_every, cfg.train_steps):
                    if step_0 != stream_start:  # each call reads its stream from the start
                        train_ds = fit_calls.advance_stream(train_ds, step_0 - stream_start,
                                                            lambda: stream_at(step_0))
                        stream_start = step_0
                    spe = math.gcd(cfg.steps_per_execution, steps)  # (a short epoch: may differ)
                    with fit_calls.steps_per_execution(model, spe):
                        histories.append(model.fit(
                            train_ds, epochs=epochs, initial_epoch=first_epoch,
                            steps_per_epoch=steps, validation_data=val_ds,
                            validation_steps=val_steps, callbacks=callbacks, verbose=0,
                            shuffle=False))  # (the streams are shuffled themselves)
                    if model.stop_training:
                        break
        except Exception as e:
            if not generated:
                train_streams.raise_shard_error(cfg, e)
            raise
        history = {}
        for h in histories:
            for k, v in h.history.items():
                history.setdefault(k, []).extend(v)
        if guard.bad_step is not None:
            last = checkpoints.checkpoint_weights_path(ckpt_dir)
            last_step = (checkpoints.read_checkpoint_state(ckpt_dir)["step"] if last is not None
                         else 0)
            raise TrainingDiverged(
                f"non-finite {guard.what} at step {guard.bad_step}; last good checkpoint: "
                f"{last or '(none)'} (step {last_step}). Resuming with the same flags repeats the "
                "same batches and diverges again: check the data, or train anew with a lower "
                "--learning_rate (a new --model_dir, or --overwrite).")
        step = int(keras.ops.convert_to_numpy(model.optimizer.iterations))
        if limit is not None and limit.stopped_step is not None and step < cfg.train_steps:
            by = limit.stopped_by or "time limit"
            printer(f"stopped at step {step} of {cfg.train_steps} by "
                    + (f"the time limit ({time_limit_s:g} s)" if by == "time limit" else by)
                    + "; its checkpoint is saved: the same command resumes from there"
                    + (f" (the run --overwrite replaced stays in {run_dir.PREVIOUS_RUN} until "
                       "this one finishes)" if os.path.isdir(os.path.join(
                           cfg.model_dir, run_dir.PREVIOUS_RUN)) else ""))
            return {"final_step": step, "stopped_at_time_limit": by == "time limit",
                    "stopped_by": by, "wall_s_this_run": time.time() - t0}
        final_path = os.path.join(cfg.model_dir, run_dir.FINAL_MODEL)
        tmp = os.path.join(cfg.model_dir, f"tmp-{os.getpid()}-{run_dir.FINAL_MODEL}")
        if cluster.is_chief:
            with distribute.local_only(cluster):
                model.save(tmp)
            fsync_replace(tmp, final_path)
        result = {"final_step": int(keras.ops.convert_to_numpy(model.optimizer.iterations)),
                  "wall_s_this_run": time.time() - t0, "machine": machine_info(),
                  "history": {k: [float(x) for x in v] for k, v in history.items()}}
        if cluster.is_chief:
            atomic_write_json(os.path.join(cfg.model_dir, run_dir.RESULT_FILE), result)
        completed = True
        return result
    except BaseException:
        if new_run:
            run_dir.undo_new_run(cfg.model_dir, made_dir)
        if cluster.is_chief and os.path.isdir(os.path.join(cfg.model_dir, run_dir.PREVIOUS_RUN)):
            printer(run_dir.previous_run_line(cfg.model_dir))
        raise
    finally:
        if completed and cluster.is_chief:  # (the run --overwrite replaced: no longer needed;
            run_dir.discard_previous_run(cfg.model_dir)  # kept by a run stopped before its end)
        keras.mixed_precision.set_global_policy("float32")
        if hasattr(train_ds, "close"):  # a PairStream's generator processes
            train_ds.close()
        # Its tf.data iterator sits in a reference cycle; left to the interpreter's exit, it
        # called into a finalizing Python and TensorFlow logged an error after the last line.
        gc.collect()
        distribute.deactivate(cluster)
        if lock is not None:
            lock.release()
