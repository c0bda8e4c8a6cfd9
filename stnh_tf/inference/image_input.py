"""What :class:`stnh_tf.inference.estimator.HomographyEstimator` accepts: patches and images checked
and converted to the models' input, and the resizing rule of ``estimate_images`` with its maps
between pixel frames.

Resizing rule of :meth:`~stnh_tf.inference.estimator.HomographyEstimator.estimate_images`. The
models were trained on 128 x 128 crops of 320 x 240 images with corners moved by up to 32 px. Each
image (any size, any aspect ratio; image_a and image_b need not have the same size) is converted to
grayscale (ITU-R 601 luma; an alpha channel is composited onto black), resized to 320 x 240
(aspect ratio not preserved; ``cv2.INTER_AREA`` when both sides shrink, else
``cv2.INTER_LINEAR``: the training data's rule), and the central 128 x 128 square (top-left
corner ``(96, 56)``) of each is the patch pair. A uint8 image is made gray and resized in uint8,
with the training data's own functions (:func:`stnh_tf.data.sources.to_gray_uint8` and
:func:`~stnh_tf.data.sources.resize_to_protocol`), before anything is converted to float: its
patches are the pixels ``data_prep.make_dataset`` would crop from it, and a large image costs
one uint8 gray copy at most (a 10000 x 10000 colour image converted to float first cost 2 GB).
A float image (in [0, 1]) is converted and resized in float32.

Images too thin for the patch are refused (:func:`check_image_size`): the central 128 x 128
square of the 320 x 240 version covers ``0.4 w x 0.533 h`` pixels of a ``w x h`` image, and
below :data:`~stnh_tf.data.image_checks.MIN_PATCH_SPAN_PX` = 8 of them on a side (``w < 20`` or
``h < 15``) the patch is a handful of pixels (one row of a ``5120 x 1`` image) stretched 16 times
or more: its motion along that side is not observable, and the estimate is meaningless (the
shipped weights' errors by image size: ``docs/small_images.json``, written by
``python -m experiments.benchmark_small_images``).

The patch estimate is mapped back with ``H_img = inv(S_a) @ T @ H_patch @ inv(T) @ S_b`` where
``T`` is the translation by ``(96, 56)`` and ``S_x`` maps pixels of image x to pixels of its
320 x 240 version. With pixel centres at integer coordinates a resize by ``s`` maps
``x -> s (x + 0.5) - 0.5`` (exactly what ``cv2.resize`` does), so ``S_x`` has that half-pixel
offset. The result is meaningful when, in
the 320 x 240 frame, the motion between the images is of the size the model was trained on
(corners of the central square moving by up to about 32 px, i.e. 10% of the width) and the
central square holds texture.

The feature start's images (:func:`input_image` with ``feature_image=True``, issue 79). The
feature start (:mod:`stnh_tf.inference.features`), where the work images' start gives no
confirmed estimate, matches SIFT keypoints on each image at its own resolution, where the detail
a wide zoom needs is still there: the gray image (the same gray
version as above) as it is where its long side is at most :data:`FEATURE_MAX_SIDE`, else resized
down with ``cv2.INTER_AREA`` to that long side (:func:`feature_size`; never enlarged). An image
that fits in 320 x 240 (``w <= 320`` and ``h <= 240``) has no feature image of its own: its
feature start runs on its work image, as before. The feature start's ``H_ba`` is brought into the
work frame by ``S_a @ inv(F_a) @ H_feature @ F_b @ inv(S_b)``, ``F_x`` the map from pixels of
image x to pixels of its feature image (:func:`work_from_feature`; both ``S_x`` and ``F_x`` are
:func:`resize_matrix`, with the half-pixel offset).
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from stnh_tf import geometry, pixels
from stnh_tf.data.sources import check_image_size, resize_matrix, resize_to_protocol

PATCH_SIZE = geometry.PATCH_SIZE
WORK_SIZE = (geometry.IMAGE_WIDTH, geometry.IMAGE_HEIGHT)
"""``(width, height)`` every image is resized to by ``estimate_images``."""
PATCH_ORIGIN = ((WORK_SIZE[0] - PATCH_SIZE) // 2, (WORK_SIZE[1] - PATCH_SIZE) // 2)
"""Top-left corner ``(x0, y0) = (96, 56)`` of the central patch in the 320 x 240 frame."""
FEATURE_MAX_SIDE = 1600
"""The longest side (px) of an image the feature start matches (:func:`feature_size`)."""


# --------------------------------------------------------------------------------------------
# Input checking
# --------------------------------------------------------------------------------------------
def _to_unit_float(x, name, what):
    """uint8 (0..255) or float in [0, 1] -> float32 in [0, 1]."""
    _check_pixel_values(x, name, what)
    return pixels.to_unit(x) if x.dtype == np.uint8 else x.astype(np.float32)


def _check_pixel_values(x, name, what):
    """``ValueError`` unless ``x`` is uint8, or floating point with every value in [0, 1] (checked
    by its minimum and maximum: no temporary of its size unless it fails)."""
    if x.dtype == np.uint8:
        return
    if np.issubdtype(x.dtype, np.floating):
        low, high = (x.min(), x.max()) if x.size else (0.0, 0.0)
        if not (np.isfinite(low) and np.isfinite(high) and low >= 0.0 and high <= 1.0):
            finite = np.isfinite(x)
            seen = (f"values in [{x[finite].min()}, {x[finite].max()}]" if finite.any() else
                    "no finite values")
            if not finite.all():
                seen += f" and {int(x.size - finite.sum())} NaN/inf"
            raise ValueError(f"{name}: floating-point {what} must lie in [0, 1] (use uint8 for "
                             f"0..255); received {seen} with shape {x.shape}.")
        return
    raise ValueError(f"{name}: {what} must be uint8 (0..255) or floating point in [0, 1]; "
                     f"received dtype {x.dtype} with shape {x.shape}.")


def _as_array(x, name):
    if x is None:
        raise ValueError(f"{name} is None; expected an image array.")
    try:
        arr = np.asarray(x)
    except Exception as e:  # ragged nested lists and the like
        raise ValueError(f"{name} is not an array ({type(x).__name__}): {e}") from None
    if arr.dtype == object or arr.dtype.kind in "USV":
        raise ValueError(f"{name} is not a numeric image array; received dtype {arr.dtype} with "
                         f"shape {arr.shape}.")
    return arr


def check_patch_pair(patch_a, patch_b):
    """Both of a pair of patch batches checked by :func:`check_patches` (``[B, S, S, 1]`` each),
    and ``ValueError`` unless they hold the same number of patches."""
    a, b = check_patches(patch_a, "patch_a"), check_patches(patch_b, "patch_b")
    if len(a) != len(b):
        raise ValueError(f"patch_a and patch_b must hold the same number of patches; received "
                         f"shapes {np.shape(patch_a)} and {np.shape(patch_b)}.")
    return a, b


def prepare_patches(x, name="patch") -> np.ndarray:
    """Patches ``[S, S]``, ``[S, S, 1]``, ``[B, S, S]`` or ``[B, S, S, 1]`` (S = 128; uint8 0..255
    or float in [0, 1]) -> float32 ``[B, S, S, 1]`` in [0, 1]. Anything else raises
    ``ValueError``."""
    return unit_patches(check_patches(x, name))


def unit_patches(batch) -> np.ndarray:
    """A batch that :func:`check_patches` accepted (or any part of it) as float32 in [0, 1]."""
    if batch.dtype == np.uint8:
        return pixels.to_unit(batch)
    return np.asarray(batch, np.float32)


def check_patches(x, name="patch") -> np.ndarray:
    """:func:`prepare_patches` without the conversion: the patches as ``[B, S, S, 1]`` (a view of
    ``x`` where it can be), uint8 or floating point, checked (floats in [0, 1]: no full-size
    temporary). Raises ``ValueError`` as :func:`prepare_patches`."""
    s = PATCH_SIZE
    arr = _as_array(x, name)
    shape = tuple(arr.shape)
    if len(shape) == 2:
        core = shape
        batch = (1,) + shape
    elif len(shape) == 3 and shape[:2] == (s, s) and shape[2] in (1, 3, 4):
        if shape[2] != 1:
            raise ValueError(f"{name} must be grayscale ([{s}, {s}] or [{s}, {s}, 1]); received "
                             f"shape {shape} (convert colour images to gray first).")
        core = shape[:2]
        batch = (1,) + core
    elif len(shape) == 3:
        core = shape[1:]
        batch = shape
    elif len(shape) == 4 and shape[-1] == 1:
        core = shape[1:3]
        batch = shape[:3]
    else:
        raise ValueError(f"{name} must have shape [{s}, {s}], [{s}, {s}, 1], [B, {s}, {s}] or "
                         f"[B, {s}, {s}, 1]; received shape {shape}.")
    if core != (s, s):
        raise ValueError(f"{name} must be {s}x{s} patches ([{s}, {s}], [{s}, {s}, 1], "
                         f"[B, {s}, {s}] or [B, {s}, {s}, 1]); received shape {shape}.")
    if batch[0] == 0:
        raise ValueError(f"{name} is an empty batch; received shape {shape}.")
    _check_pixel_values(arr, name, "patches")
    return arr.reshape(batch + (1,))


def prepare_image(x, name="image", channel_order: str = "rgb") -> np.ndarray:
    """One image ``[H, W]`` or ``[H, W, C]`` (C = 1, 3 or 4; uint8 or float in [0, 1]) ->
    grayscale float32 ``[H, W]`` in [0, 1]. Colour is ``channel_order`` ("rgb" as NumPy/scikit-image
    read it, "bgr" as OpenCV does)."""
    img = _to_unit_float(_check_image(x, name, channel_order), name, "images")
    if img.ndim == 3:
        alpha = img[..., 3] if img.shape[2] == 4 else None
        if img.shape[2] == 1:
            img = img[..., 0]
        else:
            code = cv2.COLOR_RGB2GRAY if channel_order == "rgb" else cv2.COLOR_BGR2GRAY
            img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), code)
        if alpha is not None:
            img = img * alpha  # composited onto black, as the training data does
    return np.ascontiguousarray(img, dtype=np.float32)


def _check_image(x, name, channel_order):
    """``x`` as an array, checked as :func:`prepare_image` describes (``ValueError``)."""
    if channel_order not in ("rgb", "bgr"):
        raise ValueError(f"channel_order must be 'rgb' or 'bgr'; received {channel_order!r}.")
    arr = _as_array(x, name)
    shape = tuple(arr.shape)
    if not (len(shape) == 2 or (len(shape) == 3 and shape[2] in (1, 3, 4))):
        raise ValueError(f"{name} must be one image [H, W] or [H, W, C] with C in (1, 3, 4); "
                         f"received shape {shape}.")
    if shape[0] == 0 or shape[1] == 0:
        raise ValueError(f"{name} is empty; received shape {shape}.")
    _check_pixel_values(arr, name, "images")
    return arr


_GRAY_BLOCK_PIXELS = 1 << 16
"""Pixels per block of rows converted to gray at a time (bounds the float64 temporaries of an
image with an alpha channel)."""


class InputImage(NamedTuple):
    """One image as ``estimate_images`` uses it (:func:`input_image`): ``work``, its gray float32
    ``[240, 320]`` version in [0, 1]; ``size``, its own ``(w, h)``; ``feature``, its feature
    image (:func:`feature_size`: gray, uint8 for a uint8 image, else float32 in [0, 1]) or
    ``None`` (not asked for, or the image fits in the work size)."""

    work: np.ndarray
    size: tuple
    feature: np.ndarray | None = None


def input_image(x, name="image", channel_order: str = "rgb",
                feature_image: bool = False) -> InputImage:
    """One image (as :func:`prepare_image` accepts it) -> :class:`InputImage`: its work image,
    its own size and, with ``feature_image``, its feature image (the module docstring).

    A uint8 image is made gray (:func:`stnh_tf.data.sources.to_gray_uint8`, a block of rows at a
    time) and resized (:func:`~stnh_tf.data.sources.resize_to_protocol`) in uint8, as the
    training data was made, and only then converted to float; a float image goes through
    :func:`prepare_image` and :func:`resize_to_work_size`. The feature image is resized from the
    same gray image (:func:`feature_size`). Raises ``ValueError`` as :func:`prepare_image`, and
    for an image too small for the patch (:func:`check_image_size`).
    """
    from stnh_tf.data import sources

    arr = _check_image(x, name, channel_order)
    size = (arr.shape[1], arr.shape[0])
    check_image_size(size, name)
    if arr.dtype != np.uint8:
        gray = prepare_image(arr, name, channel_order)
        work = resize_to_work_size(gray)
    else:
        if arr.ndim == 2 or arr.shape[2] == 1:
            gray = arr.reshape(arr.shape[:2])
        else:
            rows = max(1, _GRAY_BLOCK_PIXELS // arr.shape[1])
            gray = np.empty(arr.shape[:2], np.uint8)
            for r in range(0, arr.shape[0], rows):
                gray[r:r + rows] = sources.to_gray_uint8(arr[r:r + rows], channel_order)
        gray = np.ascontiguousarray(gray)
        work = pixels.to_unit(sources.resize_to_protocol(gray))
    target = feature_size(size) if feature_image else None
    feature = (None if target is None else gray if target == size else
               cv2.resize(gray, target, interpolation=cv2.INTER_AREA))
    return InputImage(work, size, feature)


def work_image(x, name="image", channel_order: str = "rgb"):
    """One image (as :func:`prepare_image` accepts it) -> ``(work, (w, h))``: its gray float32
    ``[240, 320]`` version in [0, 1] and its own size (:func:`input_image` without the feature
    image). Raises ``ValueError`` as :func:`input_image`."""
    return tuple(input_image(x, name, channel_order)[:2])


def feature_size(size):
    """``(w', h')`` of the feature image of an image of ``size = (w, h)``: ``(w, h)`` where
    ``max(w, h) <= FEATURE_MAX_SIDE``, else each side scaled by ``FEATURE_MAX_SIDE / max(w, h)``
    and rounded (at least 1); ``None`` where the image fits in the work size (``w <= 320`` and
    ``h <= 240``: its work image is its feature image).

    >>> feature_size((320, 240)), feature_size((640, 480)), feature_size((4000, 3000))
    (None, (640, 480), (1600, 1200))
    """
    w, h = (int(v) for v in size)
    if w <= WORK_SIZE[0] and h <= WORK_SIZE[1]:
        return None
    scale = FEATURE_MAX_SIDE / max(w, h)
    if scale >= 1.0:
        return (w, h)
    return (max(1, round(w * scale)), max(1, round(h * scale)))


def work_from_feature(size) -> np.ndarray:
    """``[3, 3]`` float64 map from pixels of the feature image of an image of ``size = (w, h)``
    (:func:`feature_size`) to pixels of its work image: ``S @ inv(F)``, ``S`` and ``F`` the
    :func:`resize_matrix` from the image to its work and feature images; the identity where the
    feature image is the work image (``feature_size`` ``None``)."""
    target = feature_size(size)
    if target is None:
        return np.eye(3)
    return resize_matrix(size, WORK_SIZE) @ np.linalg.inv(resize_matrix(size, target))


# --------------------------------------------------------------------------------------------
# Frames
# --------------------------------------------------------------------------------------------
def resize_to_work_size(gray: np.ndarray) -> np.ndarray:
    """Grayscale ``[h, w]`` (uint8 or float) -> ``[240, 320]`` as the training data was made:
    :func:`stnh_tf.data.sources.resize_to_protocol` (``cv2.INTER_AREA`` when both sides shrink,
    else ``cv2.INTER_LINEAR``; both keep the geometry of :func:`resize_matrix`)."""
    return resize_to_protocol(gray, *WORK_SIZE)


def central_patch(work: np.ndarray) -> np.ndarray:
    """The central 128 x 128 square (at :data:`PATCH_ORIGIN`) of a ``[240, 320]`` image, as a
    batch of one ``[1, 128, 128, 1]``."""
    (x0, y0), s = PATCH_ORIGIN, PATCH_SIZE
    return np.ascontiguousarray(work[None, y0:y0 + s, x0:x0 + s, None])


def patch_to_image_frames(h_patch, size_a, size_b) -> np.ndarray:
    """``H_img = inv(S_a) @ T @ H_patch @ inv(T) @ S_b`` (scaled so ``[2, 2] = 1``): the central
    patches' ``H_ba`` ``[3, 3]`` in the pixel frames of the original images of ``size_a`` and
    ``size_b`` (``(w, h)`` each; see the module docstring)."""
    h_work = geometry.patch_to_image(h_patch, *PATCH_ORIGIN)
    s_a, s_b = resize_matrix(size_a, WORK_SIZE), resize_matrix(size_b, WORK_SIZE)
    return geometry.scale_to_unit(np.linalg.inv(s_a) @ h_work @ s_b)
