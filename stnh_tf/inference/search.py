"""The estimator's alignment steps after the network: the search of a poorly aligned estimate
(:func:`search_translations`) and the ECC refinement (:func:`ecc_refine`). NumPy, OpenCV and
SciPy; the thresholds come from :class:`~stnh_tf.inference.options.Thresholds`, the search's
sizes and iteration limits are the constants below.
"""

from __future__ import annotations

import cv2
import numpy as np

from stnh_tf import geometry, hierarchy
from stnh_tf.inference import ecc
from stnh_tf.inference.checks import alignment_ncc, corner_shift
from stnh_tf.inference.options import Thresholds

_DEFAULT = Thresholds()
SEARCH_TEMPLATE_PX = 64
"""Side of patch_b's central square slid over the warped patch_a: translations up to
``(128 - 64) / 2`` px are scored."""
SEARCH_PEAKS = 8
"""Translation peaks the search starts coarse-to-fine ECC from (its iteration limits:
:func:`stnh_tf.inference.ecc.coarse_to_fine_ecc`'s defaults)."""


def ecc_refine(source_a, patch_b, a_from_b, origin=(0, 0), thresholds: Thresholds = _DEFAULT):
    """``a_from_b`` refined by OpenCV's ECC alignment (``cv2.findTransformECC``,
    ``MOTION_HOMOGRAPHY``; ``thresholds.refine_iterations``, ``refine_eps``, no pre-filter),
    started from it: the homography maximising the correlation of ``patch_b`` and patch_a warped
    onto it, over the pixels that land inside ``source_a``.

    Args:
      source_a: ``[h, w]`` image holding patch_a with its top-left corner at ``origin`` (the patch
        itself with ``(0, 0)``, or the image it was cut from as context).
      patch_b: ``[S, S]`` (any real scale: ECC ignores gain and offset).
      a_from_b: ``[3, 3]`` pixel ``H_ba`` in the patch frame, the starting point.
    Returns:
      float64 ``[3, 3]`` refined ``H_ba`` in the patch frame (``[2, 2] = 1``), or ``None`` where
      ECC does not converge (OpenCV raises) or gives a non-finite matrix.

    >>> p = cv2.GaussianBlur(np.random.default_rng(0).random((128, 128), np.float32), (0, 0), 2)
    >>> b = cv2.warpPerspective(p, geometry.translation(1.5, -1.0), (128, 128),
    ...                         flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    >>> np.round(ecc_refine(p, b, np.eye(3))[:2, 2], 1)
    array([ 1.5, -1. ])
    """
    source_from_patch = geometry.translation(*origin)
    warp = ecc.opencv_ecc(source_a, patch_b, source_from_patch @ np.asarray(a_from_b, np.float64),
                          thresholds.refine_iterations, thresholds.refine_eps)
    return None if warp is None else geometry.scale_to_unit(np.linalg.inv(source_from_patch) @ warp)


def search_translations(source_a, patch_b, a_from_b, origin=(0, 0),
                        thresholds: Thresholds = _DEFAULT):
    """A homography near ``a_from_b`` that aligns the pair almost perfectly, or ``None``.

    Patch_a is warped onto patch_b by ``a_from_b`` (mirror fill beyond ``source_a``), the central
    :data:`SEARCH_TEMPLATE_PX` square of ``patch_b`` is slid over it (``cv2.matchTemplate``,
    ``TM_CCOEFF_NORMED``), and from the translations ``d`` at its :data:`SEARCH_PEAKS`
    highest local peaks coarse-to-fine ECC (:func:`stnh_tf.inference.ecc.coarse_to_fine_ecc`) is
    started at ``a_from_b @ T(d)``. Of the results whose :func:`alignment_ncc` reaches
    ``thresholds.verified_ncc``, the highest is returned (the better-ranked peak on a tie). It
    finds the estimate that a network put one period off on a repetitive texture, or a few px off
    under an exposure change; the same result on every CPU.

    Args:
      source_a: ``[h, w]`` image holding patch_a with its top-left corner at ``origin``.
      patch_b: ``[S, S]`` (any real scale).
      a_from_b: ``[3, 3]`` pixel ``H_ba`` in the patch frame, the estimate searched around.
    Returns:
      ``(h, ncc)``: float64 ``[3, 3]`` ``H_ba`` in the patch frame (``[2, 2] = 1``) and its
      :func:`alignment_ncc`; ``None`` where no result reaches ``thresholds.verified_ncc``.

    >>> p = cv2.GaussianBlur(np.random.default_rng(0).random((128, 128), np.float32), (0, 0), 2)
    >>> b = cv2.warpPerspective(p, geometry.translation(9.0, -6.0), (128, 128),
    ...                         flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    >>> h, ncc = search_translations(p, b, np.eye(3))
    >>> np.round(h[:2, 2], 1), ncc > 0.95
    (array([ 9., -6.]), True)
    """
    size, side = np.shape(patch_b)[0], SEARCH_TEMPLATE_PX
    margin = (size - side) // 2
    b = np.asarray(patch_b, np.float32)
    warped = hierarchy.warp_crop(source_a, a_from_b, origin, size, fill="reflect")
    scores = cv2.matchTemplate(warped, b[margin:margin + side, margin:margin + side],
                               cv2.TM_CCOEFF_NORMED)
    scores = np.nan_to_num(scores, nan=-1.0)
    ys, xs = np.nonzero(scores >= cv2.dilate(scores, np.ones((5, 5), np.uint8)))
    source_from_patch = geometry.translation(*origin)
    best = None
    for k in np.argsort(-scores[ys, xs], kind="stable")[:SEARCH_PEAKS]:
        start = np.asarray(a_from_b, np.float64) @ geometry.translation(xs[k] - margin,
                                                                         ys[k] - margin)
        h = ecc.coarse_to_fine_ecc(source_a, b, source_from_patch @ start)
        if h is None:
            continue
        h = geometry.scale_to_unit(np.linalg.inv(source_from_patch) @ h)
        if not np.isfinite(corner_shift(h[None])[0]):
            continue
        ncc = alignment_ncc(source_a, b, h, origin, thresholds.min_overlap)
        if ncc >= thresholds.verified_ncc and (best is None or ncc > best[1]):
            best = (h, ncc)
    return best
