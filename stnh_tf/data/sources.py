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

import dataclasses
import io
import os

import cv2
import numpy as np

from stnh_tf import geometry, pixels
from stnh_tf.data.image_checks import (MAX_IMAGE_PIXELS, ImageDecodeError, ImageTooLargeError,
                                       check_image_size, check_pixel_count, header_size)

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".pgm", ".ppm", ".pbm", ".pnm", ".tif",
                    ".tiff", ".webp", ".gif")
"""File name endings (case-insensitive) that the ``folder`` source treats as images (a GIF's
first frame)."""

RESIZE_POLICY = "cv2.INTER_AREA if both sides shrink else cv2.INTER_LINEAR"
GRAY_POLICY = ("ITU-R 601 luma (cv2 BGR2GRAY; JPEG decoded to gray by libjpeg), 16-bit scaled by "
               "255/(2^b - 1), b the fewest bits (8 to 16) that hold its largest value, alpha "
               "composited onto black, EXIF orientation ignored")

FLOAT_OVER_ONE = 0.01
"""A float image is on ``[0, 1]`` where at most this share of its values exceed 1."""

_JPEG_MAGIC = b"\xff\xd8"

class SourceError(ValueError):
    """A source that cannot be used at all (missing folder, no images, no download possible)."""


LINK_OUTSIDE = "symbolic link to a file outside the image folder"
LINK_OUTSIDE_WHY = (
    "symbolic links leading out of an image folder are not followed, so that the data are the "
    "folder's own files (the image ids recorded with them name what was read, and a folder "
    "cannot pull in files from elsewhere on the disk): copy the files in (cp -L), or give the "
    "folder they are in as an image folder too")
"""Why a symbolic link leading out of an image folder is left out (:func:`scan_image_folder`)."""
LINK_FOLDER, SAME_FILE = "symbolic link to a folder", "the same file (a link) as"
HIDDEN = "hidden (a name starting with '.': a system's thumbnails, trash or ._ files): not used"
"""Reasons :func:`scan_image_folder` names what else it leaves out: a linked folder (not
entered), a link to a file listed already, a hidden folder or file (not photographs)."""

# ------------------------------------------------------------------------------------------------
# Listing
# ------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class FolderListing:
    """Result of scanning a folder for images.

    Attributes:
      root: absolute path of the scanned folder.
      files: absolute paths of image files, sorted by their path relative to ``root`` (POSIX
        separators), so the order (and hence every image index) is the same on every machine.
      unreadable: ``(path, reason)`` of what was left out: directories that could not be
        listed, symbolic links leading outside the folder, linked and hidden folders (not
        entered), hidden files, links to a file listed already.
      ignored: number of files skipped because of their extension (not image files).
      beyond_max_images: image files left out because they come after the first ``max_images``
        of the sorted listing (:func:`scan_image_folders`; 0 without a limit).
    """

    root: str
    files: list
    unreadable: list
    ignored: int
    ids: dict | None = None  # path -> id, for listings of several folders
    beyond_max_images: int = 0

    def image_id(self, path: str) -> str:
        """The id stored with each sample: the path relative to ``root``, POSIX separators, the
        bytes of a name that is not UTF-8 escaped (for several folders: ``<k>:`` and the path
        relative to folder ``k``)."""
        if self.ids is not None:
            return self.ids[path]
        relative = os.path.relpath(path, self.root).replace(os.sep, "/")
        # a name that is not UTF-8 (an old archive's Latin-1) as its bytes escaped: "caf\\xe9"
        return relative.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def split_folders(spec) -> list:
    """Image folders from a comma-separated string (as absl list flags take them, e.g.
    ``--image_dir``) or a sequence, each an existing directory (:func:`check_folder`), so that
    a list of them is never read as a list of image files.

    Raises:
      SourceError: no folder named (an empty string or list), or an entry that does not exist
        or is not a directory (the first such, named).
    """
    folders = spec.split(",") if isinstance(spec, str) else [os.fspath(f) for f in spec]
    folders = [f.strip() for f in folders if f.strip()]
    if not folders:
        raise SourceError(f"no image folder given (received {spec!r}).")
    for folder in folders:
        check_folder(folder)
    return folders


def check_folder(folder: str) -> str:
    """``folder``'s absolute path, if it is an existing directory.

    Raises:
      SourceError: "image folder does not exist: PATH", or "... is not a folder: PATH" (a file).

        >>> try:
        ...     check_folder("/no/such/place")
        ... except SourceError as e:
        ...     print(e)
        image folder does not exist: /no/such/place
    """
    root = os.path.abspath(folder)
    if not os.path.exists(root):
        raise SourceError(f"image folder does not exist: {root}")
    if not os.path.isdir(root):
        raise SourceError(f"image folder is not a folder (a file, not a directory): {root}")
    return root


def scan_image_folders(folders, max_images: int = 0) -> FolderListing:
    """Every image file below each of ``folders`` (a list, or a comma-separated string), folder
    after folder, each sorted as :func:`scan_image_folder` sorts. One folder gives exactly
    :func:`scan_image_folder`'s listing; with several, ``root`` is their absolute paths joined by
    commas and the id of an image is ``"<k>:<path relative to folder k>"``. ``max_images`` > 0
    keeps the first ``max_images`` files of that order (the same ones on every machine) and
    counts the others in ``beyond_max_images``.

        >>> import tempfile
        >>> folder = tempfile.mkdtemp()
        >>> for name in ("c.png", "a.jpg", "b.png", "notes.txt"):
        ...     open(os.path.join(folder, name), "wb").close()
        >>> listing = scan_image_folders(folder, max_images=2)
        >>> [listing.image_id(p) for p in listing.files], listing.beyond_max_images
        (['a.jpg', 'b.png'], 1)

    Raises:
      SourceError: no folder given, or one that is not an existing directory.
      ValueError: ``max_images`` < 0.
    """
    if max_images < 0:
        raise ValueError(f"max_images must be >= 0 (0: every image); received {max_images}.")
    folders = split_folders(folders)
    listings = [scan_image_folder(f) for f in folders]
    if len(listings) == 1:
        merged = listings[0]
    else:
        merged = FolderListing(root=",".join(x.root for x in listings), files=[], unreadable=[],
                               ignored=sum(x.ignored for x in listings), ids={})
        for k, listing in enumerate(listings):
            for path in listing.files:
                if path not in merged.ids:  # a folder given twice, or nested: list each once
                    merged.files.append(path)
                    merged.ids[path] = f"{k}:{listing.image_id(path)}"
            merged.unreadable.extend(listing.unreadable)
    if 0 < max_images < len(merged.files):
        merged.beyond_max_images = len(merged.files) - max_images
        merged.files = merged.files[:max_images]
    return merged


def scan_image_folder(folder: str) -> FolderListing:
    """Every image file below ``folder`` (recursively; extensions in :data:`IMAGE_EXTENSIONS`).

    Left out, each in ``unreadable`` with its reason: symbolic links to directories (not
    entered), a link to a file outside ``folder`` (:data:`LINK_OUTSIDE_WHY`) or to a file listed
    already, hidden folders and files (:data:`HIDDEN`).

    Raises:
      SourceError: if ``folder`` is not an existing directory (:func:`check_folder`).
    """
    root = check_folder(folder)
    files, unreadable, ignored = [], [], 0

    def onerror(err: OSError):
        unreadable.append((getattr(err, "filename", None) or str(err),
                           f"unreadable directory: {type(err).__name__}: {err.strerror or err}"))

    real_root = os.path.realpath(root)
    for dirpath, dirnames, filenames in os.walk(root, onerror=onerror, followlinks=False):
        left = [(os.path.join(dirpath, n), HIDDEN if n.startswith(".") else
                 f"{LINK_FOLDER} ({os.path.realpath(os.path.join(dirpath, n))}): not entered")
                for n in dirnames if n.startswith(".") or os.path.islink(os.path.join(dirpath, n))]
        unreadable += left
        dirnames[:] = sorted(set(dirnames) - {os.path.basename(p) for p, _ in left})
        for name in filenames:
            if not name.lower().endswith(IMAGE_EXTENSIONS):
                ignored += 1
                continue
            path = os.path.join(dirpath, name)
            if name.startswith("."):
                unreadable.append((path, HIDDEN))
            elif os.path.islink(path) and os.path.commonpath(
                    [real_root, os.path.realpath(path)]) != real_root:
                unreadable.append((path, f"{LINK_OUTSIDE} ({os.path.realpath(path)}): not "
                                         "followed"))
            else:
                files.append(path)
    listing = FolderListing(root=root, files=[], unreadable=[], ignored=ignored)
    kept = {}  # one path per file: the file itself before a link to it, then the first id
    for path in sorted(files, key=lambda p: (os.path.islink(p), listing.image_id(p))):
        kept.setdefault(os.path.realpath(path), path)
    for path in sorted(files, key=listing.image_id):
        first = kept[os.path.realpath(path)]
        if first == path:
            listing.files.append(path)
        else:
            unreadable.append((path, f"{SAME_FILE} {listing.image_id(first)}"))
    listing.unreadable = sorted(unreadable)
    return listing


def list_image_files(folder: str) -> list:
    """Absolute paths of every image file below ``folder``, sorted (:func:`scan_image_folder`)."""
    return scan_image_folder(folder).files


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

