"""The progress of a reproduction's training (:class:`Progress`): one line per model every few
steps, with the model's step, loss and time left and the time left of the whole reproduction,
and the end of a reproduction whose training a signal stopped (:class:`Stopped`: Ctrl-C or
SIGTERM, after the checkpoint of the step reached is saved).

A line reads

    [train] stage2 step 120/400 loss=0.234 (1.52 steps/s, 3.1 min left; reproduction: 41.2 min left)

The model's rate is the steps per second of its current ``model.fit`` call after its first step
(compilation excluded, as :class:`~stnh_tf.training.callbacks.ProgressLogger` measures it); the
time left of the reproduction is the steps left in every model not yet finished at its kind's
rate (measured so far in this process, else the rate a plan measured beforehand:
``rates``; a sequence model of two stages at half a stage's rate where neither is known) plus,
where a plan estimated them (``fixed_s``), the seconds of everything but training not yet spent
(data, evaluation, latency, figures; "training:" then instead of "reproduction:" where none).
"""

from __future__ import annotations

import time

from stnh_tf.training.callbacks import ProgressLogger, report_every, time_left


class Stopped(RuntimeError):
    """A model's training was stopped by a signal (its checkpoint saved): the reproduction ends
    with this one line, and the same command resumes it."""


def duration(seconds: float) -> str:
    """``seconds`` as :func:`~stnh_tf.training.callbacks.time_left` writes a duration.

    >>> duration(30), duration(200), duration(7200), duration(0)
    ('30 s', '3.3 min', '2.0 h', '0 s')
    """
    return time_left(seconds, 1.0) or "0 s"


class Progress:
    """The training progress of one reproduction.

    Args:
      models: ``[(name, kind, steps)]`` of every model it may train, in order
        (:func:`stnh_tf.paper.budgets.planned_models`); kinds ``"stn"``, ``"homographynet"``,
        ``"sequence"``.
      printer: takes each line.
      clock: seconds (default ``time.monotonic``; a fake one in tests).
      rates: ``{kind: steps/s}`` measured before training (the hour budget's probe), used until
        this process has measured the kind itself.
      fixed_s: seconds the plan gives everything but training, counted from now (0: unknown).
    """

    def __init__(self, models, printer=print, clock=time.monotonic, rates=None,
                 fixed_s: float = 0.0):
        self.printer, self.clock = printer, clock
        self.rates, self.fixed_s = dict(rates or {}), float(fixed_s)
        self.kind = {name: kind for name, kind, _ in models}
        self.left = {name: int(steps) for name, _, steps in models}  # steps left per model
        self._measured = {}  # kind: [steps, seconds] of finished fit calls
        self._segment = None  # the current fit call: [name, first step, its time, step, time]
        self._t0, self._train_s, self._fit_began = clock(), 0.0, None

    # -- what the reproduction tells it --------------------------------------------------------
    def finished(self, name: str) -> None:
        """Model ``name`` is finished (found trained, or just trained): nothing left of it."""
        self.left[name] = 0

    def fit_began(self) -> None:
        self._fit_began, self._segment = self.clock(), None

    def fit_ended(self) -> None:
        now = self.clock()
        if self._segment is not None:
            name, s0, t0, step, t = self._segment
            m = self._measured.setdefault(self.kind[name], [0, 0.0])
            m[0], m[1] = m[0] + step - s0, m[1] + t - t0
        self._segment = None
        if self._fit_began is not None:
            self._train_s += now - self._fit_began
        self._fit_began = None

    def step(self, name: str, step: int, total: int) -> None:
        """Model ``name`` reached ``step`` of ``total``."""
        now = self.clock()
        self.left[name] = max(total - step, 0)
        if self._segment is None or self._segment[0] != name:
            self._segment = [name, step, now, step, now]
        self._segment[3:] = [step, now]

    # -- rates and times -----------------------------------------------------------------------
    def model_rate(self, name: str) -> float | None:
        """Steps/s of model ``name``'s current fit call (None before its second step)."""
        seg = self._segment
        if seg is None or seg[0] != name or seg[3] <= seg[1] or seg[4] <= seg[2]:
            return None
        return (seg[3] - seg[1]) / (seg[4] - seg[2])

    def rate(self, kind: str, derive: bool = True) -> float | None:
        """Steps/s of ``kind``: measured in this process (finished fit calls and the current
        one), else ``rates``', else derived from the stages' (a 2-stage sequence model at half a
        stage's rate, and the reverse); None where nothing is known."""
        steps, secs = self._measured.get(kind, [0, 0.0])
        seg = self._segment
        if seg is not None and self.kind[seg[0]] == kind:
            steps, secs = steps + seg[3] - seg[1], secs + seg[4] - seg[2]
        if steps > 0 and secs > 0:
            return steps / secs
        if self.rates.get(kind):
            return float(self.rates[kind])
        if derive and kind in ("sequence", "stn"):
            r = self.rate("stn" if kind == "sequence" else "sequence", derive=False)
            return None if r is None else (r / 2 if kind == "sequence" else r * 2)
        return None

    def seconds_left(self) -> float | None:
        """Seconds left of the reproduction (training at :meth:`rate`, plus the rest of
        ``fixed_s``); None while a model with steps left has a kind of no known rate."""
        total = 0.0
        for name, steps in self.left.items():
            if steps:
                rate = self.model_rate(name) or self.rate(self.kind[name])
                if rate is None:
                    return None
                total += steps / rate
        training_now = (self.clock() - self._fit_began) if self._fit_began is not None else 0.0
        spent_elsewhere = self.clock() - self._t0 - self._train_s - training_now
        return total + max(self.fixed_s - spent_elsewhere, 0.0)

    def line(self, name: str, step: int, total: int, loss) -> str:
        """The progress line of model ``name`` at ``step`` of ``total`` (see the module)."""
        rate = self.model_rate(name)
        left = self.seconds_left()
        what = "reproduction" if self.fixed_s else "training"
        model = (f"{rate:.2f} steps/s, {duration((total - step) / rate)} left" if rate
                 else "rate after the next report")
        loss_text = "" if loss is None else f" loss={float(loss):.4g}"
        return (f"[train] {name} step {step}/{total}{loss_text} ({model}; {what}: "
                + ("time left unknown yet" if left is None else f"{duration(left)} left") + ")")

    # -- what training calls ------------------------------------------------------------------
    def callback(self, name: str, cfg) -> "ModelProgress":
        """The Keras callback of model ``name`` trained with ``cfg``: a line every
        :func:`~stnh_tf.training.callbacks.report_every` steps (``log_every``, at least ten a
        model) and at its last step. A model not in ``models`` is added (kind ``cfg.model``)."""
        self.kind.setdefault(name, cfg.model)
        self.left.setdefault(name, cfg.train_steps)
        return ModelProgress(self, name, report_every(cfg.log_every, cfg.train_steps),
                             cfg.train_steps)

    def train_printer(self, name: str):
        """The printer for :func:`stnh_tf.training.loop.train` of model ``name``: its own lines
        prefixed with the model's name, except the progress lines (this class prints its own),
        the line of a stop (:meth:`check_stop` ends the reproduction with its own) and the one
        that the data have no ``val`` split (a reproduction writes none, by design)."""
        def printer(*args):
            line = " ".join(str(a) for a in args)
            if not line.startswith(("step ", "stopped at step ", "no validation: ")):
                self.printer(f"[train] {name}: {line}")
        return printer

    def check_stop(self, name: str, cfg, result: dict) -> dict:
        """``result`` (:func:`stnh_tf.training.loop.train`'s) of a run that finished; raises
        :class:`Stopped` where a signal stopped it (its checkpoint saved)."""
        by = result.get("stopped_by")
        if by is None:
            self.finished(name)
            return result
        raise Stopped(f"{name} stopped by {by} at step {result.get('final_step')} of "
                      f"{cfg.train_steps}; its checkpoint is saved: the same command resumes "
                      "the reproduction from there")


class ModelProgress(ProgressLogger):
    """:class:`~stnh_tf.training.callbacks.ProgressLogger` for one model of a reproduction: its
    lines are :meth:`Progress.line`'s, every ``every`` steps and at the last, ``total``."""

    def __init__(self, progress: Progress, name: str, every: int, total: int):
        super().__init__(every, total, progress.printer)
        self.progress, self.name = progress, name
        self._last = None

    def on_train_begin(self, logs=None):
        self.progress.fit_began()

    def on_train_end(self, logs=None):
        self.progress.fit_ended()

    def on_train_batch_end(self, batch, logs=None):
        step = self.step_after(batch)
        self.progress.step(self.name, step, self.total)
        last, self._last = self._last, step
        if step == self.total or (last is not None and step // self.every > last // self.every):
            self.printer(self.progress.line(self.name, step, self.total,
                                            (logs or {}).get("loss")))
