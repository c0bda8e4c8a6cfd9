"""The low-overlap set of realistic camera pairs (issue 79, item 4), what people stitching
panoramas need: camera b is camera a turned about its centre by 20-40 degrees (a pan, a tilt or
both, in a uniform direction), with a small roll and zoom, kept where the two views overlap by
30-60% (:func:`stnh_tf.data.wide_motions.overlap`); image_b's centre may lie outside image_a.
Pairs are made by :func:`stnh_tf.data.camera_pair_files.make_image_pairs` with
``motion_set="low_overlap"``, group ``"low_overlap"``, the
:class:`~stnh_tf.data.camera_motions.Degradation` of the other groups. NumPy/OpenCV only.

Frames as :mod:`stnh_tf.data.camera_motions`': ``h_ba`` (``a_from_b``) maps image_b's pixels
to image_a's in the 320 x 240 frame, ``image_b(p) = image_a(h_ba @ p)`` before the degradation.

Where image_a lies (:func:`window_origin`). With image_a at the 560 x 420 source's centre, a
20-40 degree turn puts much of image_b beyond the source, where
:func:`~stnh_tf.data.camera_motions.render_pair` samples the source's mirror image: not a real
camera's view, and mirrored content can give false matches. So each pair places image_a's
window (an integer top-left corner in the source, ``[0, 240] x [0, 180]``) where the most of
image_b's pixels sample the source itself, off-centre against the turn (of those places, the
nearest to the centre, :data:`~stnh_tf.data.camera_motions.MARGIN`), and a motion whose
image_b would still sample the mirror image at more than :data:`MAX_MIRRORED` of its pixels is
drawn again. Each pair's motion records ``"window_origin"`` and ``"mirrored_share"``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from stnh_tf.data.camera_motions import (MARGIN, SOURCE_SIZE, WORK_SIZE, MotionRanges,
                                         _homography)
from stnh_tf.data.wide_motions import overlap

KIND = "camera_rotation"
"""Every pair's kind: a rotation about the camera centre with zoom
(:func:`~stnh_tf.data.camera_motions.rotation_homography`)."""

OVERLAP_MOTIONS = MotionRanges(fov_deg=(45.0, 75.0), zoom=(0.9, 1.1), roll_deg=5.0,
                               pan_deg=40.0)
"""The set's ranges: camera a's field of view 45-75 degrees, zoom 0.9-1.1 (log-uniform), roll
up to +-5 degrees; ``pan_deg`` is the largest turn (:data:`PAN_DEG`; the other fields do not
apply)."""

PAN_DEG = (20.0, 40.0)
"""The angle between the two cameras' optical axes (degrees), uniform."""

OVERLAP = (0.3, 0.6)
"""A motion is kept where :func:`~stnh_tf.data.wide_motions.overlap` lies in this interval
(both ends included)."""

MAX_MIRRORED = 0.1
"""A motion is kept where at most this share of image_b's pixels sample the source's mirror
image (:func:`mirrored_share` at :func:`window_origin`)."""

_ORIGIN_MAX = (2 * MARGIN[0], 2 * MARGIN[1])  # image_a's window anywhere in the source


def turn_angles(pan: float, direction: float) -> tuple:
    """``(yaw, pitch)`` (radians) of :func:`~stnh_tf.data.camera_motions.rotation` (with any
    roll) that turn camera b's optical axis by ``pan`` from camera a's, towards ``direction`` in
    image_a (radians; 0: right, pi / 2: down): image_b's centre then lies in image_a at
    ``centre + focal * tan(pan) * (cos direction, sin direction)``, whatever the zoom and roll.

    >>> [round(math.degrees(v), 6) for v in turn_angles(math.radians(30), 0.0)]
    [-30.0, 0.0]
    """
    axis = (math.sin(pan) * math.cos(direction), math.sin(pan) * math.sin(direction),
            math.cos(pan))  # camera b's optical axis in camera a's coordinates
    return math.atan2(-axis[0], axis[2]), math.asin(axis[1])


def _image_b_in_a(h_ba) -> np.ndarray:
    """Image_b's pixel centres mapped into image_a's frame by ``h_ba``: float64 ``[N, 2]``."""
    ys, xs = np.mgrid[0:WORK_SIZE[1], 0:WORK_SIZE[0]]
    grid = np.stack([xs.ravel(), ys.ravel()], -1).astype(np.float64)
    return cv2.perspectiveTransform(grid[None], np.asarray(h_ba, np.float64))[0]


def _share_beyond(q, origin) -> float:
    q = q + np.asarray(origin, np.float64)
    return float(1.0 - np.all((q >= 0) & (q <= np.array(SOURCE_SIZE) - 1), axis=1).mean())


def mirrored_share(h_ba, origin=MARGIN) -> float:
    """The share of image_b's pixels (320 x 240 frame) that
    :func:`~stnh_tf.data.camera_motions.render_pair` samples beyond the 560 x 420 source (its
    mirror image) with image_a's top-left corner at ``origin`` ``(x, y)``: those whose
    ``h_ba @ p + origin`` lies outside ``[0, 559] x [0, 419]``."""
    return _share_beyond(_image_b_in_a(h_ba), origin)


def window_origin(h_ba) -> tuple:
    """Where to put image_a's window in the source for the pair ``h_ba``: of the integer
    top-left corners ``(x, y)`` in ``[0, 240] x [0, 180]``, one where the fewest of image_b's
    pixels sample the mirror image (counted by a summed-area table of their positions, exact
    but for points exactly on the source's far edges), the nearest to
    :data:`~stnh_tf.data.camera_motions.MARGIN` of those.

    Returns:
      ``((x, y), mirrored_share(h_ba, (x, y)))``.

    >>> window_origin(np.eye(3))
    ((120, 90), 0.0)
    """
    (sw, sh), (mx, my) = SOURCE_SIZE, _ORIGIN_MAX
    q = _image_b_in_a(h_ba)
    # bin b = floor(q) inside for origin o when b in [-o, size - 2 - o]: bins -max .. size - 2
    b = (np.floor(q) + np.array([mx, my])).astype(np.int64)
    keep = np.all((b >= 0) & (b <= np.array([mx + sw - 2, my + sh - 2])), axis=1)
    counts = np.bincount(b[keep, 1] * (mx + sw - 1) + b[keep, 0],
                         minlength=(my + sh - 1) * (mx + sw - 1)).reshape(my + sh - 1, -1)
    table = np.pad(counts.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    ox, oy = np.arange(mx + 1), np.arange(my + 1)[:, None]
    x0, y0 = mx - ox, my - oy  # the window of bins [x0, x0 + sw - 2] x [y0, y0 + sh - 2]
    x1, y1 = x0 + sw - 1, y0 + sh - 1
    inside = table[y1, x1] - table[y0, x1] - table[y1, x0] + table[y0, x0]
    best = inside == inside.max()
    distance = np.where(best, (ox - MARGIN[0]) ** 2 + (oy - MARGIN[1]) ** 2, np.inf)
    y, x = np.unravel_index(int(np.argmin(distance)), distance.shape)
    return (int(x), int(y)), _share_beyond(q, (int(x), int(y)))


def draw_overlap_motion(rng: np.random.Generator, ranges: MotionRanges = OVERLAP_MOTIONS,
                        max_draws: int = 1000):
    """A motion of the low-overlap set: camera a's focal length from ``ranges.fov_deg``, zoom
    (log-uniform) and roll (uniform in ``+-ranges.roll_deg``) as ``ranges`` gives them, a turn
    uniform in :data:`PAN_DEG` (up to ``ranges.pan_deg``) in a direction uniform in [0, 360)
    degrees (:func:`turn_angles`), drawn again until :func:`~stnh_tf.data.wide_motions.overlap`
    lies in :data:`OVERLAP` and :func:`window_origin` leaves at most :data:`MAX_MIRRORED` of
    image_b mirrored.

    Returns:
      ``(KIND, params, h_ba)``: params (JSON-ready) ``focal``, ``zoom``, ``roll_deg``,
      ``pan_deg``, ``pan_dir_deg``, ``yaw_deg``, ``pitch_deg`` (as
      :func:`~stnh_tf.data.camera_motions.rotation_homography` takes them), ``overlap``,
      ``window_origin`` (``[x, y]``, for ``render_pair``'s ``origin``) and ``mirrored_share``.
    Raises:
      RuntimeError: no draw fitted in ``max_draws`` tries.
    """
    lo, hi = PAN_DEG[0], min(PAN_DEG[1], ranges.pan_deg)
    for _ in range(max_draws):
        fov = math.radians(rng.uniform(*ranges.fov_deg))
        p = {"focal": WORK_SIZE[0] / 2 / math.tan(fov / 2),
             "zoom": float(np.exp(rng.uniform(*np.log(ranges.zoom)))),
             "roll_deg": float(rng.uniform(-ranges.roll_deg, ranges.roll_deg)),
             "pan_deg": float(rng.uniform(lo, hi)), "pan_dir_deg": float(rng.uniform(0, 360))}
        yaw, pitch = turn_angles(math.radians(p["pan_deg"]), math.radians(p["pan_dir_deg"]))
        p.update(yaw_deg=math.degrees(yaw), pitch_deg=math.degrees(pitch))
        h = _homography(KIND, p)
        share = overlap(h)
        if not OVERLAP[0] <= share <= OVERLAP[1]:
            continue
        origin, mirrored = window_origin(h)
        if mirrored <= MAX_MIRRORED:
            return KIND, {**p, "overlap": share, "window_origin": list(origin),
                          "mirrored_share": mirrored}, h
    raise RuntimeError(f"no low-overlap motion fitted in {max_draws} draws.")
