"""The feature start at the images' own resolution (issue 79, item 2;
:func:`stnh_tf.inference.image_input.input_image`, :func:`stnh_tf.inference.features.start_images`,
:func:`~stnh_tf.inference.features.work_start`): SIFT + ratio test + ``cv2.USAC_MAGSAC`` on each
image at its own size (capped at ``FEATURE_MAX_SIDE``, ``cv2.INTER_AREA``), its ``H_ba`` mapped
into the 320 x 240 work frame by the resize maps. References: ``cv2.resize``'s own geometry (the
maps), the homography each synthetic pair was warped with (``cv2.warpPerspective``), and
``cv2.findHomography`` on the same keypoints."""

import cv2
import numpy as np
import pytest

from conftest import constant_stage
from stnh_tf import geometry
from stnh_tf.inference import features, image_input
from stnh_tf.inference.estimator import HomographyEstimator
from stnh_tf.inference.options import EstimateOptions

WORK = image_input.WORK_SIZE


@pytest.fixture(scope="module")
def estimator():
    """A network that outputs the identity whatever its input: what the estimator finds beyond it
    comes from the feature start."""
    return HomographyEstimator([constant_stage(np.eye(3), "identity")])


def _motion(size, angle_deg, scale, tilt=0.0):
    """Image-frame a_from_b of a ``size = (w, h)`` image: rotation by ``angle_deg`` and scaling by
    ``scale`` about the image centre (``scale < 1``: b sees a magnified by ``1 / scale``), with a
    perspective term ``tilt``."""
    c = geometry.translation((size[0] - 1) / 2, (size[1] - 1) / 2)
    m = np.vstack([cv2.getRotationMatrix2D((0.0, 0.0), angle_deg, scale), [0.0, 0.0, 1.0]])
    m[2, 0] = tilt
    return c @ m @ np.linalg.inv(c)


def _texture(seed, size, fine):
    """A random texture ``uint8`` twice ``size``: smooth noise (Gaussian, sigma 6 px), or
    (``fine``) band-pass noise (sigma 1.5 to 5 px) on mid-grey in blobs covering 10% of it, which
    averages away at 1/4 of the size (a 1280 x 960 image's 320 x 240 version)."""
    rng = np.random.default_rng(seed)
    shape = (2 * size[1], 2 * size[0])
    x = rng.random(shape).astype(np.float32)
    if not fine:
        t = cv2.GaussianBlur(x, (0, 0), 6.0)
        return pixels_u8((t - t.min()) / np.ptp(t))
    band = cv2.GaussianBlur(x, (0, 0), 1.5) - cv2.GaussianBlur(x, (0, 0), 5.0)
    mask = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 12.0)
    mask = cv2.GaussianBlur((mask > np.quantile(mask, 0.9)).astype(np.float32), (0, 0), 3.0)
    return pixels_u8(0.5 + 0.15 * mask * band / band.std())


def pixels_u8(unit):
    return np.clip(np.rint(unit * 255.0), 0, 255).astype(np.uint8)


def _pair(texture, h_ba, size):
    """(image_a, image_b) of ``size``: image_a the texture's centre, ``b(q) = a(h_ba q)``
    (OpenCV warp of the texture, so b sees a's surroundings)."""
    o = geometry.translation(size[0] / 2, size[1] / 2)
    flags = cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR
    return (cv2.warpPerspective(texture, o, size, flags=flags),
            cv2.warpPerspective(texture, o @ h_ba, size, flags=flags))


def _corner_error(h, h_true, size=WORK):
    """Mean distance (px) at a ``size`` image's corners (cv2.perspectiveTransform)."""
    w, hh = size
    corners = np.array([[[0, 0], [w, 0], [w, hh], [0, hh]]], np.float64)
    return float(np.linalg.norm(cv2.perspectiveTransform(corners, h)[0]
                                - cv2.perspectiveTransform(corners, h_true)[0], axis=1).mean())


def _to_work(h_image, size):
    """An image-frame ``H_ba`` of two ``size`` images in the work frame: ``S @ H @ inv(S)``."""
    s = image_input.resize_matrix(size, WORK)
    return geometry.scale_to_unit(s @ h_image @ np.linalg.inv(s))


def _inputs(a, b):
    return (image_input.input_image(a, "image_a", feature_image=True),
            image_input.input_image(b, "image_b", feature_image=True))


def test_feature_and_work_maps_follow_cv2_resize():
    """An image whose pixels hold their own coordinates (x / w and y / h, float): its feature
    image (2400 x 1800 capped to 1600 x 1200, INTER_AREA) and its work image hold, at the
    interior pixels ``p``, the original coordinates that ``resize_matrix`` maps to ``p``; so
    ``work_from_feature`` maps a feature pixel to the work pixel of the same original point
    (the line through them within 1e-3 px; float32 resizing). Sizes that fit in 320 x 240 have
    no feature image."""
    size = (2400, 1800)
    xs, ys = np.meshgrid(np.arange(size[0]), np.arange(size[1]))
    for coord, axis in ((xs, 0), (ys, 1)):
        img = image_input.input_image((coord / size[axis]).astype(np.float32),
                                      feature_image=True)
        assert img.feature.shape == (1200, 1600) and img.size == size
        for resized, target in ((img.feature, (1600, 1200)), (img.work, WORK)):
            m = image_input.resize_matrix(size, target)
            inner = resized[2:-2, 2:-2].astype(np.float64) * size[axis]  # original coordinate
            q = np.arange(2, target[axis] - 2)
            mapped = m[axis, axis] * inner + m[axis, 2]  # its original point, mapped
            mapped = mapped.mean(axis=axis)  # over the other coordinate: all the same
            slope, offset = np.polyfit(q, mapped, 1)
            assert slope == pytest.approx(1.0, abs=1e-6) and offset == pytest.approx(0, abs=1e-3)
            # INTER_AREA at a ratio that is not an integer averages pixels as constant cells:
            # a periodic wobble about the map (1/18 px at 3:2), no offset
            assert np.abs(mapped - q).max() < 0.06
    f = image_input.resize_matrix(size, (1600, 1200))
    np.testing.assert_allclose(image_input.work_from_feature(size) @ f,
                               image_input.resize_matrix(size, WORK), atol=1e-12)
    assert image_input.feature_size((4000, 3000)) == (1600, 1200)
    assert image_input.feature_size((1600, 900)) == (1600, 900)  # never enlarged nor shrunk
    assert image_input.feature_size((321, 100)) == (321, 100)
    for small in ((320, 240), (200, 150), (64, 240)):
        assert image_input.feature_size(small) is None
        np.testing.assert_array_equal(image_input.work_from_feature(small), np.eye(3))


@pytest.mark.parametrize("size", [(1280, 960), pytest.param(
    (2400, 1800), marks=pytest.mark.slow)])  # the capped size: SIFT at 1600 x 1200, 9 s
def test_native_start_is_the_true_homography_in_the_work_frame(size):
    """A smooth texture warped by a known ``H`` (rotation 30 degrees, zoom 1.3, a perspective
    term) at 1280 x 960 (matched at that size) and 2400 x 1800 (matched at 1600 x 1200): the
    feature start's work-frame ``H_ba`` is ``S @ H @ inv(S)`` to 0.2 px at the work image's
    corners (measured 0.04-0.07 px over seeds 0-2 and both sizes; the start on the 320 x 240
    work images: 0.22-0.24 px), and it is exactly OpenCV's ``cv2.findHomography``
    (``USAC_MAGSAC``) of the same SIFT matches, made in the test, mapped by the resize maps."""
    h_true = _motion(size, 30.0, 1.3, 1e-5 * 1280 / size[0])
    a, b = _pair(_texture(0, size, fine=False), h_true, size)
    input_a, input_b = _inputs(a, b)
    start = features.start_images(input_a, input_b)
    h_work = features.work_start(start)
    assert _corner_error(h_work, _to_work(h_true, size)) < 0.2

    target = image_input.feature_size(size)
    near = [a, b] if target == size else [cv2.resize(x, target, interpolation=cv2.INTER_AREA)
                                          for x in (a, b)]
    for mine, ref in zip((start.image_a, start.image_b), near):
        np.testing.assert_array_equal(mine, ref)
    sift = cv2.SIFT_create(**features.SIFT)
    (kp_a, d_a), (kp_b, d_b) = (sift.detectAndCompute(x, None) for x in near)
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d_b, d_a, k=2)
    good = [m for m, n in knn if m.distance < features.RATIO * n.distance]
    h_feat, _ = cv2.findHomography(np.float32([kp_b[m.queryIdx].pt for m in good]),
                                   np.float32([kp_a[m.trainIdx].pt for m in good]),
                                   cv2.USAC_MAGSAC, **features.MAGSAC)
    s, f = image_input.resize_matrix(size, WORK), image_input.resize_matrix(size, target)
    want = geometry.scale_to_unit(s @ np.linalg.inv(f) @ h_feat @ f @ np.linalg.inv(s))
    np.testing.assert_allclose(h_work, want, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("motion", [(70.0, 0.4), (-120.0, 0.45, -2e-5)])
def test_native_start_finds_what_the_work_images_lost(motion):
    """Fine texture (band-pass noise at 1.5-5 px) that averages away in the 320 x 240 version of
    a 1280 x 960 image, with a zoom of 2.2-2.5x and a rotation of 70-120 degrees: the start at
    the images' own size is within 0.3 px of the true homography at the work image's corners
    (measured 0.08-0.12 px over seeds 0-2); the start on the work images finds none."""
    size = (1280, 960)
    h_true = _motion(size, *motion)
    a, b = _pair(_texture(0, size, fine=True), h_true, size)
    input_a, input_b = _inputs(a, b)
    assert _corner_error(features.work_start(features.start_images(input_a, input_b)),
                         _to_work(h_true, size)) < 0.3
    # on the work images SIFT finds no start, or (another CPU's kernels) a wrong one
    lost = features.feature_start(input_a.work, input_b.work)
    assert lost is None or _corner_error(lost, _to_work(h_true, size)) > 5.0


def test_estimate_images_recovers_a_wide_zoom_from_fine_detail(estimator):
    """The pair above through ``estimate_images`` (its default, ``photographs()``), the network
    the identity: within 0.5 px of the true homography at the 1280 x 960 image's corners
    (measured 0.12 px), made from the feature start, not flagged. Before the start ran at the
    images' own size, this pair's estimate was the identity, flagged (the work images lost the
    texture)."""
    size = (1280, 960)
    h_true = _motion(size, 70.0, 0.4)
    a, b = _pair(_texture(0, size, fine=True), h_true, size)
    est = estimator.estimate_images_with_info(a, b)
    assert _corner_error(est.homography[0], h_true, size) < 0.5
    assert est.feature_start[0] and not est.implausible[0]


def test_images_that_fit_the_work_size_keep_the_work_images_start(estimator, monkeypatch):
    """Images at or below 320 x 240 (the pair and a 256 x 192 one): no feature image, no
    :class:`features.StartImages`; the feature start receives the work images themselves, and
    no larger image is made (the path before issue 79). A pair of 1280 x 960 images whose work
    images hold the texture: their start is confirmed, and the start at the images' own size is not made (it costs more, and adds only
    the detail a strong zoom needs); where the work images' start finds nothing (fine texture),
    the start at the images' own size is made once per call."""
    seen = []
    start = features.feature_start
    monkeypatch.setattr(features, "feature_start",
                        lambda a, b: seen.append((a, b)) or start(a, b))
    for size in (WORK, (256, 192)):
        h_true = _motion(size, 100.0, 0.6)
        a, b = _pair(_texture(1, size, fine=False), h_true, size)
        input_a, input_b = _inputs(a, b)
        assert input_a.feature is None and input_b.feature is None
        assert features.start_images(input_a, input_b) is None
        seen.clear()
        est = estimator.estimate_images_with_info(a, b)
        assert seen and est.feature_start[0]
        for got_a, got_b in seen:
            np.testing.assert_array_equal(got_a, input_a.work)
            np.testing.assert_array_equal(got_b, input_b.work)
    size = (1280, 960)
    h_true = _motion(size, 100.0, 0.6)
    a, b = _pair(_texture(1, size, fine=False), h_true, size)
    seen.clear()
    est = estimator.estimate_images_with_info(a, b)
    assert seen and all(x.shape == (240, 320) for pair in seen for x in pair)
    assert est.feature_start[0] and not est.implausible[0]
    assert _corner_error(est.homography[0], h_true, size) < 0.5
    a, b = _pair(_texture(0, size, fine=True), _motion(size, 70.0, 0.4), size)
    seen.clear()
    estimator.estimate_images_with_info(a, b)
    native = [pair for pair in seen if pair[0].shape == (960, 1280)]
    assert len(native) == 1  # after the work images' start, SIFT once at the images' size


def test_the_papers_path_makes_no_feature_image(estimator, monkeypatch):
    """``features="none"`` (``network_only()``, ``EstimateOptions()``) never resizes for the
    feature start: a large pair goes through without :func:`features.start_images`."""
    def refuse(*inputs):
        raise AssertionError("start_images called with features='none'")

    monkeypatch.setattr(features, "start_images", refuse)
    size = (1280, 960)
    a, b = _pair(_texture(1, size, fine=False), _motion(size, 3.0, 1.0), size)
    for options in (EstimateOptions.network_only(), EstimateOptions()):
        est = estimator.estimate_images_with_info(a, b, options)
        assert not est.feature_start[0]
