"""Training: a run's configuration (:mod:`~stnh_tf.training.config`), its folder and atomic
checkpoints (:mod:`~stnh_tf.training.run_dir`), its input streams
(:mod:`~stnh_tf.training.streams`), the model kinds a run can train
(:mod:`~stnh_tf.training.model_kinds`), and the loop that fits every model kind with the paper's
recipe (:mod:`~stnh_tf.training.loop`, :func:`~stnh_tf.training.loop.train`)."""

__all__ = ["train"]


def __getattr__(name):
    # ``train`` is imported on first use: the loop imports Keras, and importing
    # ``stnh_tf.training.config`` must not (tests/test_layout.py).
    if name == "train":
        from stnh_tf.training.loop import train
        return train
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
