"""Whole-image refinement of ``estimate_images`` (issue 46; a deviation from the paper, off by
default on patches: ``EstimateOptions(refine="images")``; part of
``EstimateOptions.photographs()``, ``estimate_images``' default).

The network and ``refine="ecc"`` align the central 128 x 128 patch of image_b; an error there
grows towards the corners of the 320 x 240 images. :func:`refine_images` scores the patch
refinement and OpenCV's ECC alignment over the whole work images, started from the nearest
optimum of patch_b's alignment (and from the pipeline's estimate, where that lies far from it),
and keeps the one that aligns the work images best (:func:`~stnh_tf.inference.coarse.image_ncc`), if
better than the estimate; the kept estimate's alignment NCC, ``verify="ecc"`` move and
implausibility flag are then those of the refined homography. A move of the kept estimate that
the whole images bring back to it does not flag it (:func:`move_confirmed`; issue 64). Where
the estimate is a zoom, the whole-image ECC and the scores see the two images at one
resolution (:func:`equal_resolution`, ``Thresholds.resolution_sigma``; issue 64, a deviation).

Frames: the estimate is a pixel ``H_ba`` (``a_from_b``) in the patch frame; the patch's top-left
corner lies at ``origin`` in the work images. NumPy and OpenCV only.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from stnh_tf import geometry
from stnh_tf.inference import checks, coarse
from stnh_tf.inference import search as search_lib
from stnh_tf.inference.image_input import central_patch
from stnh_tf.inference.options import EstimateOptions


def refine_images(est, work_a, work_b, options: EstimateOptions, origin):
    """``est`` (the ``Estimate`` of one pair, patch frame, before any patch refinement) refined
    over the whole work images with ``options.refine == "images"``; ``est`` itself otherwise, for
    a flat pair or a non-finite estimate, or where no candidate aligns ``work_a`` onto ``work_b``
    better than the estimate.

    The candidates: the patch refinement of ``refine="ecc"`` (ECC on patch_b started from the
    estimate, where it moves the corners by at most ``thresholds.max_refine_move``), and ECC over
    the whole images started from that patch refinement and, where it lies more than
    ``thresholds.max_verify_move`` from the estimate, from the estimate too (on a blurred, noisy
    patch_b the patch optimum can be off where the whole images' is not). The one that aligns
    the images best (:func:`~stnh_tf.inference.coarse.image_ncc`) is kept: one round. From an
    estimate beyond ECC's reach the kept result can be further off than the estimate. A refined
    estimate has ``refined`` set and is flagged by
    :func:`~stnh_tf.inference.coarse.flag` (the coarse pass's corner rule where
    ``options.wide_motions``, the trained range's without), as any estimate. An estimate kept as it
    is that ``verify="ecc"`` has not checked yet (``verify_move_px`` NaN: ``estimate_images``
    leaves the check to this step) gets the move to the patch optimum and its flag.

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
    # the whole-image ECC and the scores that choose between its results see the two images at
    # one resolution; the patch ECC and the flag's measures see them as they are
    patch_b = central_patch(work_b)[0, ..., 0]
    equal_a, equal_b = equal_resolution(work_a, work_b, geometry.patch_to_image(h0, *origin),
                                        t.resolution_sigma)
    ncc_of = lambda h: coarse.image_ncc(equal_a, equal_b, h, origin, t.min_overlap)  # noqa: E731
    best, best_ncc = h0, ncc_of(h0)
    starts = [h0]
    nearest = search_lib.ecc_refine(work_a, patch_b, h0, origin, t)
    if nearest is not None:
        if float(geometry.corner_errors(nearest[None], h0[None])[0]) <= t.max_refine_move:
            ncc = ncc_of(nearest)  # refine="ecc"'s result
            if ncc > best_ncc:
                best, best_ncc = nearest, ncc
        # from the estimate too where the patch optimum lies far from it (else one basin)
        starts = [nearest, h0] if _far(nearest, h0, work_a, origin, t) else [nearest]
    for start in starts:
        h = _whole_image_ecc(equal_a, equal_b, start, origin, t)
        ncc = -math.inf if h is None else ncc_of(h)
        if ncc > best_ncc:
            best, best_ncc = h, ncc
    if best is h0:
        return _verified(est, nearest, work_a, (equal_a, equal_b), origin, options)
    move, confirmed = est.verify_move_px, est.move_confirmed
    if options.verify == "ecc":
        checked = search_lib.ecc_refine(work_a, patch_b, best, origin, t)
        move = np.array([checks.verify_move(checked, best, np.shape(work_a), origin)])
        confirmed = np.array([move_confirmed(move[0], checked, best, equal_a, equal_b,
                                             np.shape(work_a), origin, t)])
    ncc = checks.alignment_ncc(work_a, patch_b, best, origin, t.min_overlap)
    refined = dataclasses.replace(est, homography=best[None], alignment_ncc=np.array([ncc]),
                                  refined=np.array([True]), verify_move_px=move,
                                  move_confirmed=confirmed)
    return coarse.flag(refined, options, wide=options.wide_motions)


MIN_BLUR = math.sqrt(1 / 6)
"""px: :func:`equal_resolution` leaves out a blur under this, the standard deviation of bilinear
interpolation's triangle kernel (0.41 px): no more than ECC's own sampling between pixels
smooths by."""


def resolution_blurs(a_from_b, size_b, sigma: float) -> tuple:
    """``(sigma_a, sigma_b)``: the Gaussian blurs (px, each in its own image) that bring image_a
    and image_b to one resolution under the image-frame ``a_from_b``: at the scale ``s`` of
    :func:`~stnh_tf.geometry.centre_scale`, ``sigma * sqrt(s**2 - 1)`` on image_a where
    ``s > 1`` (image_a is the sharper: one pixel of image_b spans ``s`` of image_a's),
    ``sigma * sqrt(1 / s**2 - 1)`` on image_b where ``s < 1``; ``(0, 0)`` at ``s = 1``, for
    ``sigma = 0`` or an undefined scale.

    >>> [round(x, 3) for x in resolution_blurs(np.diag([2.0, 2.0, 1.0]), (320, 240), 0.8)]
    [1.386, 0.0]
    """
    s = geometry.centre_scale(a_from_b, size_b)
    if sigma <= 0 or not s > 0:
        return 0.0, 0.0
    if s >= 1:
        return sigma * math.sqrt(s * s - 1), 0.0
    return 0.0, sigma * math.sqrt(1 / (s * s) - 1)


def equal_resolution(work_a, work_b, a_from_b, sigma: float) -> tuple:
    """``(work_a, work_b)`` with the sharper one blurred by :func:`resolution_blurs`
    (``cv2.GaussianBlur``, mirrored border; a blur under :data:`MIN_BLUR` is left out and the
    image returned as it is). ECC samples image_a at ``a_from_b(p)``: where image_b is a zoom out,
    one of its pixels spans several of image_a's, and sampling image_a there without this blur
    aliases its fine detail into the alignment (issue 64's zoom-outs). Frames as in
    :func:`resolution_blurs`; a deviation from the paper (``Thresholds.resolution_sigma``)."""
    sigma_a, sigma_b = resolution_blurs(a_from_b, np.shape(work_b)[::-1], sigma)
    blur = lambda x, s: (x if s < MIN_BLUR else cv2.GaussianBlur(  # noqa: E731
        x, (0, 0), s, borderType=cv2.BORDER_REFLECT_101))
    return blur(work_a, sigma_a), blur(work_b, sigma_b)


def move_confirmed(move, optimum, a_from_b, equal_a, equal_b, work_shape, origin,
                   thresholds) -> bool:
    """Whether ``verify="ecc"``'s move of the patch-frame ``a_from_b`` (``move`` px, to
    ``optimum``: patch_b's ECC optimum started from it; ``None`` where ECC failed) is excused
    (``Estimate.move_confirmed``): it is above ``thresholds.max_verify_move``, yet the whole
    work images align at least as well under ``a_from_b`` as under ``optimum``
    (:func:`~stnh_tf.inference.coarse.image_ncc`, defined under ``a_from_b``; no NCC floor: an
    exposure change lowers both, issue 79), and ECC over them started from ``optimum``
    comes back to within ``max_verify_move`` of ``a_from_b`` (measured as the move is,
    :func:`~stnh_tf.inference.checks.verify_move`, in the ``[h, w]`` ``work_shape``): patch_b's
    optimum then lies in the whole images' basin of the estimate (issue 64). ``equal_a``,
    ``equal_b``: the work images at one resolution (:func:`equal_resolution`), as the
    whole-image ECC sees them. False where the move is within the limit or ECC fails."""
    t = thresholds
    if optimum is None or not t.max_verify_move < move < math.inf:
        return False
    mine = coarse.image_ncc(equal_a, equal_b, a_from_b, origin, t.min_overlap)
    if not (math.isfinite(mine)  # undefined (-inf) under the estimate: never confirmed
            and mine >= coarse.image_ncc(equal_a, equal_b, optimum, origin, t.min_overlap)):
        return False
    back = _whole_image_ecc(equal_a, equal_b, optimum, origin, t)
    return back is not None and checks.verify_move(back, a_from_b, work_shape,
                                                   origin) <= t.max_verify_move


def _verified(est, nearest, work_a, equal, origin, options: EstimateOptions):
    """``est`` (kept as it is) with ``verify="ecc"``'s move, :func:`move_confirmed` and flag:
    the move to ``nearest``, patch_b's ECC optimum started from the estimate (``None``: ECC
    failed, ``inf``), where the pipeline left it to this step (``verify_move_px`` NaN); where it
    was measured before (the feature start's, a retry's), the flag again as for a refined
    estimate (:func:`~stnh_tf.inference.coarse.flag`) if the move is confirmed. ``equal``:
    ``(equal_a, equal_b)``."""
    if options.verify != "ecc":
        return est
    t, h = options.thresholds, est.homography[0]
    unverified = est.verify_move_px is None or np.isnan(est.verify_move_px[0])
    move = (checks.verify_move(nearest, h, np.shape(work_a), origin) if unverified
            else float(est.verify_move_px[0]))
    confirmed = move_confirmed(move, nearest, h, *equal, np.shape(work_a), origin, t)
    est = dataclasses.replace(est, verify_move_px=np.array([move]),
                              move_confirmed=np.array([confirmed]))
    if unverified:
        return dataclasses.replace(est, implausible=est.implausible | checks.moved(
            est.verify_move_px, est.move_confirmed, t))
    return coarse.flag(est, options, wide=options.wide_motions) if confirmed else est


def _far(h, h_ref, work_a, origin, thresholds) -> bool:
    """Whether ``h`` lies more than ``thresholds.max_verify_move`` from ``h_ref`` (mean over the
    work image's corners)."""
    return checks.frame_corner_distance(h, h_ref, np.shape(work_a),
                                        origin) > thresholds.max_verify_move


def _whole_image_ecc(work_a, work_b, h_patch, origin, thresholds):
    """ECC over the whole work images started from the patch-frame ``h_patch``: the patch-frame
    result (``[2, 2] = 1``), or ``None`` where ECC does not converge."""
    warp = search_lib.ecc_refine(work_a, work_b, geometry.patch_to_image(h_patch, *origin),
                                 (0, 0), thresholds)
    return None if warp is None else geometry.image_to_patch(warp, *origin)
