"""A lost process of a multi-process run (``--num_processes`` > 1): each process beats in the
key-value store of JAX's distributed service, and when one stops (killed, crashed or cut off)
each of the others logs one line that names it and says how to resume, then ends (:func:`watch`,
which :func:`stnh_tf.training.distribute.join` calls; the line: :func:`lost_line`).

Why not JAX's own detection: its distributed service finds a lost process only after its
heartbeat timeout (100 s), then ends the others with a C++ abort (``Terminating process because
the JAX distributed service detected fatal errors``) and no word on resuming; and a collective
that lost a peer raises at once (Gloo's ``Connection reset by peer``, as a ``JaxRuntimeError``
or a ``ValueError``), after which JAX's shutdown at exit waits for the lost process, then aborts.
Standard library only at import (JAX is imported by :func:`watch`).
"""

from __future__ import annotations

import logging
import os
import shlex
import sys
import threading
import time

CHIEF = 0
"""The chief's process id (:data:`stnh_tf.training.distribute.CHIEF` is this): JAX's service
lives in it."""

HEARTBEAT_TIMEOUT_S = 20.0
"""Seconds without a heartbeat after which a process of a multi-process run is lost
(:class:`Watchdog`): the others then log :func:`lost_line` and end. Well below JAX's own
heartbeat timeout (100 s), after which its distributed service ends the others with a C++ abort
and no word on resuming; well above the longest gap between two beats measured on a busy worker
(docs/scale.md)."""

HEARTBEAT_EVERY_S = 1.0
"""Seconds between two rounds (a beat and a look at the others') of a :class:`Watchdog`."""

LOST_EXIT_STATUS = 75
"""Exit status of a process ended because another was lost (``EX_TEMPFAIL``: resume later)."""

_BEAT_KEY = "stnh_tf/heartbeat/{}"  # a process's beat count in the store (or _DONE)
_DONE = "done"  # the value of a process that ended its work: no longer watched


def resume_command(num_processes: int, argv=None, environ=None) -> str:
    """How to start the ``num_processes`` workers again, from this process's command line ``argv``
    (default ``sys.orig_argv``) and its ``KERAS_BACKEND`` and ``JAX_PLATFORMS`` (from
    ``environ``, default ``os.environ``): with ``--process_id`` in it, the command of worker
    ``K`` for ``K = 0 .. N-1``; else this worker's own command (each worker runs its own).

    >>> resume_command(2, ["python", "-m", "experiments.train_stage", "--process_id=1",
    ...                    "--model_dir=r"], {})
    'on each worker K = 0..1: python -m experiments.train_stage --process_id=K --model_dir=r'
    """
    argv = list(getattr(sys, "orig_argv", sys.argv) if argv is None else argv)
    environ = os.environ if environ is None else environ
    env = [f"{k}={shlex.quote(environ[k])}" for k in ("KERAS_BACKEND", "JAX_PLATFORMS")
           if k in environ]
    found = False
    for i, arg in enumerate(argv):
        if arg.startswith("--process_id="):
            argv[i], found = "--process_id=K", True
        elif arg == "--process_id" and i + 1 < len(argv):
            argv[i + 1], found = "K", True
    words = [*env, *(shlex.quote(a) if a != "--process_id=K" else a for a in argv)]
    command = " ".join(words)
    if found:
        return f"on each worker K = 0..{num_processes - 1}: {command}"
    return f"each with its own command (this worker's: {command})"


def lost_line(num_processes: int, process_id: int, lost, model_dir: str | None = None,
              timeout_s: float = HEARTBEAT_TIMEOUT_S, argv=None, environ=None) -> str:
    """The one line process ``process_id`` of ``num_processes`` logs when the processes ``lost``
    (their ids) are lost: which, why this one stops, and how to resume (:func:`resume_command`);
    on the chief the step of the last checkpoint in ``model_dir``.

    >>> lost_line(2, 0, [1], argv=["train", "--process_id=0"], environ={})
    ... # doctest: +NORMALIZE_WHITESPACE
    'lost worker 1 of 2: no heartbeat for 20 s (killed, crashed or cut off); this worker stops
    too (exit status 75). To resume the run from its last checkpoint, start the 2 workers again,
    on each worker K = 0..1: train --process_id=K'
    """
    names = ", ".join(f"worker {j}" + (" (the chief)" if j == CHIEF else "") for j in lost)
    where = "its last checkpoint"
    if process_id == CHIEF and model_dir:
        from stnh_tf.training import checkpoints, run_dir

        try:
            state = checkpoints.read_checkpoint_state(os.path.join(model_dir,
                                                                   run_dir.CHECKPOINT_DIR))
        except (OSError, ValueError):
            state = None
        where = (f"its last checkpoint (step {state['step']} in {model_dir})" if state else
                 f"the start (no checkpoint yet in {model_dir})")
    return (f"lost {names} of {num_processes}: no heartbeat for {timeout_s:g} s (killed, "
            f"crashed or cut off); this worker stops too (exit status {LOST_EXIT_STATUS}). To "
            f"resume the run from {where}, start the {num_processes} workers again, "
            f"{resume_command(num_processes, argv, environ)}")


def _try_get(store, key):
    """``store``'s value of ``key``, None if it has none (other errors raised)."""
    try:
        return store.key_value_try_get(key)
    except Exception as e:  # noqa: BLE001 (jaxlib's error type is not public)
        if "NOT_FOUND" in str(e):
            return None
        raise


class Watchdog(threading.Thread):
    """The heartbeats of a multi-process run: a daemon thread in each process (:func:`watch`).

    Every ``every_s`` seconds it writes this process's beat count under its key in ``store`` (the
    key-value store of JAX's distributed service, which the chief holds: ``key_value_set``,
    ``key_value_try_get``) and reads the others'. A process whose count has not changed for
    ``timeout_s`` seconds of this process's ``clock`` (the processes need no common clock) is
    lost, and so is the chief when a non-chief cannot reach the store: ``on_lost(ids)`` is called
    once with the lost ids (sorted), then :attr:`verdict` is set and the thread ends.

    At exit (:meth:`finish`) a process marks itself done, which the others stop watching, and
    waits until every other one is done too, or lost: the run's end, however this process's work
    ended (an error that a lost process caused included), is decided here, not by JAX's shutdown
    (which would wait for a lost process, then abort). A failing process stops beating
    (:meth:`stop_beating`), so that the others report it lost.

    :meth:`check` is one round (what the thread repeats; tests call it without the thread)::

        Watchdog(2, 0, store, on_lost=print).start()  # process 0 of 2
    """

    def __init__(self, num_processes: int, process_id: int, store, on_lost,
                 timeout_s: float = HEARTBEAT_TIMEOUT_S, every_s: float = HEARTBEAT_EVERY_S,
                 clock=time.monotonic):
        super().__init__(name="stnh_tf-watchdog", daemon=True)
        self.num_processes, self.process_id = int(num_processes), int(process_id)
        self.store, self.on_lost = store, on_lost
        self.timeout_s, self.every_s, self.clock = float(timeout_s), float(every_s), clock
        self.beats, self.beating, self.lost = 0, True, None
        self.max_gap_s = 0.0  # the longest time between two rounds (how late a beat came)
        self.verdict = threading.Event()  # set when the thread ends (after on_lost, if called)
        self.all_done = threading.Event()  # set when every other process is done
        self._lock, self._exiting, self._last_round = threading.Lock(), False, None
        start = clock()
        self._seen = {j: (None, start, -float("inf")) for j in range(self.num_processes)
                      if j != self.process_id}  # id: (last value, when it changed, change before)

    def check(self):
        """One round: beat (unless stopped or done), read the others' beats; the ids of the lost
        processes (sorted), or None."""
        with self._lock:
            now = self.clock()
            if self._last_round is not None:
                self.max_gap_s = max(self.max_gap_s, now - self._last_round)
            self._last_round = now
            try:
                if self.beating and not self._exiting:
                    self.beats += 1
                    self.store.key_value_set(_BEAT_KEY.format(self.process_id),
                                             str(self.beats), allow_overwrite=True)
                values = {j: _try_get(self.store, _BEAT_KEY.format(j)) for j in self._seen}
            except Exception:  # noqa: BLE001 (the store unreachable: the chief is gone)
                return None if self.process_id == CHIEF else [CHIEF]
            lost = []
            for j, value in values.items():
                last, since, _ = self._seen[j]
                if value == _DONE:
                    del self._seen[j]
                elif value != last:
                    self._seen[j] = (value, now, since)
                elif now - since > self.timeout_s:
                    lost.append(j)
            if not self._seen:
                self.all_done.set()
            return sorted(lost) or None

    def run(self):
        while True:
            lost = self.check()
            if lost:
                self.lost = lost
                self.on_lost(lost)
                break
            if self._exiting and self.all_done.is_set():
                break
            time.sleep(self.every_s)
        self.verdict.set()

    def beaten_since(self, t: float) -> bool:
        """Whether every other process not done was alive after time ``t`` of :attr:`clock`: two
        changes of its beat seen by :meth:`check` after ``t`` (one is not enough: a process killed
        just before ``t`` may have written a beat that the first round after ``t`` reads; a second
        change needs a write after that round)."""
        with self._lock:
            return all(before > t for _, _, before in self._seen.values())

    def stop_beating(self) -> None:
        """Beat no more (this process is failing): the others will find it lost."""
        with self._lock:
            self.beating = False

    def finish(self, wait_s: float = 300.0) -> None:
        """This process ended its work: mark it done in the store (unless it stopped beating),
        then, while the thread runs, wait until every other process is done (or one is lost:
        ``on_lost``), at most ``wait_s`` seconds (JAX's own shutdown timeout). Once."""
        with self._lock:
            if self._exiting:
                return
            self._exiting = True
            if self.beating:
                try:
                    self.store.key_value_set(_BEAT_KEY.format(self.process_id), _DONE,
                                             allow_overwrite=True)
                except Exception:  # noqa: BLE001 (the store gone: nobody is left to tell)
                    pass
        if self.is_alive():
            self.verdict.wait(wait_s)


_WATCHDOG = None  # this process's Watchdog (watch)


def _flush_logs() -> None:
    for handler in logging.getLogger().handlers:
        handler.flush()
    for stream in (sys.stdout, sys.stderr):
        stream.flush()


def stop_lost(line: str) -> None:
    """Log ``line`` (an error, through absl) and end this process at once with
    :data:`LOST_EXIT_STATUS` (``os._exit``: JAX's shutdown at exit would wait for the lost process,
    then abort)."""
    from absl import logging as absl_logging

    absl_logging.error(line)
    _flush_logs()
    os._exit(LOST_EXIT_STATUS)


def watch(num_processes: int, process_id: int, model_dir: str | None = None,
          timeout_s: float = HEARTBEAT_TIMEOUT_S) -> Watchdog | None:
    """Start the :class:`Watchdog` of process ``process_id`` of ``num_processes`` over JAX's
    distributed service (after it is initialized; once a process;
    :func:`stnh_tf.training.distribute.join` calls it): when another process is lost, this one
    logs :func:`lost_line` and ends (:func:`stop_lost`), ``timeout_s`` (plus up to a round)
    after the lost one's last beat. At exit (``atexit``, before JAX's shutdown) it waits for the
    others (:meth:`Watchdog.finish`): a collective that lost a peer raises at once (a
    ``JaxRuntimeError``, or a ``ValueError`` from ``multihost_utils``), and the binary or script
    then ends, but the line still comes. An uncaught exception (``sys.excepthook``) first waits
    until every other process has beaten twice (about two rounds), or one is lost (its line then
    comes instead of the traceback), then stops the beats, prints the traceback and ends the
    process at once (exit status 1: the others, maybe stuck in a collective with it, then find it
    lost). The watchdog, or None on one process or without JAX's service.
    """
    global _WATCHDOG
    if num_processes < 2 or _WATCHDOG is not None:
        return _WATCHDOG
    from jax._src import distributed as jax_distributed

    store = jax_distributed.global_state.client
    if store is None:
        return None
    _WATCHDOG = Watchdog(num_processes, process_id, store, lambda lost: stop_lost(
        lost_line(num_processes, process_id, lost, model_dir, timeout_s)), timeout_s)
    _WATCHDOG.start()
    import atexit

    atexit.register(_WATCHDOG.finish)  # (runs before JAX's shutdown, registered at its import)
    sys.excepthook = _failure_hook(sys.excepthook, _WATCHDOG)
    return _WATCHDOG


def _failure_hook(previous, watchdog: Watchdog):
    """``sys.excepthook`` of a multi-process run (:func:`watch`)."""

    def hook(kind, value, traceback):
        start = watchdog.clock()  # wait until the others beat again, or one is lost (the line)
        while watchdog.is_alive() and not watchdog.beaten_since(start) and \
                watchdog.clock() - start < watchdog.timeout_s + 3 * watchdog.every_s:
            time.sleep(watchdog.every_s / 4)
        watchdog.stop_beating()
        previous(kind, value, traceback)
        _flush_logs()
        os._exit(1)

    return hook
