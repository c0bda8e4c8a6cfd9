"""Keras layers of STN-Homography: the projective spatial transformer and the Homography Merge.

Both are written with ``keras.ops`` only, so they run under the TensorFlow and JAX backends.
Conventions (direction, the paper's ``M``) are those of :mod:`stnh_tf.geometry`.
"""

from __future__ import annotations

import keras
import numpy as np
from keras import ops

from stnh_tf import geometry

_LOW_PRECISION = ("float16", "bfloat16")


def _homography_matrix(h, name="homography"):
    shape = tuple(h.shape)
    if len(shape) == 2 and shape[-1] == 8:
        ones = ops.ones_like(h[:, :1])
        return ops.reshape(ops.concatenate([h, ones], axis=-1), (-1, 3, 3))
    if len(shape) == 3 and shape[-2:] == (3, 3):
        return h
    raise ValueError(f"{name} must have shape [B, 8] or [B, 3, 3]; received shape {shape}.")


@keras.saving.register_keras_serializable(package="stnh_tf")
class SpatialTransformer(keras.layers.Layer):
    """Differentiable projective warp driven by the normalized homography ``H_bar``.

    Called as ``SpatialTransformer()([images, h_bar])``:

    * ``images``: ``[B, h, w, C]``.
    * ``h_bar``: ``[B, 8]`` or ``[B, 3, 3]``, the normalized ``H_ba`` (``M`` built from this
      image's own ``w`` and ``h``), mapping output (patch_b) coordinates to input (patch_a)
      coordinates.

    Returns ``[B, h, w, C]`` with ``out(p) = images(H_ba @ p)``, ``H_ba = inv(M) @ H_bar @ M``,
    sampled bilinearly, zero outside the input: the same warp as
    ``cv2.warpPerspective(image, H_ba, (w, h), flags=WARP_INVERSE_MAP | INTER_LINEAR)``.
    Gradients flow to both the image and the homography (TensorFlow's built-in projective
    transform gives none to the transform). Coordinates are computed in at least float32 even
    under a mixed-precision policy.
    """

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.supports_masking = False

    def _coord_dtype(self):
        dtype = self.compute_dtype
        return "float32" if dtype in _LOW_PRECISION else dtype

    def call(self, inputs):
        if not isinstance(inputs, (list, tuple)) or len(inputs) != 2:
            raise ValueError("SpatialTransformer expects [images, homography]; received "
                             f"{type(inputs).__name__} of length "
                             f"{len(inputs) if isinstance(inputs, (list, tuple)) else 'n/a'}.")
        images, h_bar = inputs
        if len(images.shape) != 4:
            raise ValueError(f"images must have shape [B, h, w, C]; received shape {tuple(images.shape)}.")
        height, width, channels = images.shape[1], images.shape[2], images.shape[3]
        if height is None or width is None or channels is None:
            raise ValueError(f"images need static h, w and C; received shape {tuple(images.shape)}.")
        dtype = self._coord_dtype()
        h_bar = _homography_matrix(ops.cast(h_bar, dtype))
        if images.shape[0] is not None and h_bar.shape[0] is not None and images.shape[0] != h_bar.shape[0]:
            raise ValueError(f"images and homography batch sizes differ: {tuple(images.shape)} vs "
                             f"{tuple(h_bar.shape)}.")
        m = geometry.normalization_matrix(width, height)
        # H_pix = inv(M) @ H_bar @ M, applied to the pixel grid of the output.
        m = ops.convert_to_tensor(m.astype(dtype))
        m_inv = ops.convert_to_tensor(np.linalg.inv(geometry.normalization_matrix(width, height)).astype(dtype))
        h_pix = ops.matmul(ops.matmul(m_inv, h_bar), m)  # [B, 3, 3]

        xs, ys = np.meshgrid(np.arange(width), np.arange(height))
        grid = np.stack([xs.ravel(), ys.ravel(), np.ones(height * width)], axis=0)
        grid = ops.convert_to_tensor(grid.astype(dtype))  # [3, N]
        src = ops.matmul(h_pix, grid)  # [B, 3, N]
        x = src[:, 0] / src[:, 2]
        y = src[:, 1] / src[:, 2]
        values = _bilinear_sample(ops.cast(images, dtype), x, y)  # [B, N, C]
        out = ops.reshape(values, (-1, height, width, channels))
        return ops.cast(out, self.compute_dtype)

    def compute_output_shape(self, input_shape):
        return tuple(input_shape[0])


def _bilinear_sample(images, x, y):
    """Bilinear sample ``images`` ``[B, h, w, C]`` at float pixel coords ``x, y`` ``[B, N]``.

    Each of the four neighbours outside the image contributes zero (OpenCV's BORDER_CONSTANT 0).
    Returns ``[B, N, C]``.
    """
    height, width, channels = images.shape[1], images.shape[2], images.shape[3]
    flat = ops.reshape(images, (-1, height * width, channels))
    x0 = ops.floor(x)
    y0 = ops.floor(y)
    wx1 = x - x0
    wy1 = y - y0
    wx0 = 1.0 - wx1
    wy0 = 1.0 - wy1
    x0i = ops.cast(x0, "int32")
    y0i = ops.cast(y0, "int32")
    out = None
    for dx, wx in ((0, wx0), (1, wx1)):
        for dy, wy in ((0, wy0), (1, wy1)):
            xi = x0i + dx
            yi = y0i + dy
            inside = (xi >= 0) & (xi < width) & (yi >= 0) & (yi < height)
            idx = ops.clip(yi, 0, height - 1) * width + ops.clip(xi, 0, width - 1)  # [B, N]
            gathered = ops.take_along_axis(flat, ops.expand_dims(idx, -1), axis=1)  # [B, N, C]
            weight = wx * wy * ops.cast(inside, x.dtype)
            term = gathered * ops.expand_dims(weight, -1)
            out = term if out is None else out + term
    return out


@keras.saving.register_keras_serializable(package="stnh_tf")
class HomographyMerge(keras.layers.Layer):
    """The paper's Tensor Homography Merge layer: ``H_k = H_{k-1} @ H_k'``, rescaled to ``[2,2] = 1``.

    Called as ``HomographyMerge()([h_prev, h_residual])`` with both ``[B, 8]`` (or ``[B, 3, 3]``)
    normalized homographies in the ``H_ba`` direction: ``h_prev`` warps the original patch_a to
    patch_a_warp_{k-1}; ``h_residual`` maps patch_b into patch_a_warp_{k-1}. Returns ``[B, 8]``
    (``[B, 3, 3]`` if ``output_matrix=True``), differentiable in both inputs.
    """

    def __init__(self, output_matrix: bool = False, **kwargs):
        super().__init__(**kwargs)
        self.output_matrix = bool(output_matrix)

    def call(self, inputs):
        if not isinstance(inputs, (list, tuple)) or len(inputs) != 2:
            raise ValueError("HomographyMerge expects [h_prev, h_residual].")
        dtype = self.compute_dtype if self.compute_dtype not in _LOW_PRECISION else "float32"
        h_prev = _homography_matrix(ops.cast(inputs[0], dtype), "h_prev")
        h_res = _homography_matrix(ops.cast(inputs[1], dtype), "h_residual")
        merged = ops.matmul(h_prev, h_res)
        merged = merged / merged[:, 2:3, 2:3]
        if self.output_matrix:
            return merged
        return ops.reshape(merged, (-1, 9))[:, :8]

    def compute_output_shape(self, input_shape):
        batch = input_shape[0][0]
        return (batch, 3, 3) if self.output_matrix else (batch, 8)

    def get_config(self):
        config = super().get_config()
        config["output_matrix"] = self.output_matrix
        return config
