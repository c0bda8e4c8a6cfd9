"""Helpers of the data pipeline's worker pools (:func:`stnh_tf.data.batches.generator_pool`):
children that do not re-run ``__main__`` (:func:`main_not_rerun`), and a stop that does not kill
a worker in the middle of a task (:func:`stop_pool`), and a result that does not wait forever on
a worker that died (:func:`pool_result`). The standard library only."""

from __future__ import annotations

import contextlib
import sys
import time


@contextlib.contextmanager
def main_not_rerun():
    """Keep new ``forkserver``/``spawn`` children from re-running ``__main__``.

    multiprocessing rebuilds the parent's main module in each child (``runpy`` of
    ``python -m experiments.train_stage``, whose imports load Keras and its backend: ~0.7 GB a
    worker under TensorFlow). Workers need only :mod:`stnh_tf.data.batches`, so while children start the main
    module names neither a spec nor a file."""
    main = sys.modules.get("__main__")
    if main is None:
        yield
        return
    saved = {k: main.__dict__[k] for k in ("__spec__", "__file__") if k in main.__dict__}
    main.__spec__ = None
    main.__dict__.pop("__file__", None)
    try:
        yield
    finally:
        main.__dict__.pop("__spec__", None)
        main.__dict__.update(saved)


WORKER_DIED = ("a pair-generator worker process died (killed, out of memory, or failing at its "
               "start): the batch it was making is lost, so the stream stops rather than wait "
               "for it forever (what was trained up to the last checkpoint stays)")


def mark_workers(pool):
    """``pool`` with the process ids it started with (:func:`workers_died` compares them):
    ``multiprocessing.Pool`` replaces a dead worker and drops the task it was running."""
    pool.stnh_pids = frozenset(p.pid for p in pool._pool)
    return pool


def workers_died(pool) -> bool:
    """Whether a worker of ``pool`` (:func:`mark_workers`) died since it started."""
    started = getattr(pool, "stnh_pids", None)
    return started is not None and frozenset(p.pid for p in pool._pool) != started


def pool_result(pool, result, poll_s: float = 2.0):
    """``result.get()`` of a task of ``pool``, or ``RuntimeError`` (:data:`WORKER_DIED`) where a
    worker died meanwhile: its result would never come."""
    import multiprocessing

    while True:
        try:
            return result.get(poll_s)
        except multiprocessing.TimeoutError:
            if workers_died(pool):
                raise RuntimeError(WORKER_DIED) from None


def stop_pool(pool, in_flight=(), timeout: float = 60.0) -> None:
    """Stop a :func:`~stnh_tf.data.batches.generator_pool` without killing a worker in the middle of a task.

    The results of ``in_flight`` (``AsyncResult`` objects: every task not yet finished) are let
    finish first and the workers then exit on their own (``close`` + ``join``); only if those
    results take longer than ``timeout`` seconds are the workers killed (``terminate``).
    ``Pool.terminate`` while a worker sends a result back leaves the result queue's lock held
    by a dead process, and the pool's threads and the caller waiting on it forever."""
    in_flight = list(in_flight)
    if workers_died(pool):  # its lost tasks never finish, and terminate() (or its finalizer
        import multiprocessing.pool as mp_pool  # at exit) waits on a lock the dead worker held

        pool._state = pool._worker_handler._state = mp_pool.TERMINATE  # no worker replaced
        pool._change_notifier.put(None)
        for worker in list(pool._pool):
            worker.kill()
        pool._terminate.cancel()
        return
    pool.close()
    deadline = time.monotonic() + timeout
    for result in in_flight:
        result.wait(max(deadline - time.monotonic(), 0.0))
    if all(r.ready() for r in in_flight):
        pool.join()
    else:
        pool.terminate()
