"""stnh_tf.inference.ecc against independent references: exact float64 warps (scipy), NumPy's
correlation, and OpenCV's own ECC; and the same result on OpenCV's optimized and unoptimized code
paths."""

import cv2
import numpy as np
import pytest
from scipy import ndimage

from conftest import opencv_optimized
from stnh_tf import geometry
from stnh_tf.inference import ecc

TRUE = np.array([[1.03, 0.02, 3.2], [-0.015, 0.98, -2.1], [2e-4, -1e-4, 1.0]])


def _exact_warp(source, source_from_template, shape):
    """template(p) = source(H p), bilinear in float64 (no quantization), mirror beyond source."""
    ys, xs = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    pts = geometry.warp_points(source_from_template, np.stack([xs.ravel(), ys.ravel()], axis=1))
    return ndimage.map_coordinates(source, [pts[:, 1], pts[:, 0]], order=1,
                                   mode="mirror").reshape(shape)


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(3)
    source = cv2.GaussianBlur(rng.random((128, 128)), (0, 0), 2.5)
    source = (source - source.min()) / np.ptp(source)
    return source, _exact_warp(source, TRUE, (128, 128))


@pytest.fixture(params=[True, False], ids=["opencv_optimized", "opencv_unoptimized"])
def opencv_path(request):
    with opencv_optimized(request.param):
        yield request.param


def _corner_error(a, b):
    return float(geometry.corner_errors(np.asarray(a)[None], np.asarray(b)[None])[0])


def test_ecc_homography_recovers_an_exactly_warped_homography(scene):
    source, template = scene
    start = geometry.translation(1.5, -1.0) @ TRUE  # corners about 2 px off
    assert _corner_error(start, TRUE) > 1.5
    h, rho = ecc.ecc_homography(source, template, start, iterations=200, eps=1e-10)
    # the template is an exact float64 warp, so the optimum is the true H itself
    assert _corner_error(h, TRUE) < 1e-3
    assert h[2, 2] == 1.0
    # rho is the zero-mean normalized correlation (NumPy's corrcoef) of the template and the
    # source warped by the result, over the pixels inside the source
    warped = _exact_warp(source, h, template.shape)
    assert rho == pytest.approx(np.corrcoef(warped.ravel(), template.ravel())[0, 1], abs=1e-6)


def test_ecc_homography_agrees_with_opencv_near_the_optimum(scene):
    source, template = scene
    start = geometry.translation(0.4, 0.3) @ TRUE
    ours, _ = ecc.ecc_homography(source, template, start, iterations=200, eps=1e-10)
    theirs = ecc.opencv_ecc(source, template, start, 200, 1e-10)
    # OpenCV warps with bilinear weights quantized to 1/32 px: its optimum differs from the exact
    # one by a few hundredths of a px (measured 0.024 px here)
    assert _corner_error(ours, theirs) < 0.05


def test_coarse_to_fine_ecc_converges_from_far_and_is_the_same_on_both_opencv_paths(scene,
                                                                                    opencv_path):
    source, template = scene
    start = geometry.translation(7.0, -5.0) @ TRUE
    assert _corner_error(start, TRUE) > 8
    h = ecc.coarse_to_fine_ecc(source, template, start)
    # the full-resolution level is OpenCV's (quantized warp): within 0.05 px of the exact optimum
    assert _corner_error(h, TRUE) < 0.05
    cv2.setUseOptimized(not opencv_path)
    other = ecc.coarse_to_fine_ecc(source, template, start)
    # OpenCV's two paths differ in float32 rounding only (measured 6e-6 px here); 0.01 px is the
    # bar of the search's study (a different optimum is tenths of a px or more away)
    assert _corner_error(h, other) < 0.01


def test_coarse_levels_map_between_pyramid_frames():
    """A pure translation found on 1/4-size levels is scaled back exactly: cv2.pyrDown keeps
    pixel j of a level at pixel 2 j of the one below."""
    rng = np.random.default_rng(5)
    source = cv2.GaussianBlur(rng.random((128, 128)), (0, 0), 3)
    shift = geometry.translation(6.0, -4.0)
    template = _exact_warp(source, shift, (128, 128))
    h = ecc.coarse_to_fine_ecc(source, template, np.eye(3))
    np.testing.assert_allclose(h[:2, 2], [6.0, -4.0], atol=0.05)


def test_failures_return_none(scene):
    source, template = scene
    # the template maps outside the source
    assert ecc.ecc_homography(source, template, geometry.translation(500.0, 0.0)) is None
    assert ecc.opencv_ecc(source, template, np.full((3, 3), np.nan), 10, 1e-5) is None
    # anti-correlated images: ECC's step would minimise the correlation
    assert ecc.ecc_homography(source, -_exact_warp(source, TRUE, (128, 128)), TRUE) is None
    # a flat template has no correlation to maximise
    assert ecc.ecc_homography(source, np.zeros((128, 128)), TRUE) is None


def test_bilinear_is_scipys_order_1_sampling_of_every_image_at_once():
    # issue 64 (speed): one gather for the image and its two gradients instead of three
    # map_coordinates calls; the same products summed in the same order, so equal up to float64
    # rounding (measured: identical on 100,000 random points, 1 ulp on a few near the first row)
    rng = np.random.default_rng(5)
    images = rng.random((3, 30, 45))
    u = np.concatenate([rng.uniform(0, 44, 20000), [44.0, 0.0, 44.0, 7.5]])
    v = np.concatenate([rng.uniform(0, 29, 20000), [29.0, 0.0, 0.25, 29.0]])  # the far edges
    got = ecc.bilinear(images, u, v)
    want = np.stack([ndimage.map_coordinates(im, [v, u], order=1) for im in images])
    assert got.shape == (3, len(u))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-15)
