"""The ``[worker k/N]`` prefix of every log line of a process of a multi-process run (standard
library only, so that the training binaries set it before TensorFlow or JAX start;
:func:`stnh_tf.training.distribute.join` sets it too, before joining the others)."""

from __future__ import annotations

import logging


def log_prefix(num_processes: int, process_id: int) -> str:
    """What starts each log line of process ``process_id`` of ``num_processes``:
    ``"[worker k/N] "`` (``k`` its ``process_id``; worker 0 is the chief) on several processes,
    ``""`` on one.

    >>> log_prefix(2, 1), log_prefix(1, 0)
    ('[worker 1/2] ', '')
    """
    return f"[worker {process_id}/{num_processes}] " if num_processes > 1 else ""


_PREFIX = None  # what prefix_logs installed


def prefix_logs(num_processes: int, process_id: int) -> None:
    """Start every Python log record of this process with :func:`log_prefix` (a
    ``logging.setLogRecordFactory`` around the current factory: every logger and handler shows
    it, absl's included, hence all the binaries' lines, the chief's too, and JAX's). Once a
    process, idempotent; no-op on one process. Lines that C++ writes itself (XLA's, Gloo's) and
    ``print``'s are not prefixed.

    >>> prefix_logs(1, 0)  # one process: nothing changes

    Raises:
      RuntimeError: called again with another prefix.
    """
    global _PREFIX
    prefix = log_prefix(num_processes, process_id)
    if not prefix or prefix == _PREFIX:
        return
    if _PREFIX is not None:
        raise RuntimeError(f"this process's log lines start with {_PREFIX!r}; not {prefix!r}.")
    factory = logging.getLogRecordFactory()

    def record(*args, **kwargs):
        made = factory(*args, **kwargs)
        made.msg = f"{prefix}{made.msg}"
        return made

    logging.setLogRecordFactory(record)
    _PREFIX = prefix
