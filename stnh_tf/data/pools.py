"""Helpers of the data pipeline's worker pools (:func:`stnh_tf.data.batches.generator_pool`):
children that do not re-run ``__main__`` (:func:`main_not_rerun`), and a stop that does not kill
a worker in the middle of a task (:func:`stop_pool`). The standard library only."""

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


def stop_pool(pool, in_flight=(), timeout: float = 60.0) -> None:
    """Stop a :func:`~stnh_tf.data.batches.generator_pool` without killing a worker in the middle of a task.

    The results of ``in_flight`` (``AsyncResult`` objects: every task not yet finished) are let
    finish first and the workers then exit on their own (``close`` + ``join``); only if those
    results take longer than ``timeout`` seconds are the workers killed (``terminate``).
    ``Pool.terminate`` while a worker sends a result back leaves the result queue's lock held
    by a dead process, and the pool's threads and the caller waiting on it forever."""
    in_flight = list(in_flight)
    pool.close()
    deadline = time.monotonic() + timeout
    for result in in_flight:
        result.wait(max(deadline - time.monotonic(), 0.0))
    if all(r.ready() for r in in_flight):
        pool.join()
    else:
        pool.terminate()
