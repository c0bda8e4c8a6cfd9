"""Training: a run's configuration (:mod:`~stnh_tf.training.config`), its folder and atomic
checkpoints (:mod:`~stnh_tf.training.run_dir`), its input streams
(:mod:`~stnh_tf.training.streams`), the model kinds a run can train
(:mod:`~stnh_tf.training.model_kinds`), and the loop that fits every model kind with the paper's
recipe (:mod:`~stnh_tf.training.loop`, :func:`~stnh_tf.training.loop.train`)."""

from stnh_tf import _compat

# Before 0.2 ``stnh_tf.training`` was the loop's module: its names stay reachable here.
__getattr__ = _compat.delegate(__name__, "stnh_tf.training.loop")
