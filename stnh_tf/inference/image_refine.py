"""Whole-image refinement of ``estimate_images`` (issue 46; a deviation from the paper, off by
default: ``EstimateOptions(refine="images")``).

The network and ``refine="ecc"`` align the central 128 x 128 patch of image_b; an error there
grows towards the corners of the 320 x 240 images. :func:`refine_images` starts OpenCV's ECC
alignment over the whole work images from the final estimate and keeps its result where it
aligns the work images better (:func:`~stnh_tf.inference.coarse.image_ncc`); the kept estimate's
alignment NCC, ``verify="ecc"`` move and implausibility flag are then those of the refined
homography.

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
    estimate, where ECC does not converge, or where its result aligns ``work_a`` onto ``work_b``
    no better than the estimate. A refined estimate has ``refined`` set and is flagged by
    :func:`~stnh_tf.inference.coarse.flag` (the coarse pass's corner rule with
    ``options.coarse``, the trained range's without).

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
    to_patch = np.linalg.inv(geometry.translation(*origin))
    warp = search_lib.ecc_refine(work_a, work_b, coarse.to_work(h0, origin), (0, 0), t)
    if warp is None:
        return est
    h = geometry.scale_to_unit(to_patch @ warp @ np.linalg.inv(to_patch))
    if coarse.image_ncc(work_a, work_b, h, origin, t.min_overlap) <= coarse.image_ncc(
            work_a, work_b, h0, origin, t.min_overlap):
        return est
    patch_b = central_patch(work_b)[0, ..., 0]
    move = est.verify_move_px
    if options.verify == "ecc":
        checked = search_lib.ecc_refine(work_a, patch_b, h, origin, t)
        move = np.array([math.inf if checked is None else checks.frame_corner_distance(
            checked, h, np.shape(work_a), origin)])
    ncc = checks.alignment_ncc(work_a, patch_b, h, origin, t.min_overlap)
    refined = dataclasses.replace(est, homography=h[None], alignment_ncc=np.array([ncc]),
                                  refined=np.array([True]), verify_move_px=move)
    return coarse.flag(refined, options, wide=options.coarse != "none")
