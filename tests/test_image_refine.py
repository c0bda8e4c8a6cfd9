"""The whole-image refinement of ``estimate_images`` (``EstimateOptions(refine="images")``, issue
46, :mod:`stnh_tf.inference.image_refine`), with stage models that output a fixed homography
whatever their input: the network's estimate is then known, and the truth is the warp that made
image_b (OpenCV), so the refinement's error is measured against an independent reference."""

import dataclasses

import cv2
import numpy as np
import pytest
import skimage.data

from conftest import constant_stage, opencv_optimized
from stnh_tf import geometry, pixels
from stnh_tf.evaluation.camera_pairs import image_errors
from stnh_tf.inference import checks, image_input, image_refine, search
from stnh_tf.inference.estimator import HomographyEstimator
from stnh_tf.inference.options import EstimateOptions, Thresholds

W, H = image_input.WORK_SIZE
ORIGIN = image_input.PATCH_ORIGIN


def _pair(h_ba):
    """(image_a, image_b) 320 x 240 gray uint8 cut from a 512 x 512 photograph so that
    b(q) = a(h_ba q) with no empty border."""
    big = cv2.cvtColor(skimage.data.astronaut(), cv2.COLOR_RGB2GRAY)
    o = geometry.translation((512 - W) / 2, (512 - H) / 2)
    flags = cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR
    return (cv2.warpPerspective(big, o, (W, H), flags=flags),
            cv2.warpPerspective(big, o @ h_ba, (W, H), flags=flags))


# An image-frame motion within the trained range: the patch corners move 10-20 px.
TRUTH = np.array([[1.04, 0.03, -9.0], [-0.02, 0.98, 6.0], [2e-5, -1e-5, 1.0]])


def _estimator_off_by(shift):
    """An estimator whose one stage outputs the truth's patch-frame H_bar moved by ``shift`` px
    (a translation of the image_b frame): the network's estimate, off by ``shift`` everywhere."""
    h_patch = geometry.image_to_patch(TRUTH @ geometry.translation(*shift), *ORIGIN)
    return HomographyEstimator([constant_stage(h_patch, "off")])


@pytest.mark.parametrize("shift", [(3.0, -2.0), (-6.0, 5.0), (20.0, 15.0)])
def test_images_refinement_reaches_the_truth(shift):
    a, b = _pair(TRUTH)
    estimator = _estimator_off_by(shift)
    plain = estimator.estimate_images_with_info(a, b, EstimateOptions(search="none"))
    refined = estimator.estimate_images_with_info(a, b, EstimateOptions(search="none",
                                                                        refine="images"))
    before = image_errors(plain.homography, TRUTH[None])[0]
    after = image_errors(refined.homography, TRUTH[None])[0]
    assert before == pytest.approx(np.hypot(*shift), rel=0.05)  # the stage's own error
    assert after < 0.1  # measured 0.003-0.004 px
    assert refined.refined[0] and not refined.implausible[0]
    assert refined.alignment_ncc[0] > plain.alignment_ncc[0]


def test_images_refinement_beats_the_patch_refinement_on_a_degraded_pair():
    """With image_b blurred and noisy, ``refine="ecc"`` (patch_b alone) leaves the image corners
    0.44 px off and ``"images"`` (the whole images) 0.09-0.10 px (measured for both shifts)."""
    a, b = _pair(TRUTH)
    rng = np.random.default_rng(0)
    b = np.clip(cv2.GaussianBlur(b.astype(np.float32), (0, 0), 1.5)
                + rng.normal(0, 12, b.shape), 0, 255).astype(np.uint8)
    for shift in ((3.0, -2.0), (-6.0, 5.0)):
        estimator = _estimator_off_by(shift)
        errors = {refine: image_errors(estimator.estimate_images_with_info(
            a, b, EstimateOptions(search="none", refine=refine)).homography, TRUTH[None])[0]
            for refine in ("ecc", "images")}
        assert errors["images"] < 0.2 and errors["ecc"] > 2 * errors["images"]


def test_refine_images_keeps_the_estimate_where_it_does_not_apply():
    a, b = _pair(TRUTH)
    work_a, _ = image_input.work_image(a)
    work_b, _ = image_input.work_image(b)
    est = _estimator_off_by((3.0, -2.0)).estimate_images_with_info(
        a, b, EstimateOptions(search="none"))
    for options in (EstimateOptions(search="none"), EstimateOptions(refine="ecc")):
        assert image_refine.refine_images(est, work_a, work_b, options, ORIGIN) is est
    flat = np.full((H, W), 0.5, np.float32)  # nothing to align: ECC fails, the estimate stays
    options = EstimateOptions(refine="images")
    assert image_refine.refine_images(est, flat, flat, options, ORIGIN) is est
    # a start that ECC cannot improve on: the truth itself
    exact = dataclasses.replace(est, homography=geometry.image_to_patch(TRUTH, *ORIGIN)[None])
    kept = image_refine.refine_images(exact, work_a, work_b, options, ORIGIN)
    assert image_errors(geometry.patch_to_image(kept.homography[0], *ORIGIN)[None],
                        TRUTH[None])[0] < 0.1



@pytest.mark.parametrize("shift", [(25.0, 20.0), (-30.0, 20.0), (35.0, -25.0)])
def test_an_estimate_beyond_the_refinements_reach_stays_flagged(shift):
    """An estimate off by 32-43 px: the whole-image ECC stops short of the truth (10-44 px off,
    measured) and the estimate stays flagged. (Later rounds from patch_b's ECC optimum reached
    the truth on the first two; they changed no estimate of the ablation's 480 camera pairs and
    went in issue 79.)"""
    a, b = _pair(TRUTH)
    est = _estimator_off_by(shift).estimate_images_with_info(
        a, b, EstimateOptions(search="none", refine="images", verify="ecc"))
    assert image_errors(est.homography, TRUTH[None])[0] > 5.0 and est.implausible[0]


def test_estimate_images_defaults_to_photographs_and_estimate_to_the_plain_default():
    a, b = _pair(TRUTH)
    stage = constant_stage(geometry.image_to_patch(TRUTH @ geometry.translation(3.0, -2.0),
                                                   *ORIGIN), "off")
    estimator = HomographyEstimator([stage])
    assert estimator.options == EstimateOptions()
    assert estimator.image_options == EstimateOptions.photographs()
    default = estimator.estimate_images_with_info(a, b)
    explicit = estimator.estimate_images_with_info(a, b, EstimateOptions.photographs())
    assert (default.options.coarse, default.options.refine, default.options.verify,
            default.options.features) == ("none", "images", "ecc", "fallback")
    np.testing.assert_array_equal(default.homography, explicit.homography)
    assert image_errors(default.homography, TRUTH[None])[0] < 0.1  # refined (measured 0.003)
    # options given at construction apply to both methods
    network = EstimateOptions(search="none")
    plain = HomographyEstimator([stage], options=network)
    assert plain.options == plain.image_options == network
    np.testing.assert_array_equal(plain.estimate_images_with_info(a, b).homography,
                                  estimator.estimate_images_with_info(a, b, network).homography)
    assert image_errors(plain.estimate_images(a, b)[None], TRUTH[None])[0] > 3.0  # the stage's


# -- one resolution for the whole-image ECC (Thresholds.resolution_sigma) ------------------------

def _zoom_pair(scale, seed, psf=0.8, roll=0.3):
    """(image_a, image_b, h_ba): float32 320 x 240 views of one random scene by two cameras with
    the same blur (``psf`` px in each camera's own pixels), camera b zoomed out by ``scale`` and
    rolled by ``roll`` rad about the centre: image_b's pixel spans ``scale`` of image_a's, so the
    scene is blurred by ``psf * scale`` (scene px) before image_b samples it."""
    rng = np.random.default_rng(seed)
    size = (int(W * scale) + 200, int(H * scale) + 200)
    scene = cv2.GaussianBlur(rng.random(size[::-1]).astype(np.float32), (0, 0), 1.0)
    scene = (scene - scene.min()) / np.ptp(scene)
    a_in_scene = geometry.translation((size[0] - W) / 2, (size[1] - H) / 2)
    centre = geometry.translation((W - 1) / 2, (H - 1) / 2)
    c, s = np.cos(roll), np.sin(roll)
    h_ba = centre @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.diag(
        [scale, scale, 1]) @ np.linalg.inv(centre)
    flags = cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR
    a = cv2.warpPerspective(cv2.GaussianBlur(scene, (0, 0), psf), a_in_scene, (W, H), flags=flags)
    b = cv2.warpPerspective(cv2.GaussianBlur(scene, (0, 0), psf * scale), a_in_scene @ h_ba,
                            (W, H), flags=flags)
    return a, b, h_ba


def test_centre_scale_is_the_jacobian_of_the_map():
    """Against central differences of ``cv2.perspectiveTransform`` at image_b's centre."""
    h = np.array([[1.7, 0.2, 12.0], [-0.15, 1.9, -7.0], [4e-4, -3e-4, 1.0]])
    centre = np.array([(W - 1) / 2, (H - 1) / 2])
    step = 1e-3
    columns = [(cv2.perspectiveTransform((centre + d)[None, None], h)[0, 0]
                - cv2.perspectiveTransform((centre - d)[None, None], h)[0, 0]) / (2 * step)
               for d in (np.array([step, 0.0]), np.array([0.0, step]))]
    expected = np.sqrt(abs(np.linalg.det(np.stack(columns, axis=1))))
    assert geometry.centre_scale(h, (W, H)) == pytest.approx(expected, rel=1e-6)
    assert np.isnan(geometry.centre_scale(np.full((3, 3), np.nan), (W, H)))


def test_resolution_blurs_blur_the_sharper_image_by_the_camera_blur_at_the_other_zoom():
    zoom_out = np.diag([2.0, 2.0, 1.0])  # image_b's pixel spans 2 of image_a's
    assert image_refine.resolution_blurs(zoom_out, (W, H), 0.8) == pytest.approx(
        (0.8 * np.sqrt(3.0), 0.0))
    assert image_refine.resolution_blurs(np.linalg.inv(zoom_out), (W, H), 0.8) == pytest.approx(
        (0.0, 0.8 * np.sqrt(3.0)))
    assert image_refine.resolution_blurs(np.eye(3), (W, H), 0.8) == (0.0, 0.0)
    assert image_refine.resolution_blurs(zoom_out, (W, H), 0.0) == (0.0, 0.0)
    assert image_refine.resolution_blurs(np.full((3, 3), np.inf), (W, H), 0.8) == (0.0, 0.0)
    a = np.random.default_rng(0).random((H, W)).astype(np.float32)
    for h in (np.eye(3), np.diag([1.12, 1.12, 1.0])):  # a blur of 0 and of 0.40 px: left out
        same_a, same_b = image_refine.equal_resolution(a, a, h, 0.8)
        assert same_a is a and same_b is a
    blurred, same = image_refine.equal_resolution(a, a, np.diag([1.13, 1.13, 1.0]), 0.8)
    assert same is a and blurred.std() < a.std()  # 0.42 px: image_a blurred


def test_the_verify_move_is_measured_in_the_coarser_image_beyond_the_trained_zoom():
    """``checks.verify_move`` against ``cv2.perspectiveTransform`` of the work image's corners
    (patch frame, origin ORIGIN): on a 3x zoom out (beyond the trained range's 1.5) the move in
    image_b's pixels, about a third of image_a's; on a 1.3x zoom out and on a 3x zoom in the
    move in image_a's; ``inf`` without an optimum."""
    assert checks.TRAINED_ZOOM == 1.5
    corners = np.array([[[0, 0], [W, 0], [W, H], [0, H]]], np.float64)
    t = geometry.translation(*ORIGIN)
    warp = lambda p, h: cv2.perspectiveTransform(p, t @ h @ np.linalg.inv(t))  # noqa: E731
    tilt = np.array([[1.0, 0.05, 0.0], [-0.03, 1.0, 0.0], [2e-4, -1e-4, 1.0]])
    for zoom, in_image_b in ((3.0, True), (1.3, False), (1 / 3, False)):
        h = np.diag([zoom, zoom, 1.0]) @ tilt
        optimum = h @ geometry.translation(0.8, -0.5) @ np.diag([1.01, 0.99, 1.0])
        in_a = np.linalg.norm(warp(corners, optimum) - warp(corners, h), axis=-1).mean()
        in_b = np.linalg.norm(warp(warp(corners, optimum), np.linalg.inv(h)) - corners,
                              axis=-1).mean()
        move = checks.verify_move(optimum, h, (H, W), ORIGIN)
        assert move == pytest.approx(in_b if in_image_b else in_a, rel=1e-9)
        assert in_b / in_a == pytest.approx(1 / zoom, rel=0.1)
    assert checks.verify_move(None, h, (H, W), ORIGIN) == np.inf


def test_verify_move_is_measured_at_the_patch_corners_where_a_frame_corner_is_beyond_the_horizon():
    """Where the estimate maps a corner of image_b's frame beyond image_a's horizon (the paper's
    protocol on whole images, strongly projective), the move is measured where the corner
    precision is (checks.precision_corners: the patch's corners): near the horizon two
    estimates 1e-6 apart in H's last row lie far apart (issue 79: a good estimate of the paper's
    protocol, 0.02 px off, flagged by a 153-px move)."""
    t = geometry.translation(*ORIGIN)
    # the horizon at u = 310, just inside the frame (as the 153-px move's pair had it); the zoom
    # keeps the scale at the centre at 1
    tilted = np.array([[1.0, 0, 0], [0, 1.0, 0], [-1 / 310, 0, 1.0]])
    zoom = 1 / geometry.centre_scale(tilted, (W, H))
    tilted = np.diag([zoom, zoom, 1.0]) @ tilted
    optimum_image = tilted.copy()
    optimum_image[2, 0] += 1e-6
    h, optimum = (np.linalg.inv(t) @ m @ t for m in (tilted, optimum_image))  # patch frame
    square = np.array([[[96, 56], [224, 56], [224, 184], [96, 184]]], np.float64)
    assert [tuple(c) for c in square[0]] == checks.precision_corners(tilted, (H, W), ORIGIN)
    expected = np.linalg.norm(cv2.perspectiveTransform(square, optimum_image)
                              - cv2.perspectiveTransform(square, tilted), axis=-1).mean()
    move = checks.verify_move(optimum, h, (H, W), ORIGIN)
    assert move == pytest.approx(expected, rel=1e-9)
    assert move < 0.1 * Thresholds().max_verify_move
    assert checks.frame_corner_distance(optimum, h, (H, W), ORIGIN) > 10 * move


@pytest.mark.parametrize("optimized", [pytest.param(True, id="opencv_optimized"),
                                       pytest.param(False, id="opencv_unoptimized",
                                                    marks=pytest.mark.slow)])
def test_one_resolution_brings_ecc_closer_on_a_zoom_between_two_cameras(optimized):
    """Two cameras with one blur, image_b zoomed out 3x, ECC (the refinement's settings) started
    2 px off in image_b's frame: over 4 scenes, image_a blurred to image_b's resolution ends
    0.61 px off on average at the image corners against 0.99 px without it (measured, the same
    on both OpenCV paths to 1e-3 px; every scene closer with it)."""
    with opencv_optimized(optimized):
        errors = {0.0: [], 0.8: []}
        for seed in range(4):
            a, b, h_ba = _zoom_pair(3.0, seed)
            start = h_ba @ geometry.translation(2.0, -1.4)
            for sigma in errors:
                equal_a, equal_b = image_refine.equal_resolution(a, b, start, sigma)
                h = search.ecc_refine(equal_a, equal_b, start)
                errors[sigma].append(image_errors(h[None], h_ba[None])[0])
    assert np.mean(errors[0.8]) < 0.8 * np.mean(errors[0.0])


@pytest.mark.slow
def test_the_whole_image_refinement_reaches_zoomed_pairs_it_missed_at_two_resolutions():
    """``estimate_images`` (the whole-image refinement, no search) from an estimate 4 px off on
    the two-camera zoom pairs (2.5x and 3x, 4 scenes each): under 1 px on 4 of 8 with the default
    ``resolution_sigma`` (0.14-0.65 px) against 1 of 8 with 0 (the others 12-413 px; measured)."""
    reached = {0.0: 0, 0.8: 0}
    for scale in (2.5, 3.0):
        for seed in range(4):
            a, b, h_ba = _zoom_pair(scale, seed)
            off = geometry.image_to_patch(h_ba @ geometry.translation(4.0, -2.8), *ORIGIN)
            estimator = HomographyEstimator([constant_stage(off, "off")])
            for sigma in reached:
                thresholds = Thresholds() if sigma else Thresholds(resolution_sigma=0.0)
                assert thresholds.resolution_sigma == sigma  # the default is 0.8
                options = EstimateOptions(search="none", refine="images", verify="ecc",
                                          thresholds=thresholds)
                est = estimator.estimate_images_with_info(
                    pixels.to_uint8(a), pixels.to_uint8(b), options)
                reached[sigma] += int(image_errors(est.homography, h_ba[None])[0] < 1.0)
    assert reached[0.8] >= reached[0.0] + 2


def _moving_object_pair(margin):
    """(image_a, image_b) as :func:`_pair` (TRUTH), with an object in the middle of image_b
    moving on its own: the central patch's square ``margin`` px inside its border is cut from
    image_b made by TRUTH moved by (7, -5) px."""
    a, b = _pair(TRUTH)
    _, moved = _pair(TRUTH @ geometry.translation(7.0, -5.0))
    x0, y0 = ORIGIN
    inner = np.s_[y0 + margin:y0 + 128 - margin, x0 + margin:x0 + 128 - margin]
    b[inner] = moved[inner]
    return a, b


@pytest.mark.parametrize("optimized", [pytest.param(True, id="opencv_optimized"),
                                       pytest.param(False, id="opencv_unoptimized")])
def test_a_move_the_whole_images_bring_back_does_not_flag_the_estimate(optimized):
    """An object moving in the middle of image_b (the patch's central 104 x 104 px): ECC on
    patch_b follows it, 15.8 px from the right estimate (0.22 px off); ECC over the whole
    images, started there, comes back to within 0.001 px of the estimate, and the whole images
    align at NCC 0.9635 (both OpenCV paths, measured): the move is confirmed and does not flag
    the estimate. The search's bar ``verified_ncc`` plays no part (issue 79: before, above that
    NCC, 0.99, the move flagged the estimate; an exposure change brings right estimates under
    0.95). Reference: the truth that made the rest of image_b."""
    a, b = _moving_object_pair(12)
    estimator = _estimator_off_by((0.0, 0.0))
    with opencv_optimized(optimized):
        runs = {ncc: estimator.estimate_images_with_info(a, b, EstimateOptions(
            search="none", refine="images", verify="ecc",
            thresholds=Thresholds(verified_ncc=ncc))) for ncc in (0.95, 0.99)}
    est = runs[0.95]
    assert Thresholds().verified_ncc == 0.95
    assert image_errors(est.homography, TRUTH[None])[0] < 1.0
    assert est.verify_move_px[0] > 10.0
    assert est.move_confirmed[0] and not est.implausible[0]
    strict = runs[0.99]
    assert strict.verify_move_px[0] == pytest.approx(est.verify_move_px[0], rel=1e-6)
    assert strict.move_confirmed[0] and not strict.implausible[0]


@pytest.mark.parametrize("optimized", [pytest.param(True, id="opencv_optimized"),
                                       pytest.param(False, id="opencv_unoptimized")])
def test_a_move_is_confirmed_where_noise_keeps_the_whole_images_under_the_search_bar(optimized):
    """Issue 79: a right estimate of the paper's protocol with an exposure change stayed
    flagged: the patch ECC moved it 6.7 px, the whole images brought the move back, but aligned
    at NCC 0.92 under the estimate, below the search's bar 0.95 that the confirmation asked.
    Here the moving-object pair with noise (sigma 20 grey levels) in image_b: its whole images
    align under the truth well below 0.95 (the inner region's NCC, ``cv2.matchTemplate``), and
    better than where the patch ECC moved the estimate; the move is confirmed and does not flag
    the right estimate (before: flagged)."""
    a, b = _moving_object_pair(12)
    noise = np.random.default_rng(0).normal(0.0, 20.0, b.shape)
    b = np.clip(b + noise, 0, 255).astype(np.uint8)
    with opencv_optimized(optimized):
        est = _estimator_off_by((0.0, 0.0)).estimate_images_with_info(
            a, b, EstimateOptions(search="none", refine="images", verify="ecc"))
    work_a, _ = image_input.work_image(a)
    work_b, _ = image_input.work_image(b)
    warped = cv2.warpPerspective(work_a, TRUTH, (W, H),
                                 flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    inner = np.s_[40:200, 40:280]
    ncc = cv2.matchTemplate(warped[inner].astype(np.float32), work_b[inner].astype(np.float32),
                            cv2.TM_CCOEFF_NORMED)[0, 0]
    assert ncc < 0.93 < Thresholds().verified_ncc
    assert image_errors(est.homography, TRUTH[None])[0] < 1.0
    assert est.verify_move_px[0] > 2 * Thresholds().max_verify_move
    assert est.move_confirmed[0] and not est.implausible[0]


def test_move_confirmed_compares_the_two_alignments(monkeypatch):
    """The NCC condition of ``image_refine.move_confirmed`` alone (the whole-image ECC made to
    come back to the estimate): confirmed where the whole images align under the estimate at
    least as well as under patch_b's optimum, not where worse, and not where the NCC under the
    estimate is undefined (``coarse.image_ncc``'s ``-inf``), even if the optimum's is too."""
    from stnh_tf.inference import coarse

    t = Thresholds()
    estimate, optimum = np.eye(3), geometry.translation(9.0, 0.0)
    monkeypatch.setattr(image_refine, "_whole_image_ecc", lambda *args: estimate)

    def confirmed(ncc_estimate, ncc_optimum):
        values = {0.0: ncc_estimate, 9.0: ncc_optimum}
        monkeypatch.setattr(coarse, "image_ncc", lambda a, b, h, *rest: values[h[0, 2]])
        return image_refine.move_confirmed(9.0, optimum, estimate, None, None, (H, W), (0, 0), t)

    assert confirmed(0.80, 0.79) and confirmed(0.80, 0.80) and confirmed(0.5, -np.inf)
    assert not confirmed(0.79, 0.80) and not confirmed(-np.inf, -np.inf)
    assert not confirmed(-np.inf, 0.3)


def test_move_confirmed_needs_a_return_a_good_alignment_and_a_move_beyond_the_limit():
    """``image_refine.move_confirmed`` on the moving-object pair: True for the patch optimum of
    the right estimate; False where the move is within ``max_verify_move`` (nothing to excuse),
    where ECC failed (no optimum, an infinite move), for an estimate 20 px off under which the
    whole images align worse than under the patch optimum (NCCs against OpenCV's own
    ``cv2.matchTemplate``), and for a start so far (60 px) that the whole-image ECC does not
    come back to the estimate (checked with ``search.ecc_refine``)."""
    a, b = _moving_object_pair(12)
    work_a, _ = image_input.work_image(a)
    work_b, _ = image_input.work_image(b)
    t = Thresholds()
    right = geometry.image_to_patch(TRUTH, *ORIGIN)
    equal = image_refine.equal_resolution(work_a, work_b, TRUTH, t.resolution_sigma)
    patch_b = image_input.central_patch(work_b)[0, ..., 0]

    def confirmed(move, optimum, h):
        return image_refine.move_confirmed(move, optimum, h, *equal, (H, W), ORIGIN, t)

    optimum = search.ecc_refine(work_a, patch_b, right, ORIGIN, t)
    move = checks.verify_move(optimum, right, (H, W), ORIGIN)
    assert move > 10.0 and confirmed(move, optimum, right)
    assert not confirmed(t.max_verify_move, optimum, right)
    assert not confirmed(np.inf, None, right) and not confirmed(move, None, right)
    # 20 px off: the whole images align worse there than at the patch optimum
    off = geometry.image_to_patch(TRUTH @ geometry.translation(16.0, -12.0), *ORIGIN)
    inner = np.s_[40:200, 40:280]

    def ncc(h_image):
        warped = cv2.warpPerspective(work_a, h_image, (W, H),
                                     flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
        return cv2.matchTemplate(warped[inner].astype(np.float32),
                                 work_b[inner].astype(np.float32), cv2.TM_CCOEFF_NORMED)[0, 0]

    assert ncc(TRUTH @ geometry.translation(16.0, -12.0)) < 0.8
    assert ncc(TRUTH @ geometry.translation(16.0, -12.0)) + 0.05 < ncc(
        geometry.patch_to_image(optimum, *ORIGIN))
    assert not confirmed(move, optimum, off)
    # from 60 px away the whole-image ECC ends elsewhere (or fails): not back at the estimate
    far = geometry.image_to_patch(TRUTH @ geometry.translation(48.0, -36.0), *ORIGIN)
    back = search.ecc_refine(*equal, geometry.patch_to_image(far, *ORIGIN), (0, 0), t)
    assert back is None or image_errors(back[None], TRUTH[None])[0] > t.max_verify_move
    assert not confirmed(checks.verify_move(far, right, (H, W), ORIGIN), far, right)
