"""What an exported SavedModel computes (:mod:`stnh_tf.inference.export` writes it): the network's
composed estimate of :meth:`~stnh_tf.inference.estimator.HomographyEstimator.estimate` with
``EstimateOptions.network_only()``, as one TensorFlow function on uint8 patches
(:func:`serving_function`), its inputs checked in the graph (:func:`checked_inputs`) and the
estimator's degenerate-prediction rule applied between the stages
(:func:`kept_unless_degenerate`). Frames and the output's direction: :mod:`stnh_tf.geometry`
(pixel ``H_ba``, patch_b -> patch_a, ``[2, 2] = 1``).
"""

from __future__ import annotations

import numpy as np

from stnh_tf import geometry

SIGNATURE = "serving_default"
OUTPUT = "homography"


def checked_inputs(patch_a, patch_b):
    """``patch_a``, ``patch_b`` after run-time checks in the graph: each of shape
    ``[B, 128, 128, 1]`` (``tf.ensure_shape``) and the same ``B >= 1`` for both (an empty batch
    is refused as ``estimate`` refuses it); anything else raises ``InvalidArgumentError`` when
    the function runs. (A SavedModel signature's declared input
    shape is not enforced when it is called, and the graph is optimized for that shape: without
    these checks a ``[1, 128, 128]`` request aborted the serving process and a ``[1, 64, 64, 1]``
    one returned a homography.) The dtype (uint8) is checked by the signature itself."""
    import tensorflow as tf

    s = geometry.PATCH_SIZE
    patch_a = tf.ensure_shape(patch_a, [None, s, s, 1], name="check_patch_a")
    patch_b = tf.ensure_shape(patch_b, [None, s, s, 1], name="check_patch_b")
    same = tf.debugging.assert_equal(tf.shape(patch_a)[0], tf.shape(patch_b)[0],
                                     message="patch_a and patch_b must hold the same number of "
                                             "patches")
    some = tf.debugging.assert_positive(tf.shape(patch_a)[0],
                                        message="patch_a is an empty batch: patch_a and patch_b "
                                                "must hold at least one patch each")
    with tf.control_dependencies([same, some]):
        return tf.identity(patch_a), tf.identity(patch_b)


def kept_unless_degenerate(before, proposed):
    """The degenerate-prediction rule of :meth:`HomographyEstimator.estimate` in the graph
    (:func:`stnh_tf.hierarchy.rejection_reason`'s ``"non_finite"`` and ``"singular"``, with its
    thresholds): per pair, ``proposed`` (normalized ``[B, 3, 3]``, the estimate composed with a
    stage's prediction) scaled to ``[2, 2] = 1`` where its pixel homography is finite with
    ``|H[2, 2]| >= MIN_SCALE`` and, so scaled, ``|det H| >= MIN_DET`` and a homogeneous
    coordinate above ``MIN_W`` at the four patch corners (none maps to infinity or behind the
    camera); ``before`` (normalized ``[B, 3, 3]``, ``[2, 2] = 1``: the estimate before that
    stage) elsewhere."""
    from keras import ops

    from stnh_tf import hierarchy

    s = geometry.PATCH_SIZE
    m = geometry.normalization_matrix(s, s)
    m_inv = ops.convert_to_tensor(np.linalg.inv(m), "float32")
    m = ops.convert_to_tensor(m, "float32")
    corners = ops.convert_to_tensor(  # [3, 4]: the patch corners, homogeneous, as columns
        np.concatenate([geometry.patch_corners(s), np.ones((4, 1))], axis=1).T, "float32")
    pixel = ops.matmul(ops.matmul(m_inv, proposed), m)
    scale = pixel[:, 2, 2]
    finite = ops.logical_and(ops.all(ops.isfinite(pixel), axis=(1, 2)),
                             ops.abs(scale) >= hierarchy.MIN_SCALE)
    unit = pixel / scale[:, None, None]
    w = ops.matmul(unit, corners)[:, 2, :]
    kept = ops.logical_and(finite, ops.logical_and(ops.abs(ops.det(unit)) >= hierarchy.MIN_DET,
                                                   ops.all(w > hierarchy.MIN_W, axis=1)))
    return ops.where(kept[:, None, None], geometry.scale_to_unit(proposed), before)


def serving_function(estimator):
    """A TensorFlow function ``(patch_a, patch_b) -> {"homography": [B, 3, 3] float32}`` on uint8
    ``[B, 128, 128, 1]`` patches, computing the estimator's ``H_ba`` with its Keras models."""
    from keras import ops

    from stnh_tf.inference.options import EstimateOptions
    from stnh_tf.modeling.layers import SpatialTransformer

    stages, outputs = estimator.stages, estimator.output_names
    warp = SpatialTransformer(fill=EstimateOptions.network_only().fill, dtype="float32",
                              name="hierarchy_warp")

    def serve(patch_a, patch_b):
        patch_a, patch_b = checked_inputs(patch_a, patch_b)
        a = ops.cast(patch_a, "float32") / 255.0
        b = ops.cast(patch_b, "float32") / 255.0
        total, current = None, a
        for model, name in zip(stages, outputs):
            if total is not None:
                current = warp([a, total])  # patch_a(H_1 ... H_{k-1} p), mirrored outside
            h8 = ops.cast(model({"patch_a": current, "patch_b": b}, training=False)[name],
                          "float32")
            h_bar = geometry.vector_to_matrix(h8)
            if total is None:  # the estimate before the first stage: the identity
                total = ops.broadcast_to(ops.eye(3, dtype="float32"), ops.shape(h_bar))
            total = kept_unless_degenerate(total, ops.matmul(total, h_bar))
        return {OUTPUT: geometry.denormalize_homography(total)}

    serve.tracked = list(stages)  # the warp layer holds no variables
    return serve
