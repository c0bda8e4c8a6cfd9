"""The coarse pass of ``estimate_images`` for motions beyond the trained range (issue 46, item 2;
a deviation from the paper, off by default: ``EstimateOptions(coarse="rotations")``).

The stages were trained on corners moved by up to 32 px in the 128 x 128 patch. A pair whose
default estimate aligns it poorly (:func:`needs_pass`: the search's trigger) is tried again
(:func:`coarse_pass`): each rotation and zoom about the image centre of
:data:`~stnh_tf.inference.options.COARSES`, followed by the translation that best matches
image_b's central square (:func:`translated_start`), is a start ``G``; image_a is warped by the
best matched ones (:func:`warp_context`), the network alone estimates the rest ``H`` from each,
and the start whose ``G @ H`` aligns the whole 320 x 240 work images best (:func:`image_ncc`) is
run through the estimator's full pipeline; its result replaces the default estimate where it
aligns the work images better. The flag then reads the whole motion against
``thresholds.coarse_corner_shift`` (4x the trained range) instead of
``implausible_corner_shift`` (:func:`flag`): an estimate beyond that, or one that aligns poorly,
is beyond what the pass handles.

Frames: ``G`` and ``H`` are pixel ``H_ba`` (``a_from_b``) in the patch frame
(:mod:`stnh_tf.geometry`); the patch's top-left corner lies at ``origin`` in the work image.
NumPy and OpenCV only.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from stnh_tf import geometry
from stnh_tf.inference import checks, pipeline
from stnh_tf.inference.image_input import central_patch
from stnh_tf.inference.options import COARSES, EstimateOptions
from stnh_tf.pixels import unclipped

def start_homography(angle_deg: float, zoom: float, size: int = geometry.PATCH_SIZE):
    """``[3, 3]`` float64 ``a_from_b`` in the ``size x size`` patch frame: rotation by
    ``angle_deg`` (counter-clockwise on screen for positive angles: y points down) and scaling by
    ``zoom`` about the patch centre ``((size - 1) / 2, (size - 1) / 2)``, which is the centre of
    the 320 x 240 work image too.

    >>> np.allclose(start_homography(0.0, 1.0), np.eye(3))
    True
    """
    c = (size - 1) / 2.0
    t = math.radians(angle_deg)
    rs = zoom * np.array([[math.cos(t), math.sin(t), 0.0],
                          [-math.sin(t), math.cos(t), 0.0], [0.0, 0.0, 1.0]])
    return geometry.translation(c, c) @ rs @ geometry.translation(-c, -c)


def starts(name: str) -> np.ndarray:
    """The coarse starts of ``COARSES[name]`` as float64 ``[K, 3, 3]`` (the identity first)."""
    return np.stack([start_homography(a, z) for a, z in COARSES[name]])


def warp_context(work_a, start, origin) -> np.ndarray:
    """``work_a`` warped by the patch-frame start ``G``: ``out(q) = work_a(T G inv(T) q)``
    (bilinear, zero outside; same shape and dtype float32). Estimating ``H`` between ``out`` and
    image_b then estimates ``G @ H`` between ``work_a`` and image_b."""
    h, w = np.shape(work_a)[:2]
    return cv2.warpPerspective(np.asarray(work_a, np.float32), geometry.patch_to_image(start, *origin), (w, h),
                               flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)


def image_ncc(work_a, work_b, h_patch, origin, min_overlap: float) -> float:
    """NCC between the whole ``work_b`` and ``work_a`` warped onto it by the patch-frame
    ``a_from_b`` ``h_patch``, over the pixels whose source lies inside ``work_a``; where fewer
    than ``min_overlap`` of them do (image_b sees image_a small: a zoom out), the same the other
    way (``work_a`` and ``work_b`` warped onto it by ``inv(h_patch)``; issue 64); over the
    pixels clipped in neither image (:func:`stnh_tf.pixels.unclipped`); ``-inf`` where neither
    way overlaps enough, fewer than :data:`~stnh_tf.inference.checks.MIN_UNCLIPPED` pixels are
    not clipped, either side is constant there, or ``h_patch`` is not finite or singular (so
    that it ranks below every defined NCC)."""
    forward = _one_way_ncc(work_a, work_b, h_patch, origin, min_overlap)
    if forward is not None:
        return forward
    try:
        b_from_a = np.linalg.inv(np.asarray(h_patch, np.float64))
    except np.linalg.LinAlgError:
        return -math.inf
    backward = _one_way_ncc(work_b, work_a, b_from_a, origin, min_overlap)
    return -math.inf if backward is None else backward


def _one_way_ncc(work_a, work_b, h_patch, origin, min_overlap: float):
    """:func:`image_ncc` one way: ``None`` where fewer than ``min_overlap`` of work_b's pixels
    have their source inside work_a (or ``h_patch`` is not finite), ``-inf`` where a side is
    constant there."""
    if not np.isfinite(h_patch).all():
        return None
    warped, inside = checks.warped_onto(work_a, h_patch, origin, np.shape(work_b))
    if inside.mean() < min_overlap:
        return None
    inside = inside & unclipped(work_b) & unclipped(warped)
    if inside.sum() < checks.MIN_UNCLIPPED:
        return -math.inf
    x = warped[inside].astype(np.float64)
    y = np.asarray(work_b, np.float64)[inside]
    x, y = x - x.mean(), y - y.mean()
    norm = math.sqrt(float((x * x).sum() * (y * y).sum()))
    return float((x * y).sum() / norm) if norm > 1e-12 else -math.inf


def needs_pass(first, options: EstimateOptions) -> bool:
    """Whether the default estimate ``first`` (an ``Estimate`` of one pair) is tried again: the
    pair is not flat and :func:`~stnh_tf.inference.checks.beyond` with
    ``thresholds.search_below_ncc`` holds (the search's trigger)."""
    t = options.thresholds
    return bool(~first.flat[0] & checks.beyond(first.rejected_stages, first.max_corner_shift_px,
                                               first.alignment_ncc, t.search_below_ncc, t)[0])


TEMPLATE = 96
"""Side (px) of work_b's central square that :func:`translated_start` matches."""


def translated_start(context, work_b, start, origin, template: int = TEMPLATE):
    """``(score, G @ D)``: the start ``G`` followed by the translation ``D`` (patch frame) that
    best matches work_b's central ``template`` square inside ``context`` (work_a warped by
    ``G``): ``cv2.matchTemplate`` with ``TM_CCOEFF_NORMED``, so translations up to the context's
    margin around the square (112 px in x, 72 px in y for 96 px at 320 x 240) are found;
    ``score`` is its peak."""
    h, w = np.shape(work_b)[:2]
    x0, y0 = (w - template) // 2, (h - template) // 2
    square = np.asarray(work_b, np.float32)[y0:y0 + template, x0:x0 + template]
    scores = cv2.matchTemplate(np.asarray(context, np.float32), square, cv2.TM_CCOEFF_NORMED)
    _, score, _, (x, y) = cv2.minMaxLoc(np.nan_to_num(scores, nan=-1.0))
    return float(score), start @ geometry.translation(x - x0, y - y0)


def best_start(run, work_a, work_b, options: EstimateOptions, origin, keep: int = 4):
    """The start whose network estimate aligns the work images best: each rotation and zoom ``G``
    of ``options.coarse`` with its best translation (:func:`translated_start`); the ``keep``
    starts that match best go through ``run(patch_a, patch_b, contexts, options)`` (the estimator
    on ``[K, S, S, 1]`` patches with their contexts; here without search, refinement,
    verification or augmentation) from work_a warped by each, and each start times the
    network's estimate is scored by :func:`image_ncc`. Returns ``(start, the warped work_a, its
    NCC)``; the first wins a tie."""
    matched = sorted((translated_start(warp_context(work_a, g, origin), work_b, g, origin)
                      for g in starts(options.coarse)), key=lambda m: -m[0])[:keep]
    gs = [g for _, g in matched]
    contexts = [warp_context(work_a, g, origin) for g in gs]
    scout = run(np.concatenate([central_patch(c) for c in contexts]),
                np.repeat(central_patch(work_b), len(gs), axis=0), contexts,
                dataclasses.replace(options, search="none", refine="none", verify="none",
                                    tta="none", retry_tta="none", coarse="none"))
    nccs = [image_ncc(work_a, work_b, g @ h, origin, options.thresholds.min_overlap)
            for g, h in zip(gs, scout.homography)]
    k = int(np.argmax(nccs))
    return gs[k], contexts[k], nccs[k]


def coarse_pass(run, work_a, work_b, first, options: EstimateOptions, origin):
    """The estimate of one pair with ``options.coarse``: ``first`` (the pipeline's ``Estimate``
    from the identity) where the pass is off or not needed (:func:`needs_pass`), where the best
    start (:func:`best_start`) is the identity, or where the pipeline's estimate from the best
    start aligns the work images no better (:func:`image_ncc`) than ``first``; else that estimate,
    its homography ``G @ H`` in the patch frame (``[2, 2] = 1``), its other fields those of the
    rest ``H`` (NCC in the warped work_a, search, refinement). Where the pass ran, the
    implausibility flag and ``max_corner_shift_px`` are :func:`flag`'s (the whole motion, up to
    ``thresholds.coarse_corner_shift``)."""
    if options.coarse == "none" or not needs_pass(first, options):
        return first
    g, context, _ = best_start(run, work_a, work_b, options, origin)
    if np.allclose(g, np.eye(3)):
        return flag(first, options)
    est = run(central_patch(context), central_patch(work_b), [context], options)
    total = geometry.scale_to_unit(g @ est.homography[0])
    t = options.thresholds
    if image_ncc(work_a, work_b, total, origin, t.min_overlap) <= image_ncc(
            work_a, work_b, first.homography[0], origin, t.min_overlap):
        return flag(first, options)
    return flag(pipeline.replacing(dataclasses.replace(est, homography=total[None]), first),
                options)


def flag(est, options: EstimateOptions, wide: bool = True):
    """``est`` (an ``Estimate``) with the implausibility rule of the coarse pass: a stage was
    skipped as degenerate, a patch corner moved beyond ``thresholds.coarse_corner_shift`` (not
    ``implausible_corner_shift``: the pass handles motions beyond the trained range; with
    ``wide=False`` the trained range's ``implausible_corner_shift``; none for an estimate made
    from the feature start, ``est.feature_start``), the alignment NCC is below
    ``thresholds.min_alignment_ncc`` or undefined, a patch is flat, or (``verify="ecc"``) ECC
    moved the estimate by more than ``thresholds.max_verify_move``, unless
    ``est.move_confirmed`` (:func:`stnh_tf.inference.checks.moved`)."""
    t = options.thresholds
    shift = checks.corner_shift(est.homography)
    moved = checks.moved(est.verify_move_px, est.move_confirmed, t)
    rule = dataclasses.replace(t, implausible_corner_shift=t.coarse_corner_shift) if wide else t
    featured = (np.zeros(len(shift), bool) if est.feature_start is None
                else np.asarray(est.feature_start, bool))
    # the feature start handles any motion: only the alignment's checks confirm it
    shift_rule = np.where(featured & np.isfinite(shift), 0.0, shift)
    implausible = (checks.beyond(est.rejected_stages, shift_rule, est.alignment_ncc,
                                 t.min_alignment_ncc, rule) | est.flat | moved)
    return dataclasses.replace(est, implausible=implausible, max_corner_shift_px=shift)
