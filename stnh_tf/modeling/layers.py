"""Keras layers of STN-Homography: the projective spatial transformer (and where its warp is
defined, :class:`WarpValidity`), the Homography Merge, the per-patch input standardization, and
the HomographyNet baseline's :class:`OffsetsToHBar`: every custom layer of the package, each
registered with Keras (``import stnh_tf`` imports this module once Keras is imported).

They are written with ``keras.ops`` only, so they run under the TensorFlow and JAX backends.
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
    if (len(shape) == 2 and shape[-1] == 8) or (len(shape) == 3 and shape[-2:] == (3, 3)):
        return geometry.as_matrix(h)
    raise ValueError(f"{name} must have shape [B, 8] or [B, 3, 3]; received shape {shape}.")


@keras.saving.register_keras_serializable(package="stnh_tf")
class PatchStandardization(keras.layers.Layer):
    """Each image channel to zero mean and unit variance: ``(x - mean) / sqrt(var + epsilon)``
    over its ``h x w`` pixels, so a brightness offset or contrast gain of one patch of a pair
    does not reach the network.

    Input ``[B, h, w, C]``; output the same shape, float32 (statistics are computed in float32
    whatever the policy). A constant channel maps to zeros.

    >>> x = np.stack([np.linspace(0, 1, 16), 0.2 + 0.5 * np.linspace(0, 1, 16)], -1)
    >>> y = PatchStandardization()(x.reshape(1, 4, 4, 2).astype("float32"))
    >>> bool(np.allclose(y[..., 0], y[..., 1], atol=1e-2))
    True
    """

    def __init__(self, epsilon: float = 1e-4, **kwargs):
        kwargs.setdefault("dtype", "float32")
        super().__init__(**kwargs)
        if not epsilon > 0:
            raise ValueError(f"epsilon must be > 0; received {epsilon}.")
        self.epsilon = float(epsilon)

    def call(self, images):
        images = ops.cast(images, "float32")
        mean = ops.mean(images, axis=(1, 2), keepdims=True)
        var = ops.mean(ops.square(images - mean), axis=(1, 2), keepdims=True)
        return (images - mean) * ops.rsqrt(var + self.epsilon)

    def compute_output_shape(self, input_shape):
        return input_shape

    def get_config(self):
        return {**super().get_config(), "epsilon": self.epsilon}


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
    ``fill="reflect"`` samples the input mirrored about its border pixels outside it instead
    (``borderMode=cv2.BORDER_REFLECT_101``; see :data:`stnh_tf.geometry.FILLS`).
    Gradients flow to both the image and the homography (TensorFlow's built-in projective
    transform gives none to the transform). Coordinates are computed in at least float32 even
    under a mixed-precision policy.
    """

    def __init__(self, fill: str = "zeros", **kwargs):
        # No input autocast: under a mixed policy Keras would round the homography to the
        # compute dtype (bfloat16) before call(); call() casts to the coordinate dtype itself.
        kwargs.setdefault("autocast", False)
        super().__init__(**kwargs)
        self.fill = geometry.check_fill(fill)
        self.supports_masking = False

    def get_config(self):
        return {**super().get_config(), "fill": self.fill}

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
            raise ValueError(f"images must have shape [B, h, w, C]; received shape "
                             f"{tuple(images.shape)}.")
        height, width, channels = images.shape[1], images.shape[2], images.shape[3]
        if height is None or width is None or channels is None:
            raise ValueError(f"images need static h, w and C; received shape "
                             f"{tuple(images.shape)}.")
        dtype = self._coord_dtype()
        h_bar = _homography_matrix(ops.cast(h_bar, dtype))
        if (images.shape[0] is not None and h_bar.shape[0] is not None
                and images.shape[0] != h_bar.shape[0]):
            raise ValueError(f"images and homography batch sizes differ: {tuple(images.shape)} vs "
                             f"{tuple(h_bar.shape)}.")
        x, y = _source_points(h_bar, width, height, dtype)
        if self.fill == "reflect":
            x, y = _reflect_101(x, width), _reflect_101(y, height)
        values = _bilinear_sample(ops.cast(images, dtype), x, y)  # [B, N, C]
        out = ops.reshape(values, (-1, height, width, channels))
        return ops.cast(out, self.compute_dtype)

    def compute_output_shape(self, input_shape):
        return tuple(input_shape[0])


def _source_points(h_bar, width: int, height: int, dtype, in_front: bool = False):
    """Where the warp samples: ``(x, y)``, each ``[B, h * w]`` in ``dtype``, the pixel
    coordinates ``H_ba @ p`` in the input of every output pixel ``p`` (row-major), with
    ``H_ba = inv(M) @ H_bar @ M`` and ``h_bar`` ``[B, 3, 3]`` normalized (``M`` of ``width`` x
    ``height``). The one computation of :class:`SpatialTransformer` and :class:`WarpValidity`.
    With ``in_front``, also the bool ``[B, h * w]`` of the points on the same side of the
    homography's horizon as the output's centre (``w`` of the sign it has there: a point behind
    it has no place in the input, though the division gives it one)."""
    m = geometry.normalization_matrix(width, height)
    # H_pix = inv(M) @ H_bar @ M, applied to the pixel grid of the output; not scaled to
    # [2,2] = 1 (geometry.denormalize_homography does), which would move the w threshold below.
    m = ops.convert_to_tensor(m.astype(dtype))
    m_inv = ops.convert_to_tensor(
        np.linalg.inv(geometry.normalization_matrix(width, height)).astype(dtype))
    h_pix = ops.matmul(ops.matmul(m_inv, h_bar), m)  # [B, 3, 3]

    xs, ys = np.meshgrid(np.arange(width), np.arange(height))
    grid = np.stack([xs.ravel(), ys.ravel(), np.ones(height * width)], axis=0)
    grid = ops.convert_to_tensor(grid.astype(dtype))  # [3, N]
    src = ops.matmul(h_pix, grid)  # [B, 3, N]
    # A point on the homography's line at infinity (w = 0) is sent far away, not to inf/NaN,
    # and the gradient stays finite (the safe denominator is chosen before dividing).
    w = src[:, 2]
    safe = ops.where(ops.abs(w) < 1e-6, 1e-6, w)
    if not in_front:
        return src[:, 0] / safe, src[:, 1] / safe
    centre = np.array([[(width - 1) / 2], [(height - 1) / 2], [1.0]], dtype)
    side = ops.sign(ops.matmul(h_pix, ops.convert_to_tensor(centre))[:, 2])  # [B, 1]
    return src[:, 0] / safe, src[:, 1] / safe, w * side > 0


def _reflect_101(x, size: int):
    """Pixel coordinates ``x`` mirrored into ``[0, size - 1]`` about the first and last pixel
    centres (period ``2 (size - 1)``; non-finite -> 0). Bilinear sampling at the mirrored
    coordinate equals OpenCV's ``BORDER_REFLECT_101``, which mirrors the neighbour indices: the
    linear interpolant of the mirrored pixels is the mirror image of the interpolant."""
    if size == 1:
        return ops.zeros_like(x)
    last = float(size - 1)
    x = ops.where(ops.isfinite(x), x, 0.0)
    return last - ops.abs(ops.mod(x, 2.0 * last) - last)


def _bilinear_sample(images, x, y):
    """Bilinear sample ``images`` ``[B, h, w, C]`` at float pixel coords ``x, y`` ``[B, N]``.

    Each of the four neighbours outside the image contributes zero (OpenCV's BORDER_CONSTANT 0).
    Returns ``[B, N, C]``.

    Implementation: the image is padded with one ring of zeros, so every out-of-range neighbour
    index can be clipped onto a zero pad cell (no masks); the four neighbours are gathered from
    the flattened ``[B * (h+2) * (w+2), C]`` tensor with global row indices, and combined as two
    horizontal lerps and one vertical lerp (fewer full-size element-wise ops, forward and backward).
    """
    height, width, channels = images.shape[1], images.shape[2], images.shape[3]
    pad_w, pad_h = width + 2, height + 2
    padded = ops.pad(images, [[0, 0], [1, 1], [1, 1], [0, 0]])
    flat = ops.reshape(padded, (-1, channels))  # [B * pad_h * pad_w, C]
    # Points beyond one pixel outside the image sample only zeros, so clamping them to
    # [-2, size + 1] changes no value; it keeps far-away (or infinite, from a degenerate H)
    # coordinates finite, so the weights below never become inf - inf = NaN.
    finite = ops.logical_and(ops.isfinite(x), ops.isfinite(y))
    x = ops.clip(ops.where(finite, x, -2.0), -2.0, float(width + 1))
    y = ops.clip(ops.where(finite, y, -2.0), -2.0, float(height + 1))
    x0 = ops.floor(x)
    y0 = ops.floor(y)
    fx = ops.expand_dims(x - x0, -1)  # [B, N, 1]
    fy = ops.expand_dims(y - y0, -1)
    # Shift into the padded frame; any index outside [1, w] (resp. [1, h]) lands on the zero ring.
    xi = ops.cast(x0, "int32") + 1
    yi = ops.cast(y0, "int32") + 1
    x_left = ops.clip(xi, 0, pad_w - 1)
    x_right = ops.clip(xi + 1, 0, pad_w - 1)
    batch_offset = ops.reshape(ops.arange(ops.shape(images)[0], dtype="int32") * (pad_h * pad_w),
                               (-1, 1))
    row_top = ops.clip(yi, 0, pad_h - 1) * pad_w + batch_offset  # [B, N]
    row_bottom = ops.clip(yi + 1, 0, pad_h - 1) * pad_w + batch_offset
    v00 = ops.take(flat, row_top + x_left, axis=0)  # [B, N, C]
    v01 = ops.take(flat, row_top + x_right, axis=0)
    v10 = ops.take(flat, row_bottom + x_left, axis=0)
    v11 = ops.take(flat, row_bottom + x_right, axis=0)
    top = v00 + fx * (v01 - v00)
    bottom = v10 + fx * (v11 - v10)
    return top + fy * (bottom - top)


@keras.saving.register_keras_serializable(package="stnh_tf")
class WarpValidity(keras.layers.Layer):
    """Where :class:`SpatialTransformer`'s warp (``fill="zeros"``) is defined: 1 at the output
    pixels ``p`` whose ``H_ba @ p`` falls inside the input, ``0 <= x <= w - 1`` and
    ``0 <= y <= h - 1`` (every bilinear neighbour with a weight lies in the image, so the warp
    there is made of input pixels alone, none of the zeros outside), on the output centre's
    side of the homography's horizon (a point behind it, divided by its negative ``w``, lands
    somewhere in the input too, but no camera sees it there), else 0.

    Called as ``WarpValidity()([images, h_bar])`` with :class:`SpatialTransformer`'s inputs
    (``images`` ``[B, h, w, C]`` gives the size; ``h_bar`` ``[B, 8]`` or ``[B, 3, 3]``); returns
    ``[B, h, w, 1]`` float32 of 0 and 1, with no gradient (a mask, constant for the loss that
    uses it). The same coordinates as the warp (:func:`_source_points`).

    >>> shift = np.array([[1, 0, 2 * 3 / 8, 0, 1, 0, 0, 0]], "float32")  # H_ba: x + 3 px
    >>> mask = WarpValidity()([np.zeros((1, 8, 8, 1), "float32"), shift])
    >>> np.asarray(mask)[0, 0, :, 0].tolist()
    [1.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0]
    """

    def __init__(self, **kwargs):
        kwargs.setdefault("autocast", False)  # coordinates in float32 under mixed precision
        kwargs.setdefault("dtype", "float32")
        super().__init__(**kwargs)

    def call(self, inputs):
        if not isinstance(inputs, (list, tuple)) or len(inputs) != 2:
            raise ValueError("WarpValidity expects [images, homography].")
        images, h_bar = inputs
        if len(images.shape) != 4 or images.shape[1] is None or images.shape[2] is None:
            raise ValueError(f"images must have shape [B, h, w, C] with static h and w; received "
                             f"shape {tuple(images.shape)}.")
        height, width = images.shape[1], images.shape[2]
        h_bar = _homography_matrix(ops.cast(h_bar, "float32"))
        x, y, in_front = _source_points(h_bar, width, height, "float32", in_front=True)
        inside = ops.logical_and(ops.logical_and(x >= 0.0, x <= float(width - 1)),
                                 ops.logical_and(y >= 0.0, y <= float(height - 1)))
        inside = ops.logical_and(inside, in_front)  # (behind the horizon: no input pixel)
        mask = ops.stop_gradient(ops.cast(inside, "float32"))
        return ops.reshape(mask, (-1, height, width, 1))

    def compute_output_shape(self, input_shape):
        return tuple(input_shape[0][:3]) + (1,)


@keras.saving.register_keras_serializable(package="stnh_tf")
class HomographyMerge(keras.layers.Layer):
    """The paper's Tensor Homography Merge layer: ``H_k = H_{k-1} @ H_k'``, rescaled to
    ``[2,2] = 1``.

    Called as ``HomographyMerge()([h_prev, h_residual])`` with both ``[B, 8]`` (or ``[B, 3, 3]``)
    normalized homographies in the ``H_ba`` direction: ``h_prev`` warps the original patch_a to
    patch_a_warp_{k-1}; ``h_residual`` maps patch_b into patch_a_warp_{k-1}. Returns ``[B, 8]``
    (``[B, 3, 3]`` if ``output_matrix=True``), differentiable in both inputs.
    """

    def __init__(self, output_matrix: bool = False, **kwargs):
        kwargs.setdefault("autocast", False)  # keep float32 homographies under mixed precision
        super().__init__(**kwargs)
        self.output_matrix = bool(output_matrix)

    def call(self, inputs):
        if not isinstance(inputs, (list, tuple)) or len(inputs) != 2:
            raise ValueError("HomographyMerge expects [h_prev, h_residual].")
        dtype = self.compute_dtype if self.compute_dtype not in _LOW_PRECISION else "float32"
        h_prev = _homography_matrix(ops.cast(inputs[0], dtype), "h_prev")
        h_res = _homography_matrix(ops.cast(inputs[1], dtype), "h_residual")
        product = ops.matmul(h_prev, h_res)
        # [2, 2] = 0 (the patch centre sent to infinity): a safe denominator, as the warp's, so
        # that one degenerate pair does not make the batch's loss and gradients NaN
        d = product[..., 2:3, 2:3]
        merged = product / ops.where(ops.abs(d) < 1e-6, ops.where(d < 0, -1e-6, 1e-6), d)
        return merged if self.output_matrix else geometry.matrix_to_vector(merged)

    def compute_output_shape(self, input_shape):
        batch = input_shape[0][0]
        return (batch, 3, 3) if self.output_matrix else (batch, 8)

    def get_config(self):
        config = super().get_config()
        config["output_matrix"] = self.output_matrix
        return config


HOMOGRAPHYNET_SCALE = float(geometry.MAX_PERTURBATION)
"""What :class:`OffsetsToHBar` multiplies the HomographyNet baseline's outputs by: the
perturbation range, 32 px (its targets, the corners' offsets / 32, lie in ``[-1, 1]``)."""


@keras.saving.register_keras_serializable(package="stnh_tf")
class OffsetsToHBar(keras.layers.Layer):
    """Four-point offsets (scaled by 1/32) ``[B, 8]`` -> normalized ``H_bar`` ``[B, 8]``.

    Lets the HomographyNet baseline be trained and evaluated through the same ``h_bar`` interface:
    offsets are ``H_ba @ c - c`` for the corners of :func:`geometry.patch_corners`.
    """

    def __init__(self, size: int = geometry.PATCH_SIZE, scale: float = HOMOGRAPHYNET_SCALE,
                 **kwargs):
        kwargs.setdefault("dtype", "float32")
        super().__init__(**kwargs)
        self.size, self.scale = int(size), float(scale)

    def call(self, offsets):
        offsets = ops.cast(offsets, "float32") * self.scale
        h = geometry.offsets_to_homography(ops.reshape(offsets, (-1, 4, 2)), self.size)
        h_bar = geometry.normalize_homography(h, self.size, self.size)
        return ops.reshape(h_bar, (-1, 9))[:, :8]

    def get_config(self):
        return {**super().get_config(), "size": self.size, "scale": self.scale}
