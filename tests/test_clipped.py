"""Clipped pixels (black, or saturated by an exposure change) left out of the alignment measures
(issue 79): against exact references where the two images are related by gain and offset on
every pixel that is not clipped."""

import cv2
import numpy as np
import pytest

from conftest import opencv_optimized
from stnh_tf import geometry
from stnh_tf.inference import checks, coarse, ecc
from stnh_tf.pixels import unclipped

TRUE = np.array([[1.03, 0.02, 3.2], [-0.015, 0.98, -2.1], [2e-4, -1e-4, 1.0]])


def _scene(shape=(240, 320), seed=3):
    """A smooth image in [0, 1] and the same image exposed brighter (gain 2.2, offset -0.3,
    clipped to [0, 1], as a sensor does): about a third of it saturated."""
    a = cv2.GaussianBlur(np.random.default_rng(seed).random(shape), (0, 0), 2.5)
    a = (a - a.min()) / np.ptp(a)
    return a, np.clip(2.2 * a - 0.3, 0.0, 1.0)


def test_unclipped_marks_the_ends_of_the_unit_scale_only():
    _, bright = _scene()
    mask = unclipped(bright)
    assert np.array_equal(mask, (bright > 0.5 / 255) & (bright < 1 - 0.5 / 255))
    assert 0.2 < 1 - mask.mean() < 0.6  # the scene is what the tests below need
    assert unclipped(bright * 255).all() and unclipped(bright - 0.5).all()  # other scales


def test_alignment_ncc_of_an_exposure_change_is_one_over_the_pixels_not_clipped():
    a, bright = _scene()
    patch_b = bright[:128, :128]
    kept = unclipped(patch_b)
    # the reference: NumPy's correlation over every pixel (what the NCC was) and over the kept
    assert np.corrcoef(a[:128, :128].ravel(), patch_b.ravel())[0, 1] < 0.97
    assert np.corrcoef(a[:128, :128][kept], patch_b[kept])[0, 1] == pytest.approx(1.0, abs=1e-9)
    assert checks.alignment_ncc(a, patch_b, np.eye(3)) == pytest.approx(1.0, abs=1e-6)
    assert coarse.image_ncc(a, bright, np.eye(3), (0, 0), 0.25) == pytest.approx(1.0, abs=1e-6)


def test_corner_precision_of_an_exposure_change_is_that_of_an_exact_alignment():
    a, bright = _scene()
    # gain and offset fit every pixel not clipped exactly: no residual, no spread
    assert checks.corner_std(a, bright, np.eye(3), tile=8) < 1e-6
    assert checks.corner_std(a, bright, np.eye(3)) < 1e-6
    # noise on the pixels not clipped (kept inside the grey range): a spread, the masks still on
    kept = unclipped(bright)
    noisy = np.where(kept, np.clip(bright + np.random.default_rng(1).normal(0, 0.01, bright.shape),
                                   1 / 255, 254 / 255), bright)
    assert np.array_equal(unclipped(noisy), kept)
    assert 1e-4 < checks.corner_std(a, noisy, np.eye(3)) < 0.1


@pytest.mark.parametrize("optimized", [True, False], ids=["opencv_optimized",
                                                          "opencv_unoptimized"])
def test_opencv_ecc_of_a_saturated_template_converges_to_the_true_homography(optimized):
    source, _ = _scene((160, 160))
    ys, xs = np.mgrid[0:128, 0:128].astype(np.float64)
    pts = geometry.warp_points(TRUE, np.stack([xs.ravel(), ys.ravel()], axis=1))
    from scipy import ndimage

    template = ndimage.map_coordinates(source, [pts[:, 1], pts[:, 0]], order=1,
                                       mode="mirror").reshape(128, 128)
    template = np.clip(2.2 * template - 0.3, 0.0, 1.0)
    start = geometry.translation(1.0, -0.8) @ TRUE
    with opencv_optimized(optimized):
        h = ecc.opencv_ecc(source, template, start, 100, 1e-6)
    error = float(geometry.corner_errors(h[None], TRUE[None])[0])
    assert error < 0.05, error


@pytest.mark.parametrize("optimized", [True, False])
def test_a_binary_image_is_aligned_not_left_undetermined(optimized):
    """A black-and-white image (a scan, a mask, text without anti-aliasing) had every pixel
    counted as clipped: every alignment measure undefined, the estimate replaced by the identity
    (40 px off, flagged). Fewer than 2% of its values unclipped, none is left out now: random
    30 x 40 blocks at 640 x 480, image_b shifted 40 px, found to about 0.01 px (1 px allowed: the
    flag's measures are at 1.0 and 0.0 here, far from their thresholds), not flagged; the error
    measured at image_b's corners with ``cv2.perspectiveTransform``."""
    from stnh_tf.inference.estimator import HomographyEstimator

    rng = np.random.default_rng(3)
    blocks = (rng.random((30, 40)) > 0.5).astype(np.uint8) * 255
    a = cv2.resize(blocks, (640, 480), interpolation=cv2.INTER_NEAREST)
    h_ba = np.array([[1.0, 0, 40], [0, 1, 0], [0, 0, 1]])
    b = cv2.warpPerspective(a, h_ba, (640, 480), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    assert unclipped(a / 255.0).all()  # (each pixel at 0 or 1: a binary image, all kept)
    with opencv_optimized(optimized):
        est = HomographyEstimator.load().estimate_images_with_info(a, b)
    corners = np.float32([[0, 0], [640, 0], [640, 480], [0, 480]]).reshape(-1, 1, 2)
    error = np.linalg.norm(cv2.perspectiveTransform(corners, est.homography[0])
                           - cv2.perspectiveTransform(corners, h_ba), axis=-1).mean()
    assert error < 1.0 and not est.implausible[0] and not est.undetermined[0], error
