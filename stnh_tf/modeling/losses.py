"""The two STN-Homography losses and the corner-error metric, reduced per sample.

Each loss returns ``[B]`` (one value per sample) so Keras applies per-sample weights such as the
semi-supervised mask ``h_mask`` (a sample without ground truth ``H`` gets weight 0 on the L2 term
and still contributes its L1 term), then averages over the batch.
"""

from __future__ import annotations

import keras
from keras import ops

from stnh_tf import geometry


@keras.saving.register_keras_serializable(package="stnh_tf")
def h_bar_l2(y_true, y_pred):
    """L2 loss on the 8 regressed entries of ``H_bar``: mean squared error over them, ``[B]``."""
    y_true = ops.cast(y_true, "float32")
    y_pred = ops.cast(y_pred, "float32")
    return ops.mean(ops.square(y_pred - y_true), axis=-1)


@keras.saving.register_keras_serializable(package="stnh_tf")
def photometric_l1(y_true, y_pred):
    """L1 photometric loss between patch_a_warp and patch_a_t (``[B, h, w, C]`` in [0, 1]):
    mean absolute difference over pixels, ``[B]``."""
    y_true = ops.cast(y_true, "float32")
    y_pred = ops.cast(y_pred, "float32")
    return ops.mean(ops.abs(y_pred - y_true), axis=(1, 2, 3))


@keras.saving.register_keras_serializable(package="stnh_tf")
class MeanCornerError(keras.metrics.Mean):
    """MACE in pixels between predicted and true normalized ``H_bar`` (``[B, 8]``), both mapped back
    to ``S x S`` patch pixels with the paper's ``M`` (see :mod:`stnh_tf.geometry`)."""

    def __init__(self, name="mace", size: int = geometry.PATCH_SIZE, **kwargs):
        super().__init__(name=name, **kwargs)
        self.size = int(size)

    def update_state(self, y_true, y_pred, sample_weight=None):
        h_true = geometry.denormalize_homography(
            geometry.vector_to_matrix(ops.cast(y_true, "float32")), self.size, self.size)
        h_pred = geometry.denormalize_homography(
            geometry.vector_to_matrix(ops.cast(y_pred, "float32")), self.size, self.size)
        errors = geometry.corner_errors(h_pred, h_true, self.size)
        return super().update_state(errors, sample_weight=sample_weight)

    def get_config(self):
        return {**super().get_config(), "size": self.size}
