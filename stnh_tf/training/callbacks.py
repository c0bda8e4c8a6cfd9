"""The training loop's own Keras callbacks: a guard against a non-finite loss, console progress, and
a time limit for runs trained in chunks (what Keras' built-in callbacks do not offer)."""

from __future__ import annotations

import math
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


class ProgressLogger(keras.callbacks.Callback):
    """One console line every ``every`` steps: step, losses, learning rate, steps/s."""

    def __init__(self, every, total, printer=print):
        super().__init__()
        self.every, self.total, self.printer = max(int(every), 1), total, printer
        self._t0 = self._s0 = None

    def on_train_batch_end(self, batch, logs=None):
        step = int(keras.ops.convert_to_numpy(self.model.optimizer.iterations))
        if self._t0 is None:
            self._t0, self._s0 = time.time(), step
        if step % self.every and step != self.total:
            return
        rate = (step - self._s0) / max(time.time() - self._t0, 1e-9)
        lr = float(keras.ops.convert_to_numpy(self.model.optimizer.learning_rate))
        parts = " ".join(f"{k}={float(v):.5g}" for k, v in sorted((logs or {}).items()))
        self.printer(f"step {step}/{self.total} lr={lr:.5g} {parts} ({rate:.2f} steps/s)")

    def on_epoch_end(self, epoch, logs=None):
        vals = {k: v for k, v in (logs or {}).items() if k.startswith("val_")}
        if vals:
            step = int(keras.ops.convert_to_numpy(self.model.optimizer.iterations))
            self.printer(f"step {step} validation " +
                         " ".join(f"{k}={float(v):.5g}" for k, v in sorted(vals.items())))


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
