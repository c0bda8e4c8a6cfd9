"""Inference for users: :class:`~stnh_tf.inference.estimator.HomographyEstimator` (patches and
whole images), what it accepts (:mod:`~stnh_tf.inference.image_input`), where its models are
(:mod:`~stnh_tf.inference.model_files`), the ECC alignment of its search and refinement
(:mod:`~stnh_tf.inference.ecc`), two image files aligned (:mod:`~stnh_tf.inference.image_files`),
the SavedModel export (:mod:`~stnh_tf.inference.export`; what it computes:
:mod:`~stnh_tf.inference.serving`) and the shipped weights' card
(:mod:`~stnh_tf.inference.shipped_weights`).

    >>> from stnh_tf.inference import HomographyEstimator  # doctest: +SKIP
    >>> h_ba = HomographyEstimator.load().estimate(patch_a, patch_b)  # doctest: +SKIP
"""

from stnh_tf.inference.options import EstimateOptions, Thresholds

__all__ = ["HomographyEstimator", "EstimateOptions", "Thresholds", "Estimate"]


def __getattr__(name):
    # Imported on first use: the estimator imports Keras, and the pipeline OpenCV; the options,
    # checks, search and pipeline must load without a backend (tests/test_layout.py).
    if name == "HomographyEstimator":
        from stnh_tf.inference.estimator import HomographyEstimator
        return HomographyEstimator
    if name == "Estimate":
        from stnh_tf.inference.pipeline import Estimate
        return Estimate
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
