"""Evaluation: MACE of models, hierarchies and baselines on stored test pairs
(:mod:`~stnh_tf.evaluation.mace`), the classical baselines and their tuning
(:mod:`~stnh_tf.evaluation.baselines`, :mod:`~stnh_tf.evaluation.baseline_tuning`), and the
benchmarks' library cores (:mod:`~stnh_tf.evaluation.benchmarks`,
:mod:`~stnh_tf.evaluation.data_benchmark`, :mod:`~stnh_tf.evaluation.search_stability`,
:mod:`~stnh_tf.evaluation.camera_pairs`)."""

__all__ = ["evaluate"]


def __getattr__(name):
    # ``evaluate`` is imported on first use, as the other packages' names are: importing one
    # module of the package (the baselines, say) loads only what that module needs.
    if name == "evaluate":
        from stnh_tf.evaluation.mace import evaluate
        return evaluate
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
