"""The feature-based start of ``estimate_images`` (issue 64; a deviation from the paper:
``EstimateOptions(features="fallback")``, part of ``EstimateOptions.photographs()``,
``estimate_images``' default, or ``"always"``; off in ``EstimateOptions()``).

The network was trained on corners moved by up to 32 px in the 128 x 128 patch; the coarse pass
(:mod:`stnh_tf.inference.coarse`) reaches rotations up to 45 degrees and zooms 0.7-1.4. For wider
baselines (zoom 0.3-3, any rotation, strong viewpoint changes) the start comes from classical
matching: OpenCV SIFT keypoints of the two work images first and, where their start gives no
confirmed estimate, of the images at their own resolution (up to
:data:`~stnh_tf.inference.image_input.FEATURE_MAX_SIDE` px on the long side; :class:`StartImages`,
issue 79; :func:`candidate`), Lowe's ratio test and
``cv2.findHomography`` with ``cv2.USAC_MAGSAC`` (:func:`feature_start`, the SIFT baseline's
settings), its ``H_ba`` brought into the work frame (:func:`work_start`). image_a is
warped by that start ``G`` (:func:`stnh_tf.inference.coarse.warp_context`), the estimator's
pipeline (the network's stages, the search and refinement its options ask for) estimates the
rest ``H`` from it, and the better of ``G @ H`` and ``G`` by the whole work images' alignment
(:func:`stnh_tf.inference.coarse.image_ncc`) replaces the network's estimate where it aligns the
work images better (:func:`feature_pass`). With ``"fallback"`` the start is tried before the
search, which runs only where the start's estimate is not confirmed (:func:`estimate`). The
whole-image ECC of ``refine="images"`` follows as for any estimate.

The flag stays the alignment's: an estimate made from the feature start has
``Estimate.feature_start`` set and no corner rule (the motion may be anything), but is flagged
where its alignment NCC is below ``thresholds.min_alignment_ncc`` or ECC moves it by more than
``thresholds.max_verify_move`` (:func:`stnh_tf.inference.coarse.flag`).

Frames: ``G`` and ``H`` are pixel ``H_ba`` (``a_from_b``) in the patch frame
(:mod:`stnh_tf.geometry`), the patch's top-left corner at ``origin`` in the work images;
:func:`feature_start` returns the frame of the images it is given, :func:`work_start` the work
images'. NumPy and OpenCV only.
"""

from __future__ import annotations

import dataclasses
import functools

import cv2
import numpy as np

from stnh_tf import geometry, pixels
from stnh_tf.inference import checks, coarse, pipeline
from stnh_tf.inference import search as search_lib
from stnh_tf.inference.image_input import central_patch, work_from_feature
from stnh_tf.inference.options import EstimateOptions

SIFT = {"nOctaveLayers": 3, "contrastThreshold": 0.01, "edgeThreshold": 10.0, "sigma": 1.6}
"""``cv2.SIFT_create``'s arguments: those of the SIFT baseline
(:data:`stnh_tf.evaluation.baselines.SIFT_SETTINGS`, tuned on training photographs; the
inference layer does not import the evaluation layer)."""

RATIO = 0.8
"""Lowe's ratio test: a match is kept where its distance is below ``RATIO`` times the second's."""

MAGSAC = {"ransacReprojThreshold": 3.0, "maxIters": 2000, "confidence": 0.995}
"""``cv2.findHomography``'s arguments with ``cv2.USAC_MAGSAC``."""

MIN_INLIERS = 6
"""Fewer inliers: no start."""


@functools.lru_cache(maxsize=1)
def _sift():
    return cv2.SIFT_create(**SIFT)


def feature_start(work_a, work_b):
    """``H_ba`` ``[3, 3]`` (work_b pixel -> work_a pixel, ``[2, 2] = 1``) of SIFT matches of two
    gray work images (float in [0, 1] or uint8): keypoints and descriptors (:data:`SIFT`),
    brute-force L2 matches of work_b's to work_a's passing Lowe's ratio test (:data:`RATIO`),
    ``cv2.findHomography`` with ``cv2.USAC_MAGSAC`` (:data:`MAGSAC`); ``None`` where there are
    fewer than :data:`MIN_INLIERS` inliers, or the result is not finite or maps a corner of
    work_b behind camera a.

    >>> a = cv2.GaussianBlur(np.random.default_rng(0).random((240, 320)), (0, 0), 1.5)
    >>> a = (a - a.min()) / np.ptp(a)
    >>> h = geometry.translation(7.0, -5.0)
    >>> b = cv2.warpPerspective(a, h, (320, 240), flags=cv2.WARP_INVERSE_MAP)
    >>> bool(np.abs(feature_start(a, b) - h).max() < 0.05)
    True
    """
    to_u8 = lambda x: (np.asarray(x) if np.asarray(x).dtype == np.uint8  # noqa: E731
                       else pixels.to_uint8(np.asarray(x, np.float32)))
    (kp_a, desc_a), (kp_b, desc_b) = (_sift().detectAndCompute(to_u8(x), None)
                                      for x in (work_a, work_b))
    if desc_a is None or desc_b is None or len(desc_a) < 2 or len(desc_b) < 2:
        return None
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(desc_b, desc_a, k=2)  # query b, train a
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < RATIO * m[1].distance]
    if len(good) < MIN_INLIERS:
        return None
    pts_b = np.float32([kp_b[m.queryIdx].pt for m in good]).reshape(-1, 1, 2)
    pts_a = np.float32([kp_a[m.trainIdx].pt for m in good]).reshape(-1, 1, 2)
    try:
        h, mask = cv2.findHomography(pts_b, pts_a, cv2.USAC_MAGSAC, **MAGSAC)
    except cv2.error:
        return None
    if h is None or mask is None or int(mask.sum()) < MIN_INLIERS or not np.isfinite(h).all() \
            or abs(h[2, 2]) < 1e-12:
        return None
    h = geometry.scale_to_unit(h)
    return h if geometry.in_front(h, np.shape(work_b)[::-1]) else None


@dataclasses.dataclass(frozen=True)
class StartImages:
    """The images the feature start matches for one pair (:func:`start_images`) and the maps
    from their pixel frames to the work images'.

    Attributes:
      image_a, image_b: gray ``[h, w]`` images (uint8, or float in [0, 1]) of any size.
      work_from_a, work_from_b: ``[3, 3]`` float64: pixels of ``image_a`` (``image_b``) ->
        pixels of work_a (work_b)
        (:func:`stnh_tf.inference.image_input.work_from_feature`).
      found: :func:`work_start`'s result once made (``estimate_images`` may ask twice: the
        early and the late start; SIFT at the images' own size is the costly part).
    """

    image_a: np.ndarray
    image_b: np.ndarray
    work_from_a: np.ndarray
    work_from_b: np.ndarray
    found: dict = dataclasses.field(default_factory=dict, compare=False, repr=False)


def start_images(input_a, input_b):
    """The :class:`StartImages` of a pair of
    :class:`~stnh_tf.inference.image_input.InputImage` s made with ``feature_image=True``: each
    image's feature image, or its work image where it has none (it fits in the work size);
    ``None`` where neither has one: the feature start then runs on the work images, as
    :func:`candidate` does with ``start=None``."""
    if input_a.feature is None and input_b.feature is None:
        return None
    pick = lambda x: ((x.work, np.eye(3)) if x.feature is None  # noqa: E731
                      else (x.feature, work_from_feature(x.size)))
    (a, a_map), (b, b_map) = pick(input_a), pick(input_b)
    return StartImages(a, b, a_map, b_map)


def work_start(start: StartImages):
    """:func:`feature_start` of ``start``'s images in the work frame: ``H_ba`` ``[3, 3]`` (work_b
    pixel -> work_a pixel, ``[2, 2] = 1``) ``= work_from_a @ H @ inv(work_from_b)``, ``H`` the
    start in the frames of ``start``'s images; ``None`` where :func:`feature_start` finds none.
    Made once per ``start`` (kept in ``start.found``)."""
    if "h" not in start.found:
        h = feature_start(start.image_a, start.image_b)
        start.found["h"] = None if h is None else geometry.scale_to_unit(
            start.work_from_a @ h @ np.linalg.inv(start.work_from_b))
    return start.found["h"]


def wanted(first, options: EstimateOptions) -> bool:
    """Whether :func:`feature_pass` tries the feature start for ``first`` (the network's
    ``Estimate`` of one pair): ``features="always"``, or ``"fallback"`` where the coarse pass's
    trigger holds (:func:`stnh_tf.inference.coarse.needs_pass`: not flat and poorly aligned,
    beyond the trained range, or a stage skipped)."""
    if options.features == "none" or first.flat[0]:
        return False
    return options.features == "always" or coarse.needs_pass(first, options)


def candidate(run, work_a, work_b, options: EstimateOptions, origin, start=None):
    """The feature start's estimate of one pair (:func:`from_start`), or ``None`` where no start
    is found. The start is matched on work_a and work_b first; where it gives no estimate or one
    that is not :func:`confirmed`, and the pair has larger images (``start``, :func:`work_start`),
    the start matched on those gives a second estimate, and the one :func:`late_better` prefers
    is returned (the larger images cost more, and add only the detail a strong zoom needs)."""
    made = from_start(run, work_a, work_b, options, origin, feature_start(work_a, work_b))
    if start is None or (made is not None and confirmed(made, options)):
        return made
    native = from_start(run, work_a, work_b, options, origin, work_start(start))
    if native is None or made is None:
        return made if native is None else native
    return native if late_better(native, made, work_a, work_b, options, origin) else made


def from_start(run, work_a, work_b, options: EstimateOptions, origin, h_image):
    """The estimate of one pair from the start ``h_image`` (``[3, 3]`` ``H_ba`` in the work
    frame; ``None``: no start, and ``None`` is returned): ``G @ H``
    (``H``: ``run(patch_a, patch_b, contexts, options)``, the pipeline without
    the search on the central patches of work_a warped by ``G`` and of work_b) or ``G`` itself,
    whichever aligns the work images better (:func:`stnh_tf.inference.coarse.image_ncc`;
    ``G @ H`` on a tie): an ``Estimate`` (B = 1) with that homography in the patch frame
    (``[2, 2] = 1``),
    ``alignment_ncc`` measured in work_a, ``feature_start`` set, the other fields those of ``H``,
    flagged by :func:`stnh_tf.inference.coarse.flag` (no corner rule). Arguments as in
    :func:`feature_pass`."""
    if h_image is None:
        return None
    g = geometry.image_to_patch(h_image, *origin)
    context = coarse.warp_context(work_a, g, origin)
    # no search from the start (issue 64, its speed): it seldom finds one there, and the
    # whole-image refinement that follows reaches what it finds (BENCHMARKS.md)
    est = run(central_patch(context), central_patch(work_b), [context],
              dataclasses.replace(options, search="none"))
    t = options.thresholds
    score = lambda h: coarse.image_ncc(work_a, work_b, h, origin, t.min_overlap)  # noqa: E731
    refined = geometry.scale_to_unit(g @ est.homography[0])
    total = max((refined, g), key=score)  # the network's rest first on a tie
    patch_b = central_patch(work_b)[0, ..., 0]
    ncc = checks.alignment_ncc(work_a, patch_b, total, origin, t.min_overlap)
    move = est.verify_move_px
    if total is not refined:  # G itself: the check of verify="ecc" from it
        move = np.array([np.nan])
        if options.verify == "ecc":
            optimum = search_lib.ecc_refine(work_a, patch_b, total, origin, t)
            move[0] = checks.verify_move(optimum, total, np.shape(work_a), origin)
    featured = dataclasses.replace(est, homography=total[None], alignment_ncc=np.array([ncc]),
                                   feature_start=np.array([True]), verify_move_px=move)
    return coarse.flag(featured, options)


def confirmed(est, options: EstimateOptions) -> bool:
    """Whether ``est`` (an ``Estimate`` of one pair) is a feature start's estimate that needs no
    search: made from the feature start, not flagged, and aligned at least at
    ``thresholds.search_below_ncc`` (the search's trigger)."""
    return bool(est.feature_start is not None and est.feature_start[0]
                and not est.implausible[0]
                and est.alignment_ncc[0] >= options.thresholds.search_below_ncc)


def better(made, first, work_a, work_b, options: EstimateOptions, origin) -> bool:
    """Whether the feature start's estimate ``made`` (:func:`candidate`; ``None``: none) aligns
    the work images better than ``first`` (:func:`stnh_tf.inference.coarse.image_ncc`)."""
    if made is None:
        return False
    t = options.thresholds
    score = lambda h: coarse.image_ncc(work_a, work_b, h, origin, t.min_overlap)  # noqa: E731
    return score(made.homography[0]) > score(first.homography[0])


def late_wanted(est, options: EstimateOptions) -> bool:
    """Whether ``estimate_images`` tries the feature start again after the refinement and the
    checks (``features="fallback"``): ``est`` (the finished ``Estimate`` of one pair) was not
    made from the feature start, is not flat, and is flagged, or aligns the whole work images
    below ``thresholds.late_start_below_ncc`` (``Estimate.image_ncc``; undefined, NaN, is
    below; 0 switches that trigger off): the network's estimate passed the early trigger
    (:func:`wanted`) yet the finished one says it may be off (docs/estimate.md, "What each rule
    buys")."""
    if (options.features != "fallback" or est.flat[0]
            or (est.feature_start is not None and est.feature_start[0])):
        return False
    t = options.thresholds
    return bool(est.implausible[0]) or bool(
        t.late_start_below_ncc > 0 and est.image_ncc is not None
        and not est.image_ncc[0] >= t.late_start_below_ncc)


def late_better(late, est, work_a, work_b, options: EstimateOptions, origin) -> bool:
    """Whether ``late`` (the finished estimate from the feature start) replaces ``est`` (the
    finished one without it): the one that is not flagged where one of them is, else the one
    that aligns the work images better (:func:`better`; ``est`` on a tie)."""
    if bool(late.implausible[0]) != bool(est.implausible[0]):
        return not late.implausible[0]
    return better(late, est, work_a, work_b, options, origin)


NOT_MADE = object()
"""The ``made`` of :func:`feature_pass` when the feature start was not tried yet."""


def feature_pass(run, work_a, work_b, first, options: EstimateOptions, origin, made=NOT_MADE,
                 start=None):
    """The estimate of one pair with ``options.features``: ``first`` (the pipeline's
    ``Estimate`` from the identity) where the feature start is not :func:`wanted` or fails, or
    where its estimate (:func:`candidate`) does not align the work images better than ``first``
    (:func:`better`); else that estimate.

    Args:
      run: the estimator's pipeline on ``[1, S, S, 1]`` patches with their contexts.
      work_a, work_b: the ``[240, 320]`` float work images.
      first: an ``Estimate`` with B = 1 (patch frame).
      options: the options of ``run``.
      origin: ``(x0, y0)`` of the central patch in the work images.
      made: :func:`candidate`'s result for this pair if already made (not made again).
      start: the :class:`StartImages` of the pair (:func:`start_images`); ``None``: the feature
        start matches work_a and work_b.
    """
    if not wanted(first, options):
        return first
    if made is NOT_MADE:
        made = candidate(run, work_a, work_b, options, origin, start)
    if not better(made, first, work_a, work_b, options, origin):
        return first
    return pipeline.replacing(made, first)  # the search may have looked at it in first


def estimate(run, work_a, work_b, options: EstimateOptions, origin, start=None):
    """The estimate of one pair from its central patches with ``options.features``:
    ``run(patch_a, patch_b, [work_a], options)``, then :func:`feature_pass`. With
    ``"fallback"`` (and a search, no retry) the feature start comes before the search: the
    pipeline runs first without the search; where the feature start is :func:`wanted`, its
    estimate (:func:`candidate`) is kept if :func:`confirmed` and :func:`better` than that;
    otherwise the pipeline runs again with the search and :func:`feature_pass` follows as
    without the early start (the same result, one network pass later). Its
    ``network_homography`` is always the network's own estimate from the identity start.
    Arguments as in :func:`feature_pass`."""
    patches = (central_patch(work_a), central_patch(work_b), [work_a])
    early = options.features == "fallback" and options.search != "none" and not options.retries
    first = run(*patches, dataclasses.replace(options, search="none") if early else options)
    made = NOT_MADE
    if early and wanted(first, options):
        made = candidate(run, work_a, work_b, options, origin, start)
        if made is not None and confirmed(made, options) and better(made, first, work_a, work_b,
                                                                    options, origin):
            return dataclasses.replace(made, network_homography=first.network_homography)
        first = run(*patches, options)  # the search, as without the early start
    result = feature_pass(run, work_a, work_b, first, options, origin, made, start)
    return dataclasses.replace(result, network_homography=first.network_homography)
