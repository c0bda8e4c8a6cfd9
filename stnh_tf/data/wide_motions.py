"""The wide-baseline set of realistic camera pairs (issue 64): motions at full range (zoom
0.3-3.0, in-plane rotation up to +-180 degrees, a plane's viewpoint up to 60 degrees), kept where
the two views overlap, and a low-light degradation. Pairs are made by
:func:`stnh_tf.data.camera_pair_files.make_image_pairs` with ``motion_set="wide"``; frames
and rendering as :mod:`stnh_tf.data.camera_motions`'. NumPy/OpenCV only.
"""

from __future__ import annotations

import cv2
import numpy as np

from stnh_tf import geometry
from stnh_tf.data.camera_motions import (KINDS, WORK_SIZE, Degradation, MotionRanges,
                                         _draw_full, _homography)

WIDE_MOTIONS = MotionRanges(zoom=(0.3, 3.0), roll_deg=180.0, view_deg=60.0, shift_px=48.0)
"""The wide-baseline set's ranges (issue 64), each motion drawn at full range
(:func:`draw_wide_motion`): zoom 0.3-3.0, in-plane rotation up to +-180 degrees (every kind),
a plane's viewpoint up to 60 degrees, shifts up to +-48 px; the rest as
:class:`~stnh_tf.data.camera_motions.MotionRanges`' defaults."""

LOW_LIGHT = Degradation(blur_sigma=(0.5, 2.0), exposure_ev=(-3.0, -1.5), read_noise=(2.0, 6.0),
                        shot_noise=(0.1, 0.5), jpeg_quality=(40, 85))
"""Low light (issue 64): darker by 1.5-3 stops, blurred, noisier, more compressed than
:class:`~stnh_tf.data.camera_motions.Degradation`'s defaults."""

MIN_OVERLAP = 0.5
"""A wide motion is kept where at least this share of the smaller of image_a and image_b's view
(in image_a's frame) lies in both (:func:`overlap`)."""


def overlap(h_ba, size=WORK_SIZE) -> float:
    """The share of the smaller of image_a and image_b's view that both see: image_b's frame
    mapped into image_a's by ``h_ba`` (a convex quadrilateral where
    :func:`stnh_tf.geometry.in_front`) intersected with image_a's
    (``cv2.intersectConvexConvex``), over the smaller of the two areas; 0 where a corner of
    image_b lies behind camera a.

    >>> overlap(np.eye(3)), overlap(geometry.translation(160.0, 0.0))
    (1.0, 0.5)
    """
    if not geometry.in_front(h_ba, size):
        return 0.0
    w, h = size
    frame = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64)
    view_b = cv2.perspectiveTransform(frame[None], np.asarray(h_ba, np.float64))[0]
    area, _ = cv2.intersectConvexConvex(frame.astype(np.float32), view_b.astype(np.float32))
    smaller = min(float(w * h), abs(float(cv2.contourArea(view_b.astype(np.float32)))))
    return float(area) / smaller if smaller > 0 else 0.0


def draw_wide_motion(rng: np.random.Generator, ranges: MotionRanges = WIDE_MOTIONS,
                     max_draws: int = 1000):
    """A motion of the wide-baseline set: a kind (uniform over :data:`KINDS`) and its parameters
    at the full range of ``ranges`` (not scaled towards the identity), drawn again until
    :func:`overlap` reaches :data:`MIN_OVERLAP` (so image_b's corners also lie in front of
    camera a).

    Returns:
      ``(kind, params, h_ba)``, params with ``"overlap"``.
    Raises:
      RuntimeError: no draw overlapped enough in ``max_draws`` tries.
    """
    kind = KINDS[int(rng.integers(len(KINDS)))]
    for _ in range(max_draws):
        params = _draw_full(rng, kind, ranges)
        h = _homography(kind, params)
        share = overlap(h)
        if share >= MIN_OVERLAP:
            return kind, {**params, "overlap": share}, h
    raise RuntimeError(f"no wide motion of kind {kind!r} overlapped in {max_draws} draws.")
