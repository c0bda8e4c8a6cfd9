"""Inference for users: :class:`~stnh_tf.inference.estimator.HomographyEstimator` (patches and
whole images), what it accepts (:mod:`~stnh_tf.inference.image_input`), where its models are
(:mod:`~stnh_tf.inference.model_files`), the ECC alignment of its search and refinement
(:mod:`~stnh_tf.inference.ecc`), two image files aligned (:mod:`~stnh_tf.inference.image_files`),
the SavedModel export (:mod:`~stnh_tf.inference.export`) and the shipped weights' card
(:mod:`~stnh_tf.inference.shipped_weights`).

    >>> from stnh_tf.inference import HomographyEstimator  # doctest: +SKIP
    >>> h_ba = HomographyEstimator.load().estimate(patch_a, patch_b)  # doctest: +SKIP
"""

from stnh_tf import _compat

from stnh_tf.inference.options import EstimateOptions, Thresholds  # noqa: E402

__all__ = ["HomographyEstimator", "EstimateOptions", "Thresholds", "Estimate"]

# Before 0.2 ``stnh_tf.inference`` was the estimator's module: its names stay reachable here.
__getattr__ = _compat.delegate(__name__, "stnh_tf.inference.estimator")
