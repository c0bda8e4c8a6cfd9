"""The training loop's own Keras callbacks: a guard against a non-finite loss, console progress,
TensorBoard scalars against the global step, and a time limit for runs trained in chunks (what
Keras' built-in callbacks do not offer)."""

from __future__ import annotations

import math
import os
import time

import keras


class NonFiniteGuard(keras.callbacks.Callback):
    """Stops training at the first non-finite loss and remembers the step."""

    def __init__(self):
        super().__init__()
        self.bad_step = None

    def on_train_batch_end(self, batch, logs=None):
        loss = (logs or {}).get("loss")
        if loss is not None and not math.isfinite(float(loss)):
            self.bad_step = int(keras.ops.convert_to_numpy(self.model.optimizer.iterations))
            self.model.stop_training = True


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
    return float(keras.ops.convert_to_numpy(model.optimizer.learning_rate))


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
    learning rate, steps/s."""

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
        self.printer(f"step {step}/{self.total} lr={lr:.5g} {parts} ({rate:.2f} steps/s)")

    def on_epoch_end(self, epoch, logs=None):
        vals = {k: v for k, v in (logs or {}).items() if k.startswith("val_")}
        if vals:
            self.printer(f"step {_step(self.model)} validation " +
                         " ".join(f"{k}={float(v):.5g}" for k, v in sorted(vals.items())))


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


class TimeLimit(keras.callbacks.Callback):
    """Stops training at an epoch end (just after its checkpoint, which an earlier callback
    writes) when another epoch, as long as the last one, would end more than ``seconds`` after
    ``start`` (``time.monotonic()``; default: when training began). ``stopped_step`` is the step it
    stopped at (``None`` if it did not)."""

    def __init__(self, seconds: float, start: float | None = None, clock=time.monotonic):
        super().__init__()
        self.seconds, self.start, self.clock = float(seconds), start, clock
        self.stopped_step = None
        self._last = None

    def on_train_begin(self, logs=None):
        self.start = self.clock() if self.start is None else self.start
        self._last = self.clock()

    def on_epoch_end(self, epoch, logs=None):
        now = self.clock()
        if now - self.start + (now - self._last) > self.seconds:
            self.model.stop_training = True
            self.stopped_step = int(keras.ops.convert_to_numpy(self.model.optimizer.iterations))
        self._last = now
