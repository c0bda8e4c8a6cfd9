"""Whole-image refinement of ``estimate_images`` (issue 46; a deviation from the paper, off by
default: ``EstimateOptions(refine="images")``).

The network and ``refine="ecc"`` align the central 128 x 128 patch of image_b; an error there
grows towards the corners of the 320 x 240 images. :func:`refine_images` starts OpenCV's ECC
alignment over the whole work images from the final estimate (and from the nearest optimum of
patch_b's alignment, where that is far from it) and keeps the result that aligns the work images
best (:func:`~stnh_tf.inference.coarse.image_ncc`), if better than the estimate; the kept
estimate's alignment NCC, ``verify="ecc"`` move and implausibility flag are then those of the
refined homography.

Frames: the estimate is a pixel ``H_ba`` (``a_from_b``) in the patch frame; the patch's top-left
corner lies at ``origin`` in the work images. NumPy and OpenCV only.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from stnh_tf import geometry
from stnh_tf.inference import checks, coarse
from stnh_tf.inference import search as search_lib
from stnh_tf.inference.image_input import central_patch
from stnh_tf.inference.options import EstimateOptions


def refine_images(est, work_a, work_b, options: EstimateOptions, origin):
    """``est`` (the ``Estimate`` of one pair, patch frame) refined over the whole work images
    with ``options.refine == "images"``; ``est`` itself otherwise, for a flat pair or a non-finite
    estimate, or where no refinement aligns ``work_a`` onto ``work_b`` better than the estimate.

    ECC over the whole images starts from the estimate and, where ECC on patch_b alone moves the
    estimate by more than ``thresholds.max_verify_move`` (the estimate is off its nearest
    optimum: ``verify="ecc"``'s signal), also from that patch optimum; the result that aligns the
    images best (:func:`~stnh_tf.inference.coarse.image_ncc`) is kept. From an estimate beyond
    ECC's reach the kept result can be further off than the estimate. A refined estimate has
    ``refined`` set and is flagged by :func:`~stnh_tf.inference.coarse.flag` (the coarse pass's
    corner rule with ``options.coarse``, the trained range's without), as any estimate.

    Args:
      est: an ``Estimate`` with B = 1.
      work_a, work_b: the ``[240, 320]`` float work images.
      options: the estimate's options.
      origin: ``(x0, y0)`` of the central patch in the work images.
    """
    h0 = np.asarray(est.homography[0], np.float64)
    if options.refine != "images" or est.flat[0] or not np.isfinite(h0).all():
        return est
    t = options.thresholds
    patch_b = central_patch(work_b)[0, ..., 0]
    starts = [h0]
    nearest = search_lib.ecc_refine(work_a, patch_b, h0, origin, t)
    if nearest is not None and checks.frame_corner_distance(
            nearest, h0, np.shape(work_a), origin) > t.max_verify_move:
        starts.append(nearest)
    best, best_ncc = h0, coarse.image_ncc(work_a, work_b, h0, origin, t.min_overlap)
    for start in starts:
        h = _whole_image_ecc(work_a, work_b, start, origin, t)
        ncc = -math.inf if h is None else coarse.image_ncc(work_a, work_b, h, origin,
                                                            t.min_overlap)
        if ncc > best_ncc:
            best, best_ncc = h, ncc
    if best is h0:
        return est
    move = est.verify_move_px
    if options.verify == "ecc":
        checked = search_lib.ecc_refine(work_a, patch_b, best, origin, t)
        move = np.array([math.inf if checked is None else checks.frame_corner_distance(
            checked, best, np.shape(work_a), origin)])
    ncc = checks.alignment_ncc(work_a, patch_b, best, origin, t.min_overlap)
    refined = dataclasses.replace(est, homography=best[None], alignment_ncc=np.array([ncc]),
                                  refined=np.array([True]), verify_move_px=move)
    return coarse.flag(refined, options, wide=options.coarse != "none")


def _whole_image_ecc(work_a, work_b, h_patch, origin, thresholds):
    """ECC over the whole work images started from the patch-frame ``h_patch``: the patch-frame
    result (``[2, 2] = 1``), or ``None`` where ECC does not converge."""
    warp = search_lib.ecc_refine(work_a, work_b, geometry.patch_to_image(h_patch, *origin),
                                 (0, 0), thresholds)
    return None if warp is None else geometry.image_to_patch(warp, *origin)
