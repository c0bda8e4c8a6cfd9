"""The feature-based start of ``estimate_images`` (``EstimateOptions(features=...)``, issue 64,
:mod:`stnh_tf.inference.features`), with a stage model that outputs the identity whatever its
input (a network that cannot estimate anything): what the estimator finds beyond the identity is
then the feature start, refined by ECC. References: the homography the pair was made with
(``cv2.warpPerspective``) and corner errors from ``cv2.perspectiveTransform``."""

import dataclasses

import cv2
import numpy as np
import pytest
import skimage.data

from conftest import constant_stage
from stnh_tf import geometry
from stnh_tf.inference import coarse, features, image_input
from stnh_tf.inference.estimator import HomographyEstimator
from stnh_tf.inference.options import EstimateOptions

W, H = image_input.WORK_SIZE


@pytest.fixture(scope="module")
def estimator():
    return HomographyEstimator([constant_stage(np.eye(3), "identity")])


def _wide_motion(angle_deg, scale, tilt=0.0):
    """Image-frame a_from_b: rotation by angle_deg and scaling by ``scale`` about the image
    centre (b sees a zoomed by 1 / scale), with a perspective term ``tilt``."""
    c = geometry.translation((W - 1) / 2, (H - 1) / 2)
    m = np.vstack([cv2.getRotationMatrix2D((0.0, 0.0), angle_deg, scale), [0.0, 0.0, 1.0]])
    m[2, 0] = tilt
    return c @ m @ np.linalg.inv(c)


def _pair(h_ba):
    """(image_a, image_b) 320 x 240 gray uint8 from astronaut(): b(q) = a(h_ba q) (OpenCV warp of
    the 512 x 512 photograph, so b sees a's surroundings)."""
    big = cv2.cvtColor(skimage.data.astronaut(), cv2.COLOR_RGB2GRAY)
    o = geometry.translation((512 - W) / 2, (512 - H) / 2)
    flags = cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR
    return (cv2.warpPerspective(big, o, (W, H), flags=flags),
            cv2.warpPerspective(big, o @ h_ba, (W, H), flags=flags))


def _corner_error(h, h_true):
    """Mean distance (px) at the 320 x 240 image's corners (cv2.perspectiveTransform)."""
    corners = np.array([[[0, 0], [W, 0], [W, H], [0, H]]], np.float64)
    return float(np.linalg.norm(cv2.perspectiveTransform(corners, h)[0]
                                - cv2.perspectiveTransform(corners, h_true)[0], axis=1).mean())


# photographs() without the feature start
WHOLE = EstimateOptions(refine="images", verify="ecc")


@pytest.mark.parametrize("motion", [(-100.0, 2.2), (60.0, 0.45), (-170.0, 1.6, 4e-4)])
def test_feature_start_recovers_wide_motions_and_the_flag_stays_honest(estimator, motion):
    """Rotations of 60-170 degrees with zooms 0.45-2.2: without the feature start the estimate is
    far off and flagged; with features="fallback" (and "always") it is within 0.5 px of the true
    homography at the image corners, made from the feature start, not flagged, and its
    network_move_px is its distance from the network's own estimate (the identity here)."""
    h_true = _wide_motion(*motion)
    a, b = _pair(h_true)
    plain = estimator.estimate_images_with_info(a, b, WHOLE)
    assert _corner_error(plain.homography[0], h_true) > 50 and plain.implausible[0]
    assert not plain.feature_start[0]
    for mode in ("fallback", "always"):
        est = estimator.estimate_images_with_info(a, b, dataclasses.replace(WHOLE,
                                                                            features=mode))
        assert _corner_error(est.homography[0], h_true) < 0.5, mode
        assert est.feature_start[0] and not est.implausible[0], mode
        assert est.network_move_px[0] == pytest.approx(
            _corner_error(est.homography[0], est.network_homography[0]), rel=1e-6)
        np.testing.assert_allclose(est.network_homography[0], np.eye(3), atol=1e-12)  # its own


def test_feature_start_that_cannot_be_confirmed_is_flagged(estimator):
    """Unrelated photographs: whatever the feature start gives is not kept as a plausible
    estimate (flagged, or the network's own kept); a flat image_b gets no feature start."""
    a = _pair(np.eye(3))[0]
    other = cv2.resize(skimage.data.camera(), (W, H), interpolation=cv2.INTER_AREA)
    est = estimator.estimate_images_with_info(a, other,
                                              dataclasses.replace(WHOLE, features="always"))
    assert est.implausible[0]
    flat = np.full((H, W), 128, np.uint8)
    est = estimator.estimate_images_with_info(a, flat, EstimateOptions(features="always"))
    assert est.flat[0] and est.implausible[0] and not est.feature_start[0]


def test_feature_start_alone_matches_opencv_warp():
    """features.feature_start on an OpenCV-warped pair (rotation 120 degrees, zoom 1.8) returns
    the homography it was warped with, to 1 px at the image corners; on a flat image, None."""
    h_true = _wide_motion(120.0, 1.8)
    a, b = _pair(h_true)
    assert _corner_error(features.feature_start(a, b), h_true) < 1.0
    assert features.feature_start(a, np.full_like(b, 90)) is None


def test_the_papers_path_has_no_feature_start():
    """network_only() and EstimateOptions() leave it off; an unknown mode is a clear error."""
    assert EstimateOptions.network_only().features == "none"
    assert EstimateOptions().features == "none"
    with pytest.raises(ValueError, match="features must be one of"):
        EstimateOptions(features="orb")


def test_the_feature_start_uses_the_tuned_sift_baselines_settings():
    """features.SIFT / RATIO are a copy of the tuned baseline's (the inference layer may not
    import the evaluation layer): the two stay the same numbers."""
    from stnh_tf.evaluation import baselines

    tuned = baselines.SIFT_SETTINGS
    assert features.SIFT == {k: tuned[k] for k in features.SIFT}
    assert features.RATIO == tuned["ratio"]


def _pipeline(estimator, calls):
    """``run(patch_a, patch_b, contexts, options)`` of ``estimate_images`` (the estimator's
    pipeline at the central patch's origin), recording each call's ``options.search`` and whether
    it started from the identity (its context is work_a itself)."""
    def run(a, b, contexts, options):
        calls.append(options.search)
        return estimator._run(a, b, contexts, image_input.PATCH_ORIGIN, options, 64)
    return run


def _work(image):
    return image_input.work_image(image, "image", "rgb")[0]


def test_fallback_tries_the_feature_start_before_the_search(estimator):
    """With features="fallback" the pipeline from the identity runs without the search; a
    confirmed feature start is kept and the search never runs (two pipeline calls: the network
    alone, then from the start, also without the search since issue 64's speed change). Where
    the start is not confirmed (unrelated photographs), the result is the same, bit for bit, as
    the feature pass after the pipeline with the search, which then runs from the identity."""
    options = dataclasses.replace(WHOLE, features="fallback", refine="none", verify="none")
    a, b = (_work(x) for x in _pair(_wide_motion(-100.0, 2.2)))
    calls = []
    est = features.estimate(_pipeline(estimator, calls), a, b, options, image_input.PATCH_ORIGIN)
    assert est.feature_start[0] and not est.implausible[0] and calls == ["none", "none"]

    other = _work(cv2.resize(skimage.data.camera(), (W, H), interpolation=cv2.INTER_AREA))
    other[:100, :110] = a[20:120, 30:140]  # a corner of work_a, shifted: matches there only
    calls = []
    est = features.estimate(_pipeline(estimator, calls), a, other, options,
                            image_input.PATCH_ORIGIN)
    assert calls == ["none", "none", "ecc"]  # the network alone, from the start, the search
    assert not features.confirmed(features.candidate(_pipeline(estimator, []), a, other, options,
                                                     image_input.PATCH_ORIGIN), options)
    run = _pipeline(estimator, [])
    first = run(image_input.central_patch(a), image_input.central_patch(other), [a], options)
    ref = features.feature_pass(run, a, other, first, options, image_input.PATCH_ORIGIN)
    for field in ("homography", "implausible", "alignment_ncc", "feature_start", "searched",
                  "network_homography"):
        np.testing.assert_array_equal(getattr(est, field), getattr(ref, field), err_msg=field)


def test_the_flag_reads_how_precisely_the_images_fix_the_estimate(estimator):
    """With verify="ecc", estimate_images reports checks.corner_std of its final estimate (in
    the 320 x 240 images' frame here, which is the work frame; over 8 x 8 squares by default,
    the classical one with ``corner_std_tile=0``), flags the estimate where it is
    above Thresholds.max_corner_std (the same homography), returns the identity (flagged,
    undetermined) above Thresholds.undetermined_corner_std, and reports NaN without the check."""
    from stnh_tf.inference import checks

    a, b = _pair(_wide_motion(-100.0, 2.2))
    options = dataclasses.replace(WHOLE, features="fallback")
    est = estimator.estimate_images_with_info(a, b, options)
    std = est.corner_std_px[0]
    assert 0 < std < options.thresholds.max_corner_std and not est.implausible[0]
    assert options.thresholds.corner_std_tile == 8  # the cluster-robust covariance (issue 64)
    assert std == pytest.approx(checks.corner_std(_work(a), _work(b), est.homography[0],
                                                  tile=8), rel=1e-9)
    classical = dataclasses.replace(options, thresholds=dataclasses.replace(
        options.thresholds, corner_std_tile=0))
    assert estimator.estimate_images_with_info(a, b, classical).corner_std_px[0] == \
        pytest.approx(checks.corner_std(_work(a), _work(b), est.homography[0]), rel=1e-9)
    strict = dataclasses.replace(options, thresholds=dataclasses.replace(
        options.thresholds, max_corner_std=std / 2))
    flagged = estimator.estimate_images_with_info(a, b, strict)
    assert flagged.implausible[0]
    np.testing.assert_array_equal(flagged.homography, est.homography)
    assert not est.undetermined[0] and not flagged.undetermined[0]
    # Where the images leave the estimate undetermined (here: a threshold under its std), the
    # identity takes its place, flagged, as SIFT + RANSAC returns the identity without a model.
    lost = estimator.estimate_images_with_info(a, b, dataclasses.replace(
        options, thresholds=dataclasses.replace(options.thresholds,
                                                undetermined_corner_std=std / 2)))
    assert lost.undetermined[0] and lost.implausible[0] and lost.corner_std_px[0] == std
    np.testing.assert_array_equal(lost.homography[0], np.eye(3))  # 320 x 240: the work frame
    np.testing.assert_array_equal(lost.network_homography, est.network_homography)
    unchecked = estimator.estimate_images_with_info(a, b, dataclasses.replace(options,
                                                                              verify="none"))
    assert np.isnan(unchecked.corner_std_px[0]) and not unchecked.undetermined[0]


def test_no_feature_start_keeps_the_corner_rule_of_motions_beyond_the_trained_range(monkeypatch):
    """A network estimate that moves a patch corner beyond the trained range's rule (48 px) yet
    aligns the pair: with a feature start (``wide_motions``) and none found, it is judged by the
    coarse pass's corner rule (``coarse_corner_shift``, 128 px) as after a coarse pass that finds
    nothing, so not flagged; without the feature start the trained range's rule flags it. The
    stage outputs the true homography (rotation by 40 degrees: the patch corners move 62 px)."""
    h_true = _wide_motion(40.0, 1.0)
    a, b = _pair(h_true)
    origin = image_input.PATCH_ORIGIN
    truth = HomographyEstimator([constant_stage(geometry.image_to_patch(h_true, *origin),
                                                "truth")])
    monkeypatch.setattr(features, "feature_start", lambda *images: None)  # no start found
    t = EstimateOptions().thresholds
    wide = truth.estimate_images_with_info(a, b, EstimateOptions(search="none",
                                                                 features="fallback"))
    plain = truth.estimate_images_with_info(a, b, EstimateOptions(search="none"))
    np.testing.assert_array_equal(wide.homography, plain.homography)
    assert _corner_error(wide.homography[0], h_true) < 0.5
    assert t.implausible_corner_shift < wide.max_corner_shift_px[0] < t.coarse_corner_shift
    assert wide.alignment_ncc[0] > 0.9 and not wide.feature_start[0]
    assert not wide.implausible[0] and plain.implausible[0]
    assert EstimateOptions(features="fallback").wide_motions
    assert EstimateOptions(coarse="rotations").wide_motions
    assert not EstimateOptions().wide_motions


def test_late_feature_start_rescues_what_the_early_trigger_let_through(estimator, monkeypatch):
    """The early trigger (:func:`features.wanted`) judges the network's estimate before the
    refinement; where it lets an estimate through that the finished result then flags (or moves
    far), ``estimate_images`` tries the feature start after all (:func:`features.late_wanted`).
    With the early trigger switched off, a wide motion is still recovered to under 0.5 px of the
    homography the pair was made with (cv2.perspectiveTransform), unflagged and from the start;
    without the late trigger too, the finished estimate is far off and flagged."""
    h_true = _wide_motion(-100.0, 2.2)
    a, b = _pair(h_true)
    monkeypatch.setattr(features, "wanted", lambda first, options: False)
    made = []
    candidate = features.candidate
    monkeypatch.setattr(features, "candidate",
                        lambda *args: made.append(1) or candidate(*args))
    late = estimator.estimate_images_with_info(a, b, EstimateOptions.photographs())
    assert made == [1]
    assert _corner_error(late.homography[0], h_true) < 0.5
    assert late.feature_start[0] and not late.implausible[0]
    monkeypatch.setattr(features, "late_wanted", lambda *args: False)
    early_only = estimator.estimate_images_with_info(a, b, EstimateOptions.photographs())
    assert _corner_error(early_only.homography[0], h_true) > 50 and early_only.implausible[0]
    assert not early_only.feature_start[0]


def test_searched_says_the_search_looked_even_where_the_feature_start_won(estimator,
                                                                          monkeypatch):
    """``Estimate.searched``: where the feature start is not confirmed early, the search runs
    from the identity (and looks at this pair: the network's identity aligns it poorly); the
    feature start's estimate then replaces that one as the better alignment. The estimate
    returned is the start's (``found`` False: not the search's result; within 3 px of the motion
    the pair was made with, cv2.perspectiveTransform, unrefined here; the identity is hundreds of
    px off), and ``searched`` still says the
    search looked at the pair (it said False before). The same from the late feature start."""
    h_true = _wide_motion(-100.0, 2.2)
    a, b = _pair(h_true)
    monkeypatch.setattr(features, "confirmed", lambda made, options: False)
    calls = []
    options = dataclasses.replace(WHOLE, features="fallback", refine="none", verify="none")
    wa, wb = _work(a), _work(b)
    est = features.estimate(_pipeline(estimator, calls), wa, wb, options,
                            image_input.PATCH_ORIGIN)
    assert calls[-1] == "ecc" and est.feature_start[0]
    assert est.searched[0] and not est.found[0]
    h = geometry.patch_to_image(est.homography[0], *image_input.PATCH_ORIGIN)
    assert _corner_error(h, h_true) < 3.0

    # the late start: its finished estimate replaces a flagged one the search looked at
    estimate = features.estimate
    monkeypatch.setattr(features, "estimate", lambda *args: dataclasses.replace(
        estimate(*args), searched=np.array([True]), feature_start=np.array([False])))
    monkeypatch.setattr(features, "late_wanted", lambda *args: True)
    monkeypatch.setattr(features, "late_better", lambda *args: True)
    late = estimator.estimate_images_with_info(a, b, EstimateOptions.photographs())
    assert late.searched[0] and late.feature_start[0] and not late.found[0]
    assert _corner_error(late.homography[0], h_true) < 0.5


def test_late_trigger_and_choice(estimator):
    """:func:`features.late_wanted`: only with ``features="fallback"``, never for an estimate
    made from the feature start or a flat pair; where the finished estimate is flagged (not
    where it merely lies far from the network's: that trigger went in issue 79), or unflagged
    but aligning the whole work images below ``Thresholds.late_start_below_ncc``
    (coarse.image_ncc: the identity of a rotated pair; issue 79, facades one period off).
    :func:`features.late_better`: an unflagged estimate beats a flagged one; otherwise the
    better whole-image NCC (the estimate on a tie)."""
    h_true = _wide_motion(5.0, 1.05)
    a, b = _pair(h_true)
    wa, wb, origin = _work(a), _work(b), image_input.PATCH_ORIGIN
    est = estimator.estimate_images_with_info(a, b, EstimateOptions.photographs())
    assert _corner_error(est.homography[0], h_true) < 0.5 and not est.implausible[0]
    est = dataclasses.replace(est, feature_start=np.array([False]),  # as if the network's
                              homography=geometry.image_to_patch(est.homography[0], *origin)[None])
    fallback = EstimateOptions.photographs()
    flagged = dataclasses.replace(est, implausible=np.array([True]))
    wanted = features.late_wanted
    assert not wanted(est, fallback)
    assert wanted(flagged, fallback)
    for options in (EstimateOptions(), dataclasses.replace(fallback, features="always")):
        assert not wanted(flagged, options)
    assert not wanted(dataclasses.replace(flagged, feature_start=np.array([True])), fallback)
    assert not wanted(dataclasses.replace(flagged, flat=np.array([True])), fallback)
    # the estimate's image_ncc is the whole work images' NCC under it
    aligned = coarse.image_ncc(wa, wb, est.homography[0], origin,
                               fallback.thresholds.min_overlap)
    # (atol: the frames' round trip; 0 on both OpenCV paths here)
    np.testing.assert_allclose(est.image_ncc[0], aligned, atol=1e-6)
    # unflagged but off: the identity aligns the rotated pair's work images poorly
    ncc = coarse.image_ncc(wa, wb, np.eye(3), origin, fallback.thresholds.min_overlap)
    off = dataclasses.replace(est, homography=np.eye(3)[None], image_ncc=np.array([ncc]))
    assert ncc < fallback.thresholds.late_start_below_ncc <= aligned
    assert wanted(off, fallback)
    assert wanted(dataclasses.replace(off, image_ncc=np.array([np.nan])), fallback)  # undefined
    assert not wanted(off, dataclasses.replace(fallback, thresholds=dataclasses.replace(
        fallback.thresholds, late_start_below_ncc=0.0)))
    assert not wanted(dataclasses.replace(off, feature_start=np.array([True])), fallback)
    right = dataclasses.replace(est, homography=geometry.image_to_patch(h_true, *origin)[None])
    wrong = dataclasses.replace(right, homography=np.eye(3)[None])
    assert features.late_better(right, wrong, wa, wb, fallback, origin)
    assert not features.late_better(wrong, right, wa, wb, fallback, origin)
    assert not features.late_better(right, right, wa, wb, fallback, origin)
    assert features.late_better(wrong, dataclasses.replace(right, implausible=np.array([True])),
                                wa, wb, fallback, origin)
