"""Evaluation: MACE of models, hierarchies and baselines on stored test pairs
(:mod:`~stnh_tf.evaluation.mace`), the classical baselines and their tuning
(:mod:`~stnh_tf.evaluation.baselines`, :mod:`~stnh_tf.evaluation.baseline_tuning`), and the
benchmarks' library cores (:mod:`~stnh_tf.evaluation.benchmarks`,
:mod:`~stnh_tf.evaluation.data_benchmark`, :mod:`~stnh_tf.evaluation.search_stability`,
:mod:`~stnh_tf.evaluation.camera_pairs`)."""

from stnh_tf import _compat

# Before 0.2 ``stnh_tf.evaluation`` was the MACE module: its names stay reachable here.
__getattr__ = _compat.delegate(__name__, "stnh_tf.evaluation.mace")
