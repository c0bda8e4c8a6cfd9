"""The overlay PNG of ``experiments.predict``: image_a with image_b's border mapped into it, and
image_a warped onto image_b's frame in colour (:func:`overlay`); the file rules are
:mod:`stnh_tf.inference.image_files`'.

The border is drawn where it lies in front of camera a: a homography that maps part of image_b
beyond image_a's horizon (a homogeneous coordinate at or below 0) gets the part in front drawn,
clipped at the horizon (:func:`border_polygon`), never the mirrored image of the part behind.
"""

import numpy as np

OVERLAY_CAPTIONS = ("image_a; green: image_b's border mapped into it",
                    "magenta: image_a warped onto image_b; green: image_b; gray: aligned")
"""The caption above each panel of :func:`overlay` (wrapped to the panel's width:
:func:`caption_lines`)."""
CAPTION_MARGIN = 4
"""Pixels left free on each side of a caption line."""
OVERLAY_MAX_SIDE = 4096
"""The overlay draws larger images at this long side (px)."""
MIN_PANEL_WIDTH = 240
"""Panels narrower than this are enlarged (nearest neighbour, an integer factor) before their
caption is drawn, so that the caption stays legible (images down to 20 x 15 px are accepted)."""


def caption_scale(widths) -> float:
    """The font scale of both captions of panels of ``widths`` (one size, so that equal lines
    are as high): ``min(widths) / 900``, at least 0.35."""
    return max(min(widths) / 900.0, 0.35)


def caption_lines(text, width, scale) -> list:
    """``text`` wrapped into lines that fit a panel ``width`` px wide at font ``scale`` (each
    line's ``cv2.getTextSize`` width plus :data:`CAPTION_MARGIN` on each side): whole clauses
    (split after ``;``) where they fit, else words; a word wider than that on its own is a line
    of its own (at :func:`caption_scale` none is: the longest word takes about a fifth of the
    narrowest panel). ``" ".join(lines) == text`` for a text with single spaces.

        >>> caption_lines("magenta: image_a warped; green: image_b", 180, 0.35)
        ['magenta: image_a warped;', 'green: image_b']
    """
    import cv2

    def fits(line):
        size, _ = cv2.getTextSize(line, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
        return size[0] + 2 * CAPTION_MARGIN <= width

    def pack(pieces, lines):
        for piece in pieces:
            if lines and fits(f"{lines[-1]} {piece}"):
                lines[-1] = f"{lines[-1]} {piece}"
            elif fits(piece) or " " not in piece:
                lines.append(piece)
            else:
                pack(piece.split(" "), lines)
        return lines

    clauses = text.split("; ")
    return pack([c + ";" for c in clauses[:-1]] + clauses[-1:], [])


def _line_step(scale):
    """``(text height, pixels from one caption line to the next)`` at font ``scale``."""
    import cv2

    (_, h), base = cv2.getTextSize("Ag", cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    return h, h + base + 4


def _caption_band(lines, width, scale, height):
    """A black band ``height`` x ``width`` px holding ``lines`` in white (font ``scale``)."""
    import cv2

    h, step = _line_step(scale)
    band = np.zeros((height, width, 3), np.uint8)
    for k, line in enumerate(lines):
        cv2.putText(band, line, (CAPTION_MARGIN, 4 + h + k * step), cv2.FONT_HERSHEY_SIMPLEX,
                    scale, (255, 255, 255), 1, cv2.LINE_AA)
    return band


def _enlarged(panel):
    """``panel`` enlarged by the smallest integer factor that makes it at least
    :data:`MIN_PANEL_WIDTH` wide (nearest neighbour), or as it is."""
    import cv2

    factor = -(-MIN_PANEL_WIDTH // panel.shape[1])
    if factor <= 1:
        return panel
    return cv2.resize(panel, None, fx=factor, fy=factor, interpolation=cv2.INTER_NEAREST)


def matched_brightness(warped_a, gray_b, valid) -> np.ndarray:
    """``warped_a`` (uint8 ``[h, w]``) with its gray levels mapped onto those of ``gray_b``
    (histogram matching over ``valid``, bool ``[h, w]``: where image_a reaches; 0 elsewhere), so
    that a change of brightness, contrast, gamma or clipping between the photographs does not
    tint the overlay's aligned regions: a level whose share of ``warped_a``'s pixels at or below
    it is q becomes the lowest level of ``gray_b`` with a share of at least q.

        >>> a = np.arange(256, dtype=np.uint8).reshape(16, 16)
        >>> b = np.clip(a * 1.5, 0, 255).astype(np.uint8)
        >>> bool((matched_brightness(a, b, np.ones_like(a, bool)) == b).all())
        True
    """
    if not valid.any():
        return np.zeros_like(warped_a)
    share_a, share_b = (np.cumsum(np.bincount(x[valid], minlength=256)) / valid.sum()
                        for x in (warped_a, gray_b))
    lut = np.searchsorted(share_b, share_a - 1e-9).clip(0, 255).astype(np.uint8)
    return np.where(valid, lut[warped_a], 0).astype(np.uint8)


IN_FRONT = 1e-6
"""A point of image_b maps in front of camera a where its homogeneous coordinate under ``H_ba``
(``H[2][2] = 1``) is above this (:func:`stnh_tf.geometry.in_front`'s bound)."""
FAR = 1e5
"""How far (px) the border drawn by :func:`border_polygon` may reach: cut that far out (where it
goes to the horizon, or an image_b far larger than image_a), beyond any image."""


def points_in_a(h_ba, points_b) -> np.ndarray:
    """``points_b`` (``[N, 2]``) mapped into image_a by ``h_ba`` (``[3, 3]``, ``H[2][2] = 1``),
    NaN for a point beyond image_a's horizon (homogeneous coordinate at or below
    :data:`IN_FRONT`), which has no place in image_a.

        >>> points_in_a([[1, 0, 0], [0, 1, 0], [-0.004, 0, 1]], [[0, 0], [300, 0]]).tolist()
        [[0.0, 0.0], [nan, nan]]
    """
    from stnh_tf import geometry

    h_ba, points_b = np.asarray(h_ba, np.float64), np.asarray(points_b, np.float64)
    mapped = geometry.warp_points(h_ba, points_b)
    mapped[points_b @ h_ba[2, :2] + h_ba[2, 2] <= IN_FRONT] = np.nan
    return mapped


def border_polygon(h_ba, size_b) -> np.ndarray:
    """The part of image_b's border (``size_b = (w, h)``) in front of camera a, mapped into
    image_a by ``h_ba`` (``[3, 3]``, ``H[2][2] = 1``) and cut at :data:`FAR` px: ``[N, 2]``
    vertices (none where nothing of it is in front), finite. image_b's quadrilateral is clipped
    (Sutherland-Hodgman; hand-written: OpenCV clips polygons against rectangles only) against
    the half-planes of image_b, linear in its homogeneous coordinates, where a point maps in
    front (``w > IN_FRONT``) and within ``FAR`` px (``|x|, |y| <= FAR w``): points beyond image_a's
    horizon are never drawn at the mirrored places plain division gives them.

        >>> border_polygon(np.eye(3), (320, 240)).tolist()
        [[0.0, 0.0], [319.0, 0.0], [319.0, 239.0], [0.0, 239.0]]
        >>> len(border_polygon([[1, 0, 0], [0, 1, 0], [-0.01, 0, -1]], (320, 240)))  # behind
        0
    """
    from stnh_tf import geometry

    h_ba = np.asarray(h_ba, np.float64)
    w, h = size_b
    polygon = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], float)
    x, y, z = h_ba
    for plane in (z - np.array([0, 0, IN_FRONT]), FAR * z - x, FAR * z + x, FAR * z - y,
                  FAR * z + y):  # keep plane . p >= 0
        depth, kept = polygon @ plane, []
        for k in range(len(polygon)):
            p, q, dp, dq = polygon[k], polygon[(k + 1) % len(polygon)], depth[k], \
                depth[(k + 1) % len(polygon)]
            if dp >= 0:
                kept.append(p)
            if (dp >= 0) != (dq >= 0):
                kept.append(p + (q - p) * dp / (dp - dq))
        if not kept:
            return np.zeros((0, 2))
        polygon = np.array(kept)
    return geometry.warp_points(h_ba, polygon[:, :2])


def overlay(image_a, image_b, h_ba, gray_a=None, gray_b=None):
    """Two captioned panels (uint8 BGR, :data:`OVERLAY_CAPTIONS`): image_a with image_b's border
    mapped into it, and the colour overlay of image_b (green) on image_a warped onto image_b's
    frame by ``h_ba`` (magenta), of ``gray_a`` and ``gray_b`` (the gray images estimated on, when
    given; else the BGR images made gray), image_a's gray levels matched to image_b's over
    their overlap (:func:`matched_brightness`): aligned regions look gray, also across an
    exposure change.
    Each caption is wrapped to its panel's width (:func:`caption_lines`), a panel narrower than
    :data:`MIN_PANEL_WIDTH` enlarged first. Returns ``(panels, quad)``, ``quad`` the ``[4, 2]``
    corners of image_b in image_a, NaN for a corner beyond image_a's horizon
    (:func:`border_polygon`), in the images' own pixels; images with a side above
    :data:`OVERLAY_MAX_SIDE` are drawn at that long side (OpenCV warps below 32,767 px)."""
    import cv2

    if gray_a is None:
        gray_a = cv2.cvtColor(image_a, cv2.COLOR_BGR2GRAY)
    if gray_b is None:
        gray_b = cv2.cvtColor(image_b, cv2.COLOR_BGR2GRAY)
    h64 = np.asarray(h_ba, np.float64)
    hb, wb = image_b.shape[:2]
    quad = points_in_a(h64, np.array([[0, 0], [wb - 1, 0], [wb - 1, hb - 1], [0, hb - 1]],
                                     np.float64))
    scales = [min(1.0, OVERLAY_MAX_SIDE / max(im.shape[:2])) for im in (image_a, image_b)]
    if min(scales) < 1:  # a_small = S_a a, b_small = S_b b: H' = S_a H S_b^-1
        image_a, gray_a = (_shrunk(im, scales[0]) for im in (image_a, gray_a))
        image_b, gray_b = (_shrunk(im, scales[1]) for im in (image_b, gray_b))
        h64 = np.diag([scales[0], scales[0], 1.0]) @ h64 @ np.diag(
            [1 / scales[1], 1 / scales[1], 1.0])
    return _panels(image_a, image_b, h64, gray_a, gray_b), quad


def _shrunk(image, factor: float):
    """``image`` resized by ``factor`` (<= 1; ``cv2.INTER_AREA``)."""
    import cv2

    if factor == 1:
        return image
    size = (max(1, round(image.shape[1] * factor)), max(1, round(image.shape[0] * factor)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def _panels(image_a, image_b, h64, gray_a, gray_b):
    """:func:`overlay`'s drawing, at the images' size."""
    import cv2

    (ha, wa), (hb, wb) = image_a.shape[:2], image_b.shape[:2]
    warped_a = cv2.warpPerspective(gray_a, h64, (wb, hb),
                                   flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    valid = cv2.warpPerspective(np.ones((ha, wa), np.uint8), h64, (wb, hb),
                                flags=cv2.WARP_INVERSE_MAP | cv2.INTER_NEAREST) > 0
    ys, xs = np.mgrid[:hb, :wb]
    valid &= xs * h64[2, 0] + ys * h64[2, 1] + h64[2, 2] > IN_FRONT  # not the mirrored image
    warped_a = matched_brightness(warped_a, gray_b, valid)
    blend = np.stack([warped_a, gray_b, warped_a], axis=-1)  # BGR: a -> magenta, b -> green
    left = image_a.copy()
    thickness = max(1, round(max(wa, ha) / 300))
    drawn = border_polygon(h64, (wb, hb))
    if len(drawn):
        cv2.polylines(left, [np.round(drawn).astype(np.int32).reshape(-1, 1, 2)], True,
                      (0, 255, 0), thickness, cv2.LINE_AA)
    left, blend = _enlarged(left), _enlarged(blend)
    widths = (left.shape[1], blend.shape[1])
    scale = caption_scale(widths)
    lines = [caption_lines(c, w, scale) for c, w in zip(OVERLAY_CAPTIONS, widths)]
    band_height = _line_step(scale)[1] * max(map(len, lines)) + 4  # both panels start level
    panels = [np.concatenate([_caption_band(ls, w, scale, band_height), p], axis=0)
              for ls, w, p in zip(lines, widths, (left, blend))]
    height = max(p.shape[0] for p in panels)
    panels = [cv2.copyMakeBorder(p, 0, height - p.shape[0], 0, 8, cv2.BORDER_CONSTANT, value=0)
              for p in panels]
    return np.concatenate(panels, axis=1)
