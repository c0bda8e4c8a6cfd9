"""How a training run's steps are cut into ``model.fit`` calls: one Keras epoch per checkpoint
interval (``checkpoint_every`` steps), and for a run resumed between two checkpoints (stopped by its
time limit or a signal: :class:`~stnh_tf.training.callbacks.TimeLimit`) first a short epoch to the
next one; the training stream and the compiled step made ready for each call.
"""

from __future__ import annotations

import contextlib


def calls(start_step: int, every: int, total: int) -> list:
    """The ``model.fit`` calls that train from ``start_step`` to ``total`` with a checkpoint at
    every multiple of ``every`` (one Keras epoch each), as ``(first_step, initial_epoch, epochs,
    steps_per_epoch)``: a start between two checkpoints (a run stopped by its time limit or a
    signal) first takes one short epoch to the next multiple, then the whole ones.

    >>> calls(0, 500, 1500), calls(1500, 500, 1500)
    ([(0, 0, 3, 500)], [])
    >>> calls(700, 500, 1500)
    [(700, 1, 2, 300), (1000, 2, 3, 500)]
    """
    out = []
    if start_step % every and start_step < total:
        out.append((start_step, start_step // every, start_step // every + 1,
                    every - start_step % every))
    first = -(-start_step // every)
    if first < total // every:
        out.append((first * every, first, total // every, every))
    return out


def advance_stream(stream, steps: int, rebuild):
    """The training stream ``steps`` items on, for the next ``fit`` call (each call reads its
    stream from its first item): a stream indexed from its ``start_step`` (``PairStream``,
    ``ArrayStream``) is moved on, keeping its workers and pairs; any other is closed and made anew
    at the step by ``rebuild()`` (a TFRecord stream positions itself as on a resume)."""
    if isinstance(getattr(stream, "start_step", None), int):
        stream.start_step += steps
        return stream
    if hasattr(stream, "close"):
        stream.close()
    return rebuild()


@contextlib.contextmanager
def steps_per_execution(model, steps: int):
    """The compiled ``model``'s training step running ``steps`` steps a call while inside (for a
    short first epoch that the configured number does not divide: a run resumed between two
    checkpoints with another ``steps_per_execution``), the configured number again after (each
    change rebuilds the step, which compiles it once more)."""
    configured = model.steps_per_execution
    if steps == configured:
        yield
        return
    model.steps_per_execution = steps
    model.make_train_function(force=True)
    try:
        yield
    finally:
        model.steps_per_execution = configured
        model.make_train_function(force=True)
