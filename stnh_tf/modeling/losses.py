"""The two STN-Homography losses and the corner-error metric, reduced per sample.

Each loss returns ``[B]`` (one value per sample) so Keras applies per-sample weights such as the
semi-supervised mask ``h_mask``, then averages over the batch. A pair with ground truth (``h_mask``
1) trains on :func:`h_bar_l2` and on :func:`photometric_l1` against ``patch_a_t`` (the paper's
losses); a pair without (``h_mask`` 0, in a run that has such pairs) carries nothing made from
its ``H`` and trains on :func:`photometric_l1_valid` alone, ``patch_a_warp`` against ``patch_b``
where the warp is defined (docs/training.md, "Training with missing labels").
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
def photometric_l1_valid(y_true, y_pred):
    """The L1 photometric loss of a pair without ground truth: ``patch_a_warp`` against
    ``patch_b`` over the pixels where the warp is defined, ``[B]``.

    ``y_true``: patch_b ``[B, h, w, 1]`` in [0, 1]. ``y_pred``: ``[B, h, w, 2]``, channel 0
    ``patch_a_warp`` (patch_a warped by the predicted ``H_ba``), channel 1 its validity mask
    ``V`` (:class:`~stnh_tf.modeling.layers.WarpValidity`: 1 where ``H_ba @ p`` falls inside
    patch_a). Per sample ``sum_p V |patch_a_warp - patch_b| / max(sum_p V, 1)``: the mean
    absolute difference over the valid pixels (normalized by the mask's area, so a pair whose
    warp covers all of patch_b gives :func:`photometric_l1`'s mean over every pixel; a pair
    whose warp leaves patch_a entirely gives 0). ``V`` carries no gradient. No field made from
    the pair's true ``H`` enters.

    >>> import numpy as np
    >>> b = np.full((1, 2, 2, 1), 0.5, "float32")
    >>> warp = np.array([0.25, 0.5, 0.0, 0.0], "float32").reshape(1, 2, 2, 1)
    >>> valid = np.array([1, 1, 0, 0], "float32").reshape(1, 2, 2, 1)
    >>> float(photometric_l1_valid(b, np.concatenate([warp, valid], -1))[0])  # (0.25 + 0) / 2
    0.125
    """
    y_true = ops.cast(y_true, "float32")
    y_pred = ops.cast(y_pred, "float32")
    warp, valid = y_pred[..., :1], y_pred[..., 1:]
    area = ops.sum(valid, axis=(1, 2, 3))
    return ops.sum(valid * ops.abs(warp - y_true), axis=(1, 2, 3)) / ops.maximum(area, 1.0)


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
