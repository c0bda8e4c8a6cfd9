"""Image sources for data generation: listing, decoding and the paper's 320x240 gray conversion.

NumPy / OpenCV (and Pillow as a decoding fallback) only: this module never imports TensorFlow or
Keras, so data-generation worker processes and the backend-free ``PairSequence`` can use it.

Every source image becomes ``uint8 [240, 320]`` (height, width) through :func:`load_gray_320x240`:

* refused before decoding when the header declares more than :data:`MAX_IMAGE_PIXELS` pixels
  (a decompression bomb; :func:`check_pixel_count`);
* decoded with OpenCV (``IMREAD_IGNORE_ORIENTATION``: raw pixel order, EXIF rotation ignored, the
  same as tensorflow-datasets' decoder); JPEGs straight to gray (libjpeg's luma), every other
  file unchanged and then converted here; Pillow is tried when OpenCV cannot decode a file;
* 16-bit and other wide integer images scaled to 8 bits by the bit depth their values use
  (``round(v * 255 / (2^b - 1))``, ``b`` the fewest bits, 8 to 16, that hold the image's largest
  value: :func:`integer_full_scale`; a 16-bit file holding 0..255 reads as the 8-bit image, 12-bit
  data by 255/4095, full-range data by 255/65535), float images taken as ``[0, 1]`` (clipped)
  when at most 1% of their values exceed 1 (highlights of a linear image, a sharpening's
  overshoot; else ``[0, 255]``), booleans as 0/255;
* colour (BGR/RGB, palette expanded, CMYK converted by the decoder) to gray with the ITU-R 601
  weights ``0.299 R + 0.587 G + 0.114 B`` (``cv2.COLOR_BGR2GRAY``);
* an alpha channel is composited onto black (``gray * alpha``), so that hidden colour values of
  transparent pixels never leak into the data;
* resized to exactly 320x240 (aspect ratio not kept, as in the paper): ``cv2.INTER_AREA`` when
  both sides shrink, ``cv2.INTER_LINEAR`` otherwise (small images are enlarged; those under 20 x
  15 px refused, as by ``estimate_images``: :func:`check_image_size`).

Files that cannot be turned into an image raise :class:`ImageDecodeError`, whose message is the
reason recorded in a dataset's ``metadata.json``.
"""

from __future__ import annotations

import io

import cv2
import numpy as np

from stnh_tf import geometry, pixels
from stnh_tf.data.image_checks import (MAX_IMAGE_PIXELS, ImageDecodeError, ImageTooLargeError,
                                       check_image_size, check_pixel_count, header_size)
from stnh_tf.data.image_folders import (  # noqa: F401 (the listing, in its own module)
    HIDDEN, IMAGE_EXTENSIONS, LINK_FOLDER, LINK_OUTSIDE, LINK_OUTSIDE_WHY, NOT_A_FILE, SAME_FILE,
    FolderListing, SourceError, check_folder, list_image_files, scan_image_folder,
    scan_image_folders, split_folders)

RESIZE_POLICY = "cv2.INTER_AREA if both sides shrink else cv2.INTER_LINEAR"
GRAY_POLICY = ("ITU-R 601 luma (cv2 BGR2GRAY; JPEG decoded to gray by libjpeg), 16-bit scaled by "
               "255/(2^b - 1), b the fewest bits (8 to 16) that hold its largest value, alpha "
               "composited onto black, EXIF orientation ignored")

FLOAT_OVER_ONE = 0.01
"""A float image is on ``[0, 1]`` where at most this share of its values exceed 1."""

_JPEG_MAGIC = b"\xff\xd8"


# ------------------------------------------------------------------------------------------------
# Decoding
# ------------------------------------------------------------------------------------------------
def to_gray_uint8(image: np.ndarray, channel_order: str = "bgr") -> np.ndarray:
    """Any decoded image -> ``uint8 [h, w]`` gray (see the module docstring for the rules).

    Args:
      image: ``[h, w]``, ``[h, w, 1]``, ``[h, w, 2]`` (gray + alpha), ``[h, w, 3]`` (colour) or
        ``[h, w, 4]`` (colour + alpha); uint8, uint16, other integers, float or bool.
      channel_order: ``"bgr"`` (OpenCV) or ``"rgb"`` (Pillow) for 3/4-channel images.
    Raises:
      ImageDecodeError: unsupported shape or dtype.
    """
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (2, 3, 4)) \
            or img.shape[0] == 0 or img.shape[1] == 0:
        raise ImageDecodeError(f"unsupported image shape {img.shape}")
    alpha = None
    if img.ndim == 3 and img.shape[2] in (2, 4):
        img, alpha = img[..., :-1], img[..., -1]
        if img.shape[2] == 1:
            img = img[..., 0]
    if img.dtype == np.uint8 and alpha is None:  # the common case, in OpenCV's fixed point
        if img.ndim == 2:
            return np.ascontiguousarray(img)
        code = cv2.COLOR_BGR2GRAY if channel_order == "bgr" else cv2.COLOR_RGB2GRAY
        return cv2.cvtColor(np.ascontiguousarray(img), code)
    gray = _unit_float(img)
    if gray.ndim == 3:
        b, g, r = (gray[..., 0], gray[..., 1], gray[..., 2]) if channel_order == "bgr" else \
            (gray[..., 2], gray[..., 1], gray[..., 0])
        gray = 0.299 * r + 0.587 * g + 0.114 * b
    if alpha is not None:  # (integer alpha on the colour's full scale or its own, the larger)
        gray = gray * (_unit_float(alpha) if not np.issubdtype(alpha.dtype, np.integer)
                       or alpha.dtype == np.uint8 else
                       np.clip(alpha.astype(np.float64), 0, 65535.0)
                       / max(integer_full_scale(img), integer_full_scale(alpha)))
    return pixels.to_uint8(gray)


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Any decoded image (uint8, 16-bit or other integers, float or bool; any channels) as uint8
    with its channels kept, scaled as :func:`to_gray_uint8` scales (module docstring): the
    colours of the pixels that image estimates on."""
    image = np.asarray(image)
    return image if image.dtype == np.uint8 else pixels.to_uint8(_unit_float(image))


def _unit_float(img: np.ndarray) -> np.ndarray:
    """Scale any dtype to float64 in [0, 1]."""
    if img.dtype == np.bool_:
        return img.astype(np.float64)
    if img.dtype == np.uint8:
        return img.astype(np.float64) / 255.0
    if np.issubdtype(img.dtype, np.integer):
        # 16-bit (uint16, or Pillow's int32 mode "I" holding 16-bit data)
        return np.clip(img.astype(np.float64), 0, 65535.0) / integer_full_scale(img)
    if np.issubdtype(img.dtype, np.floating):  # (a few values above 1: highlights, sharpening)
        f = np.nan_to_num(img.astype(np.float64))
        return np.clip(f if np.count_nonzero(f > 1.0) <= FLOAT_OVER_ONE * f.size else f / 255.0,
                       0.0, 1.0)
    raise ImageDecodeError(f"unsupported pixel type {img.dtype}")


def integer_full_scale(img: np.ndarray) -> float:
    """The value that stands for white in a 16-bit (or other wide integer) image: ``2^b - 1``,
    ``b`` the fewest bits, from 8 to 16, that hold its largest value. A low-range export (a
    16-bit PNG holding 0..255) is white at 255, not black; 10-, 12- and 14-bit sensor data at
    their own full scale; full-range data at 65535.

        >>> [integer_full_scale(np.array([v], np.uint16)) for v in (0, 255, 256, 4095, 65535)]
        [255, 255, 511, 4095, 65535]
    """
    largest = int(np.max(img)) if img.size else 0
    return 2 ** min(16, max(8, largest.bit_length())) - 1


def decode_gray(data: bytes, max_pixels: int = MAX_IMAGE_PIXELS) -> np.ndarray:
    """Encoded image bytes -> ``uint8 [h, w]`` gray at the file's own size. The size its header
    declares is checked against ``max_pixels`` first (:func:`check_pixel_count`), before
    anything is decoded.

    Raises:
      ImageDecodeError: empty, truncated, corrupt or non-image data (message = reason);
        ImageTooLargeError: over ``max_pixels``.
    """
    if len(data) == 0:
        raise ImageDecodeError("empty file (0 bytes)")
    check_pixel_count(header_size(data), max_pixels)
    buf = np.frombuffer(data, np.uint8)
    flags = cv2.IMREAD_IGNORE_ORIENTATION
    if data[:2] == _JPEG_MAGIC:
        img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE | flags)
        if img is not None:
            return img
    else:
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED | flags)
        if img is not None:
            return to_gray_uint8(img, "bgr")
    return _decode_with_pillow(data)


def _decode_with_pillow(data: bytes) -> np.ndarray:
    try:
        from PIL import Image, UnidentifiedImageError
    except ImportError:  # pragma: no cover - Pillow comes with matplotlib
        raise ImageDecodeError("not a decodable image (OpenCV failed; Pillow unavailable)")
    try:
        with Image.open(io.BytesIO(data)) as im:
            im.load()  # raises OSError on truncated data
            mode = im.mode
            if mode == "P" or mode == "PA":
                im = im.convert("RGBA")
            elif mode in ("CMYK", "YCbCr", "LAB", "HSV"):
                im = im.convert("RGB")
            elif mode == "1":
                im = im.convert("L")
            elif mode.startswith("I;16"):
                return to_gray_uint8(np.asarray(im, dtype=np.uint16))
            arr = np.asarray(im)
    except UnidentifiedImageError:
        raise ImageDecodeError("not a decodable image (unknown or corrupt format)") from None
    except Image.DecompressionBombError as e:  # a cap raised beyond Pillow's own limit
        raise ImageTooLargeError(f"too large for Pillow's decoder: {e}") from None
    except (OSError, ValueError, SyntaxError) as e:
        raise ImageDecodeError(f"corrupt or truncated image: {e}") from None
    return to_gray_uint8(arr, "rgb")


def resize_to_protocol(gray: np.ndarray, width: int = geometry.IMAGE_WIDTH,
                       height: int = geometry.IMAGE_HEIGHT) -> np.ndarray:
    """``uint8 [h, w]`` -> ``uint8 [height, width]`` (area when shrinking, else bilinear; both
    with the geometry of :func:`resize_matrix`)."""
    h, w = gray.shape[:2]
    if (w, h) == (width, height):
        return np.ascontiguousarray(gray)
    interp = cv2.INTER_AREA if (w >= width and h >= height) else cv2.INTER_LINEAR
    return cv2.resize(gray, (width, height), interpolation=interp)


def resize_matrix(src_size, dst_size) -> np.ndarray:
    """``[3, 3]`` float64 map from pixels of an image of ``src_size = (w, h)`` to pixels of its
    resized version of ``dst_size = (w', h')`` (``cv2.resize`` geometry, pixel centres at integer
    coordinates): ``x' = s_x (x + 0.5) - 0.5`` with ``s_x = w' / w`` (same for y)."""
    sx, sy = dst_size[0] / src_size[0], dst_size[1] / src_size[1]
    return np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])


def read_gray(path_or_bytes, max_pixels: int = MAX_IMAGE_PIXELS) -> np.ndarray:
    """Read an image file (path) or encoded bytes -> ``uint8 [h, w]`` gray at the file's own size
    (:func:`decode_gray`: the module docstring's rules, a truncated file refused, one whose
    header declares more than ``max_pixels`` pixels refused before decoding). The one reading
    of image files: make_dataset's (:func:`load_gray_320x240`) and ``experiments.predict``'s.

    Raises:
      ImageDecodeError: the file cannot be read or decoded (message = reason);
        ImageTooLargeError: over ``max_pixels``.
    """
    if isinstance(path_or_bytes, (bytes, bytearray, memoryview)):
        data = bytes(path_or_bytes)
    else:
        try:
            with open(path_or_bytes, "rb") as f:
                data = f.read()
        except OSError as e:
            reason = f"unreadable file: {type(e).__name__}: {e.strerror or e}"
            raise ImageDecodeError(reason) from None
    return decode_gray(data, max_pixels)


def load_gray_320x240(path_or_bytes) -> np.ndarray:
    """Read an image file (path) or encoded bytes -> ``uint8 [240, 320]`` gray
    (:func:`read_gray`, :func:`check_image_size`, then :func:`resize_to_protocol`).

    Raises:
      ImageDecodeError: unreadable, undecodable, or under 20 x 15 px (message = reason).
    """
    gray = read_gray(path_or_bytes)
    check_image_size(gray.shape[1::-1])
    return resize_to_protocol(gray)


def as_gray_320x240(image) -> np.ndarray:
    """Path, encoded bytes, or an already decoded array (any dtype/channels, BGR order) ->
    ``uint8 [240, 320]``."""
    if isinstance(image, np.ndarray):
        gray = to_gray_uint8(image, "bgr")
        check_image_size(gray.shape[1::-1])
        return resize_to_protocol(gray)
    return load_gray_320x240(image)


def quiet_opencv() -> None:
    """Silence OpenCV's decoder warnings (bad files are reported through ImageDecodeError)."""
    try:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    except AttributeError:  # pragma: no cover - very old OpenCV
        pass

