"""The training loop's own Keras callbacks: a guard against a non-finite loss, console progress,
TensorBoard scalars against the global step, and a time limit (and stop signals) for runs trained
in chunks (what Keras' built-in callbacks do not offer)."""

from __future__ import annotations

import contextlib
import math
import os
import signal
import threading
import time

import keras


class NonFiniteGuard(keras.callbacks.Callback):
    """Stops training at the first non-finite loss, or at non-finite weights at an epoch end
    (:meth:`weights_finite`; before the checkpoint callbacks after it, which then write none:
    the last checkpoint stays the good one), and remembers the step (``bad_step``) and which it
    was (``what``: ``"loss"`` or ``"weights"``). First in the callbacks."""

    def __init__(self):
        super().__init__()
        self.bad_step, self.what = None, None

    def on_train_batch_end(self, batch, logs=None):
        loss = (logs or {}).get("loss")
        if loss is not None and not math.isfinite(float(loss)):
            self._stop(self.model, "loss")

    def on_epoch_end(self, epoch, logs=None):
        if self.bad_step is None:
            self.weights_finite(self.model)

    def weights_finite(self, model) -> bool:
        """Whether every floating-point weight of ``model`` is finite; where one is not, training
        stops as at a non-finite loss (an update can overflow the weights although the loss it
        was computed from was finite: the loss alone let such weights be checkpointed)."""
        import numpy as np

        if all(np.isfinite(np.asarray(keras.ops.convert_to_numpy(v), np.float64)).all()
               for v in model.weights if "float" in str(v.dtype)):
            return True
        self._stop(model, "weights")
        return False

    def _stop(self, model, what):
        self.bad_step, self.what = _step(model), what
        model.stop_training = True


class TrainingClock(keras.callbacks.Callback):
    """When training began (``began``, ``time.time()`` at the first ``fit`` call's start: the
    pairs made and the model built), for a chunk's ledger row of a training that ends in an
    error (its steps/s over training time, as the others'; ``None``: it never began)."""

    def __init__(self):
        super().__init__()
        self.began = None

    def on_train_begin(self, logs=None):
        if self.began is None:
            self.began = time.time()


def report_every(log_every: int, total: int) -> int:
    """Steps between progress reports: ``log_every``, but at least ten reports in a run of
    ``total`` steps.

    >>> report_every(50, 20), report_every(50, 91000), report_every(500, 1000)
    (2, 50, 100)
    """
    return max(min(int(log_every), math.ceil(total / 10)), 1)


def _step(model) -> int:
    return int(keras.ops.convert_to_numpy(model.optimizer.iterations))


def _learning_rate(model) -> float:
    """The learning rate of the update that made the current step: a schedule's at the step
    before (the optimizer's ``learning_rate`` is evaluated at ``iterations``: the next
    update's; logged as it was, a step schedule's drop showed one step early)."""
    optimizer = getattr(model.optimizer, "inner_optimizer", model.optimizer)  # (loss scaling)
    schedule = getattr(optimizer, "_learning_rate", None)  # (Keras keeps no public handle)
    if isinstance(schedule, keras.optimizers.schedules.LearningRateSchedule):
        return float(keras.ops.convert_to_numpy(schedule(max(_step(model) - 1, 0))))
    return float(keras.ops.convert_to_numpy(optimizer.learning_rate))


class _GlobalStep(keras.callbacks.Callback):
    """Knows the global step after each call from Keras' batch index and the optimizer's
    iterations at the epoch's start, without reading the model mid-epoch: under JAX that read
    copies the whole training state back into the model (``jax_state_sync``), which Keras
    itself does only at epoch ends."""

    def on_epoch_begin(self, epoch, logs=None):
        self._epoch_start = _step(self.model)  # the state is the model's between epochs

    def step_after(self, batch) -> int:
        """The global step after the call whose last step is ``batch`` of this epoch."""
        return self._epoch_start + int(batch) + 1


class ProgressLogger(_GlobalStep):
    """One console line every ``every`` steps (and at the last, ``total``): step, losses,
    learning rate, steps/s and, before the last, the time the steps left take at that rate
    (:func:`time_left`)."""

    def __init__(self, every, total, printer=print):
        super().__init__()
        self.every, self.total, self.printer = max(int(every), 1), total, printer
        self._t0 = self._s0 = None

    def on_train_batch_end(self, batch, logs=None):
        step = self.step_after(batch)
        if self._t0 is None:
            self._t0, self._s0 = time.time(), step
        if step % self.every and step != self.total:
            return
        rate = (step - self._s0) / max(time.time() - self._t0, 1e-9)
        lr = _learning_rate(self.model)
        parts = " ".join(f"{k}={float(v):.5g}" for k, v in sorted((logs or {}).items()))
        left = time_left(self.total - step, rate)
        self.printer(f"step {step}/{self.total} lr={lr:.5g} {parts} ({rate:.2f} steps/s"
                     + (f", {left} left" if left else "") + ")")

    def on_epoch_end(self, epoch, logs=None):
        vals = {k: v for k, v in (logs or {}).items() if k.startswith("val_")}
        if vals:
            self.printer(f"step {_step(self.model)} validation " +
                         " ".join(f"{k}={float(v):.5g}" for k, v in sorted(vals.items())))


def time_left(steps: int, steps_per_s: float) -> str:
    """``steps`` at ``steps_per_s`` as a short duration ('' for none, or no rate yet).

    >>> time_left(91_000 - 50, 2.0), time_left(450, 2.0), time_left(0, 2.0)
    ('12.6 h', '3.8 min', '')
    """
    if steps <= 0 or not steps_per_s > 0:
        return ""
    seconds = steps / steps_per_s
    if seconds >= 5_400:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 60:.1f} min" if seconds >= 90 else f"{seconds:.0f} s"


class StepScalars(_GlobalStep):
    """TensorBoard scalars against the global step (the optimizer's iterations): in
    ``log_dir/train`` the batch's losses and metrics and ``learning_rate`` every ``every`` steps
    and at the last (``total``), in ``log_dir/validation`` the validation metrics at every epoch
    end (each checkpoint). Hand-written: Keras' TensorBoard callback writes epoch-level scalars
    against the epoch index, and batch-level ones only where its own counter meets update_freq,
    so some runs got no scalars at all. Needs TensorFlow (its summary writer)."""

    def __init__(self, log_dir, every, total):
        super().__init__()
        self.log_dir, self.every, self.total = log_dir, max(int(every), 1), total
        self._writers = None

    def _write(self, name, values, step):
        import tensorflow as tf

        if self._writers is None:
            self._writers = {n: tf.summary.create_file_writer(os.path.join(self.log_dir, n))
                             for n in ("train", "validation")}
        with self._writers[name].as_default(step=step):
            for key, value in values.items():
                tf.summary.scalar(key, float(value))
        self._writers[name].flush()

    def on_train_batch_end(self, batch, logs=None):
        step = self.step_after(batch)
        if step % self.every == 0 or step == self.total:
            self._write("train", {**(logs or {}), "learning_rate": _learning_rate(self.model)},
                        step)

    def on_epoch_end(self, epoch, logs=None):
        vals = {k[len("val_"):]: v for k, v in (logs or {}).items() if k.startswith("val_")}
        if vals:
            self._write("validation", vals, _step(self.model))

    def on_train_end(self, logs=None):
        for writer in (self._writers or {}).values():
            writer.close()
        self._writers = None


class TimeLimit(_GlobalStep):
    """Stops training within one step of a time limit, or at a stop signal, so that the run's
    state at that step is saved: the stop ends the Keras epoch early, and Keras still runs the
    epoch's end (validation, then the checkpoint that
    :class:`~stnh_tf.training.checkpoints.AtomicCheckpoint` writes of the step reached), from which
    :func:`stnh_tf.training.loop.train` resumes.

    * ``seconds`` (``None``: no time limit): after each step (each call of the compiled step:
      ``steps_per_execution`` steps), stop if another one, as long as it, would end more than
      ``seconds`` after ``start`` (``clock()`` time; default: when training began). At least one
      step runs. ``per_step=False``: decide at epoch ends only (after their checkpoint), when
      another epoch as long as the last one would end past the limit; for several processes,
      which must stop at the same step (:class:`~stnh_tf.training.distribute.SyncStop` shares
      the chief's decision at epoch ends).
    * :meth:`request_stop` (what :func:`stop_on_signals` calls for a SIGTERM): stop after the
      current step, ``stopped_by`` naming the reason.

    ``stopped_step``: the step it stopped at (``None`` if it did not); ``stopped_by``:
    ``"time limit"``, the signal's name, or ``None``.

        >>> limit = TimeLimit(480)            # a GPU chunk of 8 minutes
        >>> limit.stopped_step, limit.stopped_by
        (None, None)
    """

    def __init__(self, seconds: float | None, start: float | None = None, clock=None,
                 per_step: bool = True):
        super().__init__()
        self.seconds = None if seconds is None else float(seconds)
        self.start, self.clock = start, clock or time.monotonic
        self.per_step = per_step
        self.stopped_step = self.stopped_by = None
        self._requested = None
        self._last = self._began = None

    def request_stop(self, reason: str) -> None:
        """Stop after the current step (the first reason given is kept)."""
        self._requested = self._requested or reason

    def _over(self, now, took) -> bool:
        return self.seconds is not None and now - self.start + took > self.seconds

    def _stop(self, step, reason):
        self.model.stop_training = True
        self.stopped_step, self.stopped_by = step, reason

    def on_train_begin(self, logs=None):
        self.start = self.clock() if self.start is None else self.start
        self._last = self.clock()

    def on_train_batch_begin(self, batch, logs=None):
        if self.per_step:
            self._began = self.clock()

    def on_train_batch_end(self, batch, logs=None):
        if not self.per_step:
            return
        now = self.clock()
        if self._requested:
            self._stop(self.step_after(batch), self._requested)
        elif self._over(now, now - self._began):
            self._stop(self.step_after(batch), "time limit")

    def on_epoch_end(self, epoch, logs=None):
        now = self.clock()
        if not self.model.stop_training:
            if self._requested:
                self._stop(_step(self.model), self._requested)
            elif not self.per_step and self._over(now, now - self._last):
                self._stop(_step(self.model), "time limit")
        self._last = now


@contextlib.contextmanager
def stop_on_signals(limit: TimeLimit | None, signals=(signal.SIGTERM,)):
    """While inside, the first of ``signals`` (default SIGTERM: what ``timeout`` and a plain
    ``kill`` send) asks ``limit`` to stop after the current step (:meth:`TimeLimit.request_stop`,
    the checkpoint of that step then saved) and puts the previous handler back, so that a second
    one acts as it did before; leaving restores every handler. Does nothing without a ``limit``
    or outside the main thread (where Python cannot handle signals).

        >>> with stop_on_signals(TimeLimit(None)):
        ...     pass   # model.fit(...)
    """
    if limit is None or threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) or signal.SIG_DFL  # (None: not set from Python)
                for sig in signals}

    def handler(signum, frame):
        signal.signal(signum, previous[signum])
        limit.request_stop(signal.Signals(signum).name)

    try:
        for sig in signals:
            signal.signal(sig, handler)
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


@contextlib.contextmanager
def deferred_signals(signals=(signal.SIGTERM, signal.SIGINT)):
    """While inside, ``signals`` wait: one that arrives is delivered again (to the handler that
    was in place) when the block is left, so that a few seconds of writes that must not be cut
    (a chunk's commit and ledger row: :func:`stnh_tf.training.chunks.run_chunk`) finish first.
    Does nothing outside the main thread (where Python cannot handle signals).

        >>> with deferred_signals():
        ...     pass   # sync_out(...); add_ledger_row(...)
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) or signal.SIG_DFL for sig in signals}
    received = []
    try:
        for sig in signals:
            signal.signal(sig, lambda signum, frame: received.append(signum))
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
        for signum in dict.fromkeys(received):  # each once, in the order they came
            os.kill(os.getpid(), signum)
