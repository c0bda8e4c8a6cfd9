"""Tests of stnh_tf.geometry against OpenCV and independent NumPy references."""

import subprocess
import sys

import cv2
import numpy as np
import pytest

from conftest import norm_matrix, paper_homography
from stnh_tf import geometry as g

CORNERS = np.array([[0, 0], [128, 0], [128, 128], [0, 128]], np.float64)


def _random_hs(rng, n):
    return np.stack([paper_homography(rng) for _ in range(n)])


def test_normalization_matrix_is_the_papers():
    np.testing.assert_array_equal(g.normalization_matrix(128, 128), norm_matrix(128, 128))
    np.testing.assert_array_equal(g.normalization_matrix(320, 240), norm_matrix(320, 240))


def test_normalize_matches_independent_formula(rng):
    hs = _random_hs(rng, 5)
    m = norm_matrix()
    expected = m @ hs @ np.linalg.inv(m)
    expected = expected / expected[:, 2:3, 2:3]
    got = g.normalize_homography(hs)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
    assert np.all(got[:, 2, 2] == 1.0)
    # Non-square frame.
    m2 = norm_matrix(320, 240)
    e2 = m2 @ hs[0] @ np.linalg.inv(m2)
    np.testing.assert_allclose(g.normalize_homography(hs[0], 320, 240), e2 / e2[2, 2], atol=1e-12)


def test_normalize_denormalize_round_trip(rng):
    hs = _random_hs(rng, 6) * rng.uniform(0.5, 2.0, size=(6, 1, 1))  # arbitrary scale
    back = g.denormalize_homography(g.normalize_homography(hs))
    np.testing.assert_allclose(back, hs / hs[:, 2:3, 2:3], atol=1e-10)
    hb = g.normalize_homography(hs)
    np.testing.assert_allclose(g.normalize_homography(g.denormalize_homography(hb)), hb, atol=1e-12)
    # denormalize is inv(M) @ Hbar @ M
    m = norm_matrix()
    ref = np.linalg.inv(m) @ hb @ m
    np.testing.assert_allclose(g.denormalize_homography(hb), ref / ref[:, 2:3, 2:3], atol=1e-10)


def test_normalized_homography_maps_normalized_points(rng):
    h = paper_homography(rng)
    pts = rng.uniform(0, 128, size=(10, 2))
    pa = cv2.perspectiveTransform(pts[None], h)[0]
    to_n = lambda p: 2.0 * p / 128.0 - 1.0  # x_n = 2x/W - 1
    got = g.warp_points(g.normalize_homography(h), to_n(pts))
    np.testing.assert_allclose(got, to_n(pa), atol=1e-10)


def test_vector_matrix_round_trip(rng):
    hs = _random_hs(rng, 4)
    v = g.matrix_to_vector(hs * 3.0)
    assert v.shape == (4, 8)
    np.testing.assert_allclose(v, hs.reshape(4, 9)[:, :8], atol=1e-12)
    np.testing.assert_allclose(g.vector_to_matrix(v), hs, atol=1e-12)
    # Extra leading dimensions.
    v2 = rng.normal(size=(2, 3, 8))
    m2 = g.vector_to_matrix(v2)
    assert m2.shape == (2, 3, 3, 3)
    np.testing.assert_array_equal(m2[..., 2, 2], 1.0)
    np.testing.assert_allclose(g.matrix_to_vector(m2), v2, atol=1e-12)
    np.testing.assert_array_equal(g.as_matrix(v2), m2)
    np.testing.assert_array_equal(g.as_matrix(m2), m2)


def test_offsets_to_homography_equals_opencv(rng):
    offsets = rng.uniform(-32, 32, size=(5, 4, 2))
    got = g.offsets_to_homography(offsets)
    for i in range(5):
        ref = cv2.getPerspectiveTransform(CORNERS.astype(np.float32),
                                          (CORNERS + offsets[i]).astype(np.float32))
        np.testing.assert_allclose(got[i], ref, rtol=1e-5, atol=1e-5)
    # [..., 8] form gives the same matrices.
    np.testing.assert_allclose(g.offsets_to_homography(offsets.reshape(5, 8)), got, atol=1e-12)
    # homography_from_points with arbitrary (non-corner) points, vs OpenCV.
    pb = rng.uniform(0, 128, size=(4, 2))
    pa = pb + rng.uniform(-20, 20, size=(4, 2))
    np.testing.assert_allclose(
        g.homography_from_points(pb, pa),
        cv2.getPerspectiveTransform(pb.astype(np.float32), pa.astype(np.float32)),
        rtol=1e-4, atol=1e-4)


def test_offsets_homography_round_trip(rng):
    offsets = rng.uniform(-32, 32, size=(7, 4, 2))
    h = g.offsets_to_homography(offsets)
    np.testing.assert_allclose(g.homography_to_offsets(h), offsets, atol=1e-9)
    # Offsets are H @ c - c for the corners (0,0), (128,0), (128,128), (0,128).
    np.testing.assert_allclose(
        cv2.perspectiveTransform(CORNERS[None], h[0])[0] - CORNERS, offsets[0], atol=1e-9)
    np.testing.assert_array_equal(g.patch_corners(), CORNERS)


def test_warp_points_equals_opencv(rng):
    hs = _random_hs(rng, 3)
    pts = rng.uniform(-10, 140, size=(3, 20, 2))
    got = g.warp_points(hs, pts)
    for i in range(3):
        np.testing.assert_allclose(got[i], cv2.perspectiveTransform(pts[i][None], hs[i])[0],
                                   atol=1e-9)
    # Broadcast: one point set against a batch of homographies.
    got_b = g.warp_points(hs, pts[0])
    np.testing.assert_allclose(got_b[2], cv2.perspectiveTransform(pts[0][None], hs[2])[0],
                               atol=1e-9)


def test_image_patch_frames(rng):
    h_img = paper_homography(rng) @ g.translation(5.0, -3.0)
    h_img = h_img / h_img[2, 2]
    x0, y0 = 57, 41
    h_patch = g.image_to_patch(h_img, x0, y0)
    np.testing.assert_allclose(g.patch_to_image(h_patch, x0, y0), h_img, atol=1e-10)
    # Consistency: mapping p in the patch frame == mapping p + (x0, y0) in the image frame, shifted.
    p = rng.uniform(0, 128, size=(12, 2))
    shift = np.array([x0, y0], np.float64)
    in_patch = cv2.perspectiveTransform(p[None], h_patch)[0]
    in_image = cv2.perspectiveTransform((p + shift)[None], h_img)[0]
    np.testing.assert_allclose(in_patch, in_image - shift, atol=1e-9)
    # Pure translations are frame invariant.
    t = g.translation(3.0, 4.0)
    np.testing.assert_allclose(g.image_to_patch(t, 10, 20), t, atol=1e-12)


# OpenCV's own flips and rotations: the independent reference for dihedral_image.
_OPENCV_DIHEDRAL = {
    "identity": lambda x: x, "flip_x": lambda x: cv2.flip(x, 1), "flip_y": lambda x: cv2.flip(x, 0),
    "rotate_180": lambda x: cv2.rotate(x, cv2.ROTATE_180), "transpose": cv2.transpose,
    "rotate_90_cw": lambda x: cv2.rotate(x, cv2.ROTATE_90_CLOCKWISE),
    "rotate_90_ccw": lambda x: cv2.rotate(x, cv2.ROTATE_90_COUNTERCLOCKWISE),
    "anti_transpose": lambda x: cv2.rotate(cv2.transpose(x), cv2.ROTATE_180)}


@pytest.mark.parametrize("name", sorted(_OPENCV_DIHEDRAL))
def test_dihedral_image_and_matrix_against_opencv(rng, name):
    """dihedral_image equals OpenCV's flip/rotate/transpose (also on a batch), its matrix sends
    each pixel where the image moved it, and a homography conjugated by it warps (OpenCV) the
    transformed image_a onto the transformed image_b."""
    image = rng.random((5, 7)).astype(np.float32)
    want = _OPENCV_DIHEDRAL[name](image)
    np.testing.assert_array_equal(g.dihedral_image(image, name), want)
    batch = np.stack([image, 2 * image])[..., None]
    np.testing.assert_array_equal(g.dihedral_image(batch, name, axes=(1, 2))[1, ..., 0], 2 * want)
    gm = g.dihedral_matrix(name, 7, 5)
    ys, xs = np.mgrid[0:5, 0:7]
    moved = gm @ np.stack([xs.ravel(), ys.ravel(), np.ones(35)])
    np.testing.assert_array_equal(want[moved[1].astype(int), moved[0].astype(int)], image.ravel())
    # conjugation: b = a warped by H  =>  D(b) = D(a) warped by G H inv(G)
    a = cv2.GaussianBlur(rng.random((96, 128)).astype(np.float32), (0, 0), 2)
    h = g.translation(6.0, -4.0) @ np.array([[1.05, 0.04, 0], [-0.03, 0.97, 0], [2e-4, -1e-4, 1]])
    b = cv2.warpPerspective(a, h, (128, 96), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    gm = g.dihedral_matrix(name, 128, 96)
    ta, tb = (_OPENCV_DIHEDRAL[name](x) for x in (a, b))
    warped = cv2.warpPerspective(ta, gm @ h @ np.linalg.inv(gm), ta.shape[::-1],
                                 flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    np.testing.assert_allclose(warped[20:-20, 20:-20], tb[20:-20, 20:-20], atol=1e-3)
    with pytest.raises(ValueError, match="dihedral name"):
        g.dihedral_matrix("rotate_45", 7, 5)


def test_compose_equals_numpy_product(rng):
    a, b, c = _random_hs(rng, 3) * np.array([2.0, 0.5, 3.0])[:, None, None]
    ref = a @ b @ c
    np.testing.assert_allclose(g.compose(a, b, c), ref / ref[2, 2], atol=1e-12)
    np.testing.assert_allclose(g.compose(a), a / a[2, 2], atol=1e-12)
    with pytest.raises(ValueError):
        g.compose()


def test_mean_corner_error_known_values(rng):
    for t in (0.0, 1.0, 7.5):
        tx, ty = t * 0.6, t * 0.8  # |(tx, ty)| = t
        err = g.mean_corner_error(np.eye(3), g.translation(tx, ty))
        assert err == pytest.approx(t, abs=1e-12)
    # Batched: per-sample errors, and the mean over samples.
    hs_true = np.stack([g.translation(3, 4), g.translation(0, 2)])
    np.testing.assert_allclose(g.corner_errors(np.stack([np.eye(3)] * 2), hs_true), [5.0, 2.0])
    assert g.mean_corner_error(np.stack([np.eye(3)] * 2), hs_true) == pytest.approx(3.5)
    # A scaling about the origin: corners (0,0),(S,0),(S,S),(0,S) move by 0, s*S, s*S*sqrt2, s*S.
    s = 0.1
    expected = (0 + 12.8 + 12.8 * np.sqrt(2) + 12.8) / 4
    assert g.mean_corner_error(np.eye(3), g.scale_matrix(1 + s, 1 + s)) == pytest.approx(expected)


def _sampler_pairs(n):
    """``n`` pairs of the library's sampler:
    ``(h_ba [n, 3, 3], drawn corner offsets [n, 4, 2])``."""
    from stnh_tf.data import pairs
    protocol = pairs.Protocol(samples_per_image=1)
    image = np.zeros((protocol.image_height, protocol.image_width), np.uint8)
    params = [pairs.draw_params(pairs.image_rng(0, i), protocol)[0] for i in range(n)]
    hs = np.stack([pairs.make_pair(image, p, protocol)["h_ba"] for p in params])
    return hs, np.stack([p.offsets for p in params])


def _corner_convention_error(hs, offsets):
    """Largest distance (px) between ``dehom(H c)`` and ``c + offset`` over the conventions'
    corners ``c`` = (0,0), (128,0), (128,128), (0,128) (CORNERS, written out here)."""
    c = np.concatenate([CORNERS, np.ones((4, 1))], axis=1)
    mapped = np.einsum("nij,kj->nki", hs, c)
    return float(np.abs(mapped[..., :2] / mapped[..., 2:] - (CORNERS + offsets)).max())


def test_sampler_and_mace_use_the_conventions_corners():
    """The sampler's ``H_ba`` moves exactly the corners (0,0), (128,0), (128,128), (0,128) by the
    drawn offsets, and the identity's per-pair MACE is the mean length of those offsets. A corner
    convention off by one pixel in the sampler (a 127-px square) fails the first check by far more
    than its tolerance, and the second too where MACE keeps the 128-px corners: the sensitivity
    check on the same offsets shows both."""
    hs, offsets = _sampler_pairs(500)
    assert _corner_convention_error(hs, offsets) < 1e-6
    np.testing.assert_allclose(g.corner_errors(np.broadcast_to(np.eye(3), hs.shape), hs),
                               np.linalg.norm(offsets, axis=-1).mean(axis=-1), atol=1e-6)
    # Sensitivity: homographies built on a 127-px square with the same offsets.
    square127 = np.array([[0, 0], [127, 0], [127, 127], [0, 127]], np.float32)
    off_by_one = np.stack([cv2.getPerspectiveTransform(square127, square127 + o.astype(np.float32))
                           for o in offsets]).astype(np.float64)
    assert _corner_convention_error(off_by_one, offsets) > 0.1
    identity_127 = g.corner_errors(np.broadcast_to(np.eye(3), hs.shape), off_by_one)
    assert np.abs(identity_127 - np.linalg.norm(offsets, axis=-1).mean(axis=-1)).max() > 0.1


def test_identity_mace_of_the_pair_sampler_matches_its_closed_form():
    """The identity's MACE is the mean length of a corner offset drawn uniformly from the square
    [-32, 32]^2: E|d| = 32 (sqrt 2 + asinh 1) / 3 = 24.486 px. Over 4,000 pairs of the library's
    sampler (16,000 corners; sd of |d| 9.1 px, so the standard error is 0.072 px) the measured
    value must lie within 0.3 px (~4 standard errors). That catches a wrong perturbation range
    (32 px -> 31 px moves it by 0.77 px) or H applied in the wrong direction; it cannot catch a
    corner convention off by one pixel (about 0.2 px here), which
    :func:`test_sampler_and_mace_use_the_conventions_corners` checks exactly."""
    hs, _ = _sampler_pairs(4000)
    mace = g.mean_corner_error(np.broadcast_to(np.eye(3), hs.shape), hs)
    assert mace == pytest.approx(32 * (np.sqrt(2) + np.arcsinh(1)) / 3, abs=0.3)


def test_keras_path_agrees_with_numpy(rng):
    import keras
    from keras import ops

    hs = _random_hs(rng, 3)
    offsets = rng.uniform(-32, 32, size=(3, 4, 2))
    pts = rng.uniform(0, 128, size=(3, 5, 2))
    t = lambda x: ops.convert_to_tensor(x, dtype="float64")
    n = keras.ops.convert_to_numpy
    pairs = [
        (g.normalize_homography(t(hs)), g.normalize_homography(hs)),
        (g.denormalize_homography(t(hs)), g.denormalize_homography(hs)),
        (g.scale_to_unit(t(hs * 2)), g.scale_to_unit(hs * 2)),
        (g.matrix_to_vector(t(hs)), g.matrix_to_vector(hs)),
        (g.vector_to_matrix(t(hs.reshape(3, 9)[:, :8])),
         g.vector_to_matrix(hs.reshape(3, 9)[:, :8])),
        (g.as_matrix(t(hs.reshape(3, 9)[:, :8])), hs),
        (g.warp_points(t(hs), t(pts)), g.warp_points(hs, pts)),
        (g.homography_from_points(t(pts[:, :4]), t(pts[:, :4] + offsets)),
         g.homography_from_points(pts[:, :4], pts[:, :4] + offsets)),
        (g.offsets_to_homography(t(offsets)), g.offsets_to_homography(offsets)),
        (g.offsets_to_homography(t(offsets.reshape(3, 8))), g.offsets_to_homography(offsets)),
        (g.homography_to_offsets(t(hs)), g.homography_to_offsets(hs)),
        (g.compose(t(hs[0]), t(hs[1]), t(hs[2])), g.compose(hs[0], hs[1], hs[2])),
        (g.corner_errors(t(hs), t(hs[::-1])), g.corner_errors(hs, hs[::-1])),
        (g.mean_corner_error(t(hs), t(hs[::-1])), g.mean_corner_error(hs, hs[::-1])),
    ]
    for i, (k, ref) in enumerate(pairs):
        assert not isinstance(k, np.ndarray), i  # really went through keras.ops
        np.testing.assert_allclose(n(k), ref, rtol=1e-9, atol=1e-9, err_msg=f"pair {i}")
    # float32 tensors keep float32 and agree to float32 precision.
    k32 = g.normalize_homography(ops.convert_to_tensor(hs, dtype="float32"))
    assert keras.backend.standardize_dtype(k32.dtype) == "float32"
    np.testing.assert_allclose(n(k32), g.normalize_homography(hs), rtol=1e-4, atol=1e-5)


def test_keras_path_inside_tf_function(rng):
    import tensorflow as tf

    hs = _random_hs(rng, 2).astype(np.float32)

    @tf.function
    def f(h):
        return g.mean_corner_error(h, g.compose(h, g.translation(1.0, 0.0).astype(np.float32)))

    assert float(f(tf.constant(hs))) == pytest.approx(
        g.mean_corner_error(hs.astype(np.float64), g.compose(hs, g.translation(1.0, 0.0))),
        rel=1e-4)


@pytest.mark.parametrize("fn, arg", [
    (g.normalize_homography, np.zeros((2, 3, 4))),
    (g.denormalize_homography, np.zeros((3,))),
    (g.scale_to_unit, np.zeros((2, 2))),
    (g.vector_to_matrix, np.zeros((2, 7))),
    (g.matrix_to_vector, np.zeros((4, 4))),
    (g.as_matrix, np.zeros((2, 9))),
    (g.offsets_to_homography, np.zeros((2, 3, 2))),
    (g.homography_to_offsets, np.zeros((2, 8))),
])
def test_bad_shapes_raise_value_error_with_shape(fn, arg):
    with pytest.raises(ValueError, match=str(arg.shape).replace("(", r"\(").replace(")", r"\)")):
        fn(arg)


def test_bad_point_shapes_raise():
    with pytest.raises(ValueError, match=r"\(5, 3\)"):
        g.warp_points(np.eye(3), np.zeros((5, 3)))
    with pytest.raises(ValueError, match=r"\(3, 2\)"):
        g.homography_from_points(np.zeros((3, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"\(2, 2, 3\)"):
        g.corner_errors(np.zeros((2, 2, 3)), np.eye(3))


def test_numpy_path_does_not_import_tensorflow():
    code = ("import sys, numpy as np, stnh_tf, stnh_tf.geometry as g; "
            "h = g.offsets_to_homography(np.ones((2, 4, 2))); "
            "g.mean_corner_error(g.normalize_homography(h), h); g.compose(h, h); "
            "g.warp_points(h, g.patch_corners()); "
            "bad = [m for m in ('tensorflow', 'keras', 'jax', 'torch') if m in sys.modules]; "
            "assert not bad, bad")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
