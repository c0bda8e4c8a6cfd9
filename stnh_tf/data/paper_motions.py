"""The paper's own protocol as a set of camera pairs (issue 79): whole 320 x 240 images, image_b
the source warped by the homography that moves the central 128 x 128 square's corners by
independent uniform offsets of up to 32 px (conventions.md, section 2; DeTone et al. 2016), with
the photograph's context around it instead of the paper's crops. Pairs are made by
:func:`stnh_tf.data.camera_pair_files.make_image_pairs` with ``motion_set="paper"``; frames and
rendering as :mod:`stnh_tf.data.camera_motions`'. Their errors are measured at the patch's
corners, the paper's MACE (:data:`PATCH_FRAME_GROUPS`): a strongly projective draw can put
image_b's own corners beyond image_a's horizon, where no estimate has a finite error. There,
image_b's pixels beyond the horizon hold what ``cv2.warpPerspective`` samples behind the camera
(the mirrored source at the point the homography gives): they are part of the pair as every
method sees it, not masked. NumPy/OpenCV only.
"""

from __future__ import annotations

import cv2
import numpy as np

from stnh_tf import geometry
from stnh_tf.data.camera_motions import (PAPER_GROUPS, PATCH_ORIGIN, Degradation,
                                         draw_degradation)

KIND = "paper_protocol"
"""The kind of every pair of the set."""

PATCH_FRAME_GROUPS = PAPER_GROUPS
"""Groups whose errors are measured at the central patch's corners (the paper's MACE) rather
than the image's: ``"paper"`` (no change but 8-bit rounding and JPEG at quality 100) and
``"paper_exposure"`` (image_b exposed 1 to 2 stops darker or brighter: :data:`EXPOSURE`)."""

PLAIN = Degradation(blur_sigma=(0.0, 0.0), exposure_ev=(0.0, 0.0), read_noise=(0.0, 0.0),
                    shot_noise=(0.0, 0.0), jpeg_quality=(100, 100))
"""The ``"paper"`` group's degradation: none beyond rounding and a quality-100 JPEG."""

EXPOSURE = Degradation(blur_sigma=(0.0, 0.0), exposure_ev=(1.0, 2.0), read_noise=(0.0, 0.0),
                       shot_noise=(0.0, 0.0), jpeg_quality=(100, 100))
"""The ``"paper_exposure"`` group's: an exposure change of 1 to 2 stops (its sign drawn by
:func:`group_degradation`), clipped at saturation."""


def draw_paper_motion(rng: np.random.Generator, max_offset: float = geometry.MAX_PERTURBATION):
    """The paper's motion: each corner of the 128 x 128 square at
    :data:`~stnh_tf.data.camera_motions.PATCH_ORIGIN` moved by independent uniform offsets in
    ``[-max_offset, max_offset]`` (x, then y, corner by corner), ``h_ba =
    getPerspectiveTransform(square, moved)`` in the 320 x 240 work frame.

    Returns:
      ``(KIND, {"corner_offsets": [[dx, dy] x 4]}, h_ba)``.

    >>> kind, motion, h = draw_paper_motion(np.random.default_rng(0))
    >>> kind, len(motion["corner_offsets"]), round(float(h[2, 2]), 6)
    ('paper_protocol', 4, 1.0)
    """
    offsets = rng.uniform(-max_offset, max_offset, (4, 2))
    x0, y0 = PATCH_ORIGIN
    size = geometry.PATCH_SIZE
    square = np.float32([[x0, y0], [x0 + size, y0], [x0 + size, y0 + size], [x0, y0 + size]])
    h_ba = cv2.getPerspectiveTransform(square, (square + offsets).astype(np.float32))
    return KIND, {"corner_offsets": offsets.round(6).tolist()}, h_ba / h_ba[2, 2]


def group_degradation(rng: np.random.Generator, group: str) -> dict:
    """One pair's degradation parameters for a paper group (as
    :func:`~stnh_tf.data.camera_motions.draw_degradation` draws them), the exposure change's
    sign drawn apart for ``"paper_exposure"``."""
    params = draw_degradation(rng, EXPOSURE if group == "paper_exposure" else PLAIN)
    if group == "paper_exposure" and rng.random() < 0.5:
        params["exposure_ev"] = -params["exposure_ev"]
    return params
