"""What an image file must be to be used, checked before and after decoding: no more pixels than
:data:`MAX_IMAGE_PIXELS` (from its header, before it is decoded: :func:`header_size`,
:func:`check_pixel_count`) and large enough for the protocol's patch (:func:`check_image_size`),
with the errors :mod:`stnh_tf.data.sources` raises (:class:`ImageDecodeError` and its kinds;
``sources`` gives all these names too). Pillow reads the headers (OpenCV has no header-only
read); no backend, no OpenCV.
"""

from __future__ import annotations

import io

from stnh_tf import geometry

MAX_IMAGE_PIXELS = 120_000_000
"""The most pixels (width x height) an image file may decode to (120 megapixels: a 108-MP phone
photograph passes). Checked from the file's header before it is decoded
(:func:`stnh_tf.data.sources.decode_gray`), as Pillow's decompression-bomb guard does: a 250 KB
PNG can declare 16,000 x 16,000 pixels, and ``predict`` needed 4.3 GB for it (about 17 bytes a
pixel, issue 80). ``predict --max_image_pixels`` raises it."""


class ImageDecodeError(ValueError):
    """A file that cannot be turned into an 8-bit gray image; ``str(e)`` is the reason."""


class ImageTooSmallError(ImageDecodeError):
    """An image too small for the protocol's patches (:func:`check_image_size`)."""


class ImageTooLargeError(ImageDecodeError):
    """An image whose header declares more pixels than the cap (:func:`check_pixel_count`)."""


def header_size(data: bytes):
    """``(w, h)`` that the header of the encoded image ``data`` declares, read by Pillow's format
    plugins (the first whose ``accept`` takes the data's prefix and whose header reader
    succeeds, as ``PIL.Image.open`` chooses) without decoding the pixels; ``None`` where no
    plugin reads the header (the decoder then finds out). ``PIL.Image.open`` itself is not used:
    above twice ``PIL.Image.MAX_IMAGE_PIXELS`` it raises without giving the size, and its limit
    is not this module's (:data:`MAX_IMAGE_PIXELS`, which a binary's flag may raise)."""
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - Pillow comes with matplotlib
        return None
    Image.init()  # every format's header reader (once per process)
    for fmt in Image.ID:
        factory, accept = Image.OPEN[fmt]
        accepted = accept(data[:16]) if accept else True
        if not accepted or isinstance(accepted, str):  # a str: "this format, unsupported"
            continue
        try:
            with factory(io.BytesIO(data), "") as im:  # reads the header, decodes nothing
                return int(im.size[0]), int(im.size[1])
        except Exception:  # noqa: BLE001 - not this format's header, as Image.open goes on
            continue
    return _opencv_only_header_size(data)


def _opencv_only_header_size(data: bytes):
    r"""``(w, h)`` of a Radiance HDR, a PFM or an OpenEXR header, formats that OpenCV decodes
    (EXR where ``OPENCV_IO_ENABLE_OPENEXR`` is set) and Pillow does not read (hand-written:
    neither library reads a header alone); ``None`` for anything else.

        >>> _opencv_only_header_size(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 30 +X 40\n")
        (40, 30)
        >>> _opencv_only_header_size(b"Pf\n40 30\n-1.0\n")
        (40, 30)
    """
    if data[:4] == EXR_MAGIC:
        return _exr_size(data)
    head = data[:4096]
    if head.startswith((b"#?RADIANCE", b"#?RGBE")) and b"\n\n" in head:
        axes = head.split(b"\n\n", 1)[1].split(b"\n", 1)[0].split()  # e.g. -Y 30 +X 40
        if len(axes) == 4 and axes[0][1:] in (b"X", b"Y") and axes[1].isdigit() \
                and axes[3].isdigit():
            first, second = int(axes[1]), int(axes[3])
            return (second, first) if axes[0][1:] == b"Y" else (first, second)
    if head[:3] in (b"PF\n", b"Pf\n"):
        size = head[3:].split(b"\n", 1)[0].split()
        if len(size) == 2 and all(s.isdigit() for s in size):
            return int(size[0]), int(size[1])
    return None


EXR_MAGIC = b"\x76\x2f\x31\x01"
"""The first four bytes of an OpenEXR file."""


def _exr_size(data: bytes):
    """``(w, h)`` of an OpenEXR file's (first part's) ``dataWindow`` attribute (``box2i``: four
    little-endian int32 ``xMin, yMin, xMax, yMax``, inclusive), found among the header's
    attributes (each a name and a type, both NUL-terminated, an int32 size, the value) after the
    magic number and the version field; ``None`` where the header holds none or is cut short."""
    import struct

    at = 8
    while at < len(data) and data[at] != 0:  # an empty name ends the header
        name_end = data.find(b"\0", at)
        type_end = data.find(b"\0", name_end + 1) if name_end >= 0 else -1
        if type_end < 0 or type_end + 5 > len(data):
            return None
        name, kind = data[at:name_end], data[name_end + 1:type_end]
        (size,) = struct.unpack_from("<i", data, type_end + 1)
        at = type_end + 5
        if size < 0 or at + size > len(data):
            return None
        if name == b"dataWindow" and kind == b"box2i" and size == 16:
            x0, y0, x1, y1 = struct.unpack_from("<4i", data, at)
            return max(x1 - x0 + 1, 0), max(y1 - y0 + 1, 0)
        at += size
    return None


def check_pixel_count(size, max_pixels: int = MAX_IMAGE_PIXELS) -> None:
    """:class:`ImageTooLargeError` when an image of header ``size`` (:func:`header_size`: ``(w,
    h)``, or ``None``: unknown) has more than ``max_pixels`` pixels.

        >>> check_pixel_count((16000, 16000))  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        stnh_tf.data.image_checks.ImageTooLargeError: too large to decode: 16,000 x 16,000 px ...
    """
    if size is not None and size[0] * size[1] > max_pixels:
        raise ImageTooLargeError(
            f"too large to decode: {size[0]:,} x {size[1]:,} px is {size[0] * size[1]:,} pixels, "
            f"over the cap of {max_pixels:,} (a guard against decompression bombs: a small file "
            "that decodes to gigabytes)")


MIN_PATCH_SPAN_PX = 8
"""Fewest pixels of an image a 128 x 128 patch of its 320 x 240 version may cover on a side."""


def check_image_size(size, name="image") -> None:
    """:class:`ImageTooSmallError` (naming ``name``) unless a 128 x 128 patch of the 320 x 240
    version of a ``size = (w, h)`` image covers :data:`MIN_PATCH_SPAN_PX` of its pixels a side
    (``w >= 20``, ``h >= 15``; below, its motion is not observable: training pairs skip it).

        >>> check_image_size((5120, 1))  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        stnh_tf.data.image_checks.ImageTooSmallError: image is 5120 x 1 px: too small ... 20 x 15 px).
    """
    work, patch = (geometry.IMAGE_WIDTH, geometry.IMAGE_HEIGHT), geometry.PATCH_SIZE
    span = tuple(side * patch / w for side, w in zip(size, work))
    if min(span) < MIN_PATCH_SPAN_PX:
        least = [-(-MIN_PATCH_SPAN_PX * side // patch) for side in work]
        raise ImageTooSmallError(
            f"{name} is {size[0]} x {size[1]} px: too small to estimate a homography from; its "
            f"central {patch} x {patch} patch, after the resize to {work[0]} x {work[1]}, would "
            f"cover {span[0]:.1f} x {span[1]:.1f} of its pixels, and at least "
            f"{MIN_PATCH_SPAN_PX} x {MIN_PATCH_SPAN_PX} are needed (an image of at least "
            f"{least[0]} x {least[1]} px).")
