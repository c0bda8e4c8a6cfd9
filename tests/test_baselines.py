"""Classical baselines (ORB/SIFT + RANSAC): direction, accuracy on real photographs, failure
fallback and bad input. Pairs are made here with OpenCV from scikit-image's photographs."""

import cv2
import numpy as np
import pytest

from conftest import paper_homography
from stnh_tf import baselines, geometry


def _pairs(rng, n=12):
    import skimage.data

    photos = [skimage.data.astronaut(), skimage.data.coffee(), skimage.data.chelsea(), skimage.data.camera()]
    pa, pb, hs = [], [], []
    for i in range(n):
        p = photos[i % len(photos)]
        gray = cv2.resize(p if p.ndim == 2 else cv2.cvtColor(p, cv2.COLOR_RGB2GRAY), (320, 240),
                          interpolation=cv2.INTER_AREA)
        x0, y0 = int(rng.integers(32, 161)), int(rng.integers(32, 81))
        h = paper_homography(rng)
        t = np.array([[1, 0, x0], [0, 1, y0], [0, 0, 1.0]])
        image_b = cv2.warpPerspective(gray, t @ h @ np.linalg.inv(t), (320, 240),
                                      flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
        pa.append(gray[y0:y0 + 128, x0:x0 + 128])
        pb.append(image_b[y0:y0 + 128, x0:x0 + 128])
        hs.append(h)
    return np.stack(pa), np.stack(pb), np.stack(hs)


@pytest.mark.parametrize("name", ["orb_ransac", "sift_ransac"])
def test_feature_baselines_recover_h_ba(name, rng):
    pa, pb, h = _pairs(rng)
    res = baselines.evaluate_baseline(name, pa, pb, h)
    identity = float(geometry.mean_corner_error(np.broadcast_to(np.eye(3), h.shape), h))
    assert identity > 15
    assert res["median"] < 3.0 and res["mace"] < 0.3 * identity, res
    assert res["count"] == len(h) and 0 <= res["failure_rate"] <= 0.2
    # Direction: the estimate maps patch_b into patch_a; its inverse would be far off.
    est = baselines.make_baseline(name)
    h_pred, ok = est.estimate_batch(pa, pb)
    inverse_err = geometry.corner_errors(np.linalg.inv(h_pred[ok]), h[ok]).mean()
    assert inverse_err > 5 * geometry.corner_errors(h_pred[ok], h[ok]).mean()
    # uint8 and float [0, 1] inputs give the same estimates.
    h_float, _ = est.estimate_batch(pa / 255.0, pb / 255.0)
    np.testing.assert_allclose(h_float, h_pred, atol=1e-9)


def test_textureless_pair_falls_back_to_identity():
    flat = np.full((2, 128, 128), 127, np.uint8)
    for name in ("orb_ransac", "sift_ransac"):
        h, ok = baselines.make_baseline(name).estimate_batch(flat, flat)
        assert not ok.any()
        np.testing.assert_array_equal(h, np.broadcast_to(np.eye(3), (2, 3, 3)))


def test_identity_baseline_scores_the_identity(rng):
    pa, pb, h = _pairs(rng, 4)
    res = baselines.evaluate_baseline("identity", pa, pb, h)
    ref = float(geometry.mean_corner_error(np.broadcast_to(np.eye(3), h.shape), h))
    assert res["mace"] == pytest.approx(ref)


@pytest.mark.parametrize("shape", [(128, 128, 3), (2, 64, 64), (2, 128, 128, 2)])
def test_bad_shapes_raise(shape):
    with pytest.raises(ValueError, match=str(shape[-1])):
        baselines.make_baseline("orb_ransac").estimate_batch(np.zeros(shape, np.uint8), np.zeros(shape, np.uint8))


def test_unknown_baseline_raises():
    with pytest.raises(ValueError, match="unknown baseline"):
        baselines.make_baseline("surf")
