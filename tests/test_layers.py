"""Tests of the SpatialTransformer and HomographyMerge layers (OpenCV reference, finite
differences)."""

import cv2
import keras
import numpy as np
import pytest
import tensorflow as tf

from conftest import cv2_warp, inside_mask, keras_policy, norm_matrix, paper_homography, to_bar
from stnh_tf.modeling.layers import HomographyMerge, SpatialTransformer

TOL = 0.5  # mean absolute difference, gray levels of 255


def _stn(images, h, **kwargs):
    return keras.ops.convert_to_numpy(SpatialTransformer(**kwargs)([images, h]))


def _from_bar(h_bar):
    m = norm_matrix()
    return np.linalg.inv(m) @ h_bar @ m


def _assert_matches_cv2(out, patch, h_bar):
    """out [h, w] or [h, w, C] vs OpenCV warp of patch with inv(M) @ H_bar @ M."""
    h_pix = _from_bar(h_bar)
    ref = cv2_warp(patch, h_pix)
    mask = inside_mask(h_pix)
    assert mask.mean() > 0.3  # the comparison covers most of the patch
    diff = np.abs(out.astype(np.float64) - ref)[mask]
    assert diff.mean() < TOL, diff.mean()
    assert diff.max() < 4.0, diff.max()
    return diff.mean()


# --------------------------------------------------------------------------------------------
# Against OpenCV
# --------------------------------------------------------------------------------------------
def test_stn_matches_opencv_batched_photographs(photo_patches, rng):
    patches = list(photo_patches.values())
    bars = []
    for _ in range(3):  # three homographies per photograph, all in one batched call
        bars += [to_bar(paper_homography(rng)) for _ in patches]
    imgs = np.stack(patches * 3)[..., None]
    h8 = np.stack(bars).reshape(-1, 9)[:, :8].astype(np.float32)
    out = _stn(imgs, h8)
    assert out.shape == imgs.shape and out.dtype == np.float32
    for i in range(len(bars)):
        _assert_matches_cv2(out[i, ..., 0], imgs[i, ..., 0], bars[i])
    # Each sample uses its own homography: sample 0 differs from the warp with sample 1's H.
    wrong = cv2_warp(imgs[0, ..., 0], _from_bar(bars[1]))
    assert np.abs(out[0, ..., 0] - wrong)[inside_mask(_from_bar(bars[0]))].mean() > 5.0


def test_stn_reflect_fill_matches_opencv_reflect_101(photo_patches, rng):
    """fill="reflect" samples the patch mirrored about its border pixels, as OpenCV's
    BORDER_REFLECT_101 does, everywhere (also far outside); the zero fill differs there."""
    patches = list(photo_patches.values())
    bars = [to_bar(paper_homography(rng)) for _ in patches]
    bars.append(to_bar(np.array([[1.6, 0.2, -90.0], [-0.1, 1.5, -70.0], [0.0, 0.0, 1.0]])))
    patches.append(patches[0])  # a zoom out: much of the output lies beyond the patch
    imgs = np.stack(patches)[..., None]
    out = _stn(imgs, np.stack(bars).astype(np.float32), fill="reflect")
    for i, h_bar in enumerate(bars):
        h_pix = _from_bar(h_bar)
        ref = cv2_warp(imgs[i, ..., 0], h_pix, cv2.BORDER_REFLECT_101)
        outside = ~inside_mask(h_pix)
        assert outside.mean() > 0.02
        diff = np.abs(out[i, ..., 0].astype(np.float64) - ref)
        assert diff.mean() < TOL and diff.max() < 4.0, (diff.mean(), diff.max())
        assert np.abs(cv2_warp(imgs[i, ..., 0], h_pix) - ref)[outside].mean() > 10.0
    assert SpatialTransformer(fill="reflect").get_config()["fill"] == "reflect"
    with pytest.raises(ValueError, match="fill must be one of"):
        SpatialTransformer(fill="edge")


def test_stn_single_sample_and_matrix_input(photo_patches, rng):
    patch = photo_patches["camera"]
    h_bar = to_bar(paper_homography(rng))
    out8 = _stn(patch[None, ..., None], h_bar.reshape(9)[None, :8].astype(np.float32))
    _assert_matches_cv2(out8[0, ..., 0], patch, h_bar)
    # [B, 3, 3] input; a homography is defined up to scale, so a scaled matrix warps the same way.
    out33 = _stn(patch[None, ..., None], h_bar[None].astype(np.float32))
    np.testing.assert_allclose(out33, out8, atol=1e-3)
    out_scaled = _stn(patch[None, ..., None], (2.5 * h_bar)[None].astype(np.float32))
    np.testing.assert_allclose(out_scaled, out8, atol=1e-2)


def test_stn_matches_opencv_color(color_patch, rng):
    h_bars = [to_bar(paper_homography(rng)) for _ in range(2)]
    out = _stn(np.stack([color_patch] * 2), np.stack(h_bars).astype(np.float32))
    assert out.shape == (2, 128, 128, 3)
    for i in range(2):
        _assert_matches_cv2(out[i], color_patch, h_bars[i])
        # Channels are not mixed up.
        for c in range(3):
            _assert_matches_cv2(out[i, ..., c], color_patch[..., c], h_bars[i])


def test_stn_non_square_image(rng):
    """M is built from the image's own w and h."""
    img = cv2.cvtColor(cv2.resize(__import__("skimage").data.coffee(), (160, 96)),
                       cv2.COLOR_RGB2GRAY).astype(np.float32)
    h_pix = np.array([[1.05, 0.02, -3.0], [-0.03, 0.97, 2.0], [1e-4, -2e-4, 1.0]])
    m = norm_matrix(160, 96)
    h_bar = m @ h_pix @ np.linalg.inv(m)
    out = _stn(img[None, ..., None], (h_bar / h_bar[2, 2])[None].astype(np.float32))[0, ..., 0]
    ref = cv2_warp(img, h_pix)
    mask = inside_mask(h_pix, 96, 160)
    assert np.abs(out - ref)[mask].mean() < TOL


def test_identity_and_one_pixel_translation(photo_patches):
    patch = photo_patches["astronaut"][None, ..., None]
    ident = np.array([[1, 0, 0, 0, 1, 0, 0, 0]], np.float32)
    np.testing.assert_allclose(_stn(patch, ident), patch, atol=1e-5)
    # H_ba = translation by +1 px in x: out(x, y) = in(x + 1, y), last column zero.
    h_bar = to_bar(np.array([[1.0, 0, 1], [0, 1, 0], [0, 0, 1]]))
    out = _stn(patch, h_bar[None].astype(np.float32))[0, ..., 0]
    np.testing.assert_allclose(out[:, :-1], patch[0, :, 1:, 0], atol=1e-4)
    np.testing.assert_array_equal(out[:, -1], 0.0)
    # And one row down: out(x, y) = in(x, y + 1), last row zero.
    h_bar = to_bar(np.array([[1.0, 0, 0], [0, 1, 1], [0, 0, 1]]))
    out = _stn(patch, h_bar[None].astype(np.float32))[0, ..., 0]
    np.testing.assert_allclose(out[:-1], patch[0, 1:, :, 0], atol=1e-4)
    np.testing.assert_array_equal(out[-1], 0.0)


def test_half_pixel_translation_is_bilinear():
    img = np.arange(16, dtype=np.float32).reshape(1, 4, 4, 1) * 10
    h_bar = to_bar(np.array([[1.0, 0, 0.5], [0, 1, 0.25], [0, 0, 1]]), size=4)
    out = _stn(img, h_bar[None].astype(np.float32))[0, ..., 0]
    # Interior: linear image => exact; at x + 0.5 > 3 the right neighbour is zero (BORDER_CONSTANT).
    np.testing.assert_allclose(out[:3, :3], img[0, :3, :3, 0] + 5.0 + 10.0, atol=1e-4)
    ref = cv2_warp(img[0, ..., 0], _from_bar_size(h_bar, 4))
    np.testing.assert_allclose(out, ref, atol=0.2)


def _from_bar_size(h_bar, size):
    m = norm_matrix(size, size)
    return np.linalg.inv(m) @ h_bar @ m


def test_stn_inside_tf_function_with_unknown_batch(photo_patches, rng):
    layer = SpatialTransformer()
    f = tf.function(lambda i, h: layer([i, h]),
                    input_signature=[tf.TensorSpec([None, 128, 128, 1]), tf.TensorSpec([None, 8])])
    patch = photo_patches["coffee"]
    h_bar = to_bar(paper_homography(rng))
    out = f(patch[None, ..., None], h_bar.reshape(9)[None, :8].astype(np.float32)).numpy()
    _assert_matches_cv2(out[0, ..., 0], patch, h_bar)


# --------------------------------------------------------------------------------------------
# Gradients (float64, central differences)
# --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def smooth_setup(photo_patches):
    rng = np.random.default_rng(7)
    img = cv2.GaussianBlur(photo_patches["camera"].astype(np.float64), (0, 0), 3.0) / 255.0
    h_bar = to_bar(paper_homography(rng)).reshape(9)[:8]
    weights = rng.normal(size=(1, 128, 128, 1))
    return img[None, ..., None], h_bar[None], weights


def test_gradient_wrt_homography_matches_finite_differences(smooth_setup):
    img, h8, w = smooth_setup
    layer = SpatialTransformer(dtype="float64")
    img_t, w_t = tf.constant(img), tf.constant(w)

    def f(h):
        return tf.reduce_sum(layer([img_t, h]) * w_t)

    h = tf.Variable(h8)
    with tf.GradientTape() as tape:
        y = f(h)
    grad = tape.gradient(y, h).numpy()[0]
    assert grad.dtype == np.float64
    eps = 1e-6
    fd = np.zeros(8)
    for i in range(8):
        e = np.zeros((1, 8))
        e[0, i] = eps
        fd[i] = (f(tf.constant(h8 + e)).numpy() - f(tf.constant(h8 - e)).numpy()) / (2 * eps)
    rel = np.abs(grad - fd) / np.maximum(np.abs(fd), 1e-12)
    assert np.all(np.abs(fd) > 1e-3)  # every entry has a real effect
    assert np.all(rel < 1e-3), (grad, fd, rel)


def test_gradient_wrt_image_matches_finite_differences(smooth_setup):
    img, h8, w = smooth_setup
    layer = SpatialTransformer(dtype="float64")
    h_t, w_t = tf.constant(h8), tf.constant(w)

    def f(i):
        return tf.reduce_sum(layer([i, h_t]) * w_t)

    x = tf.Variable(img)
    with tf.GradientTape() as tape:
        y = f(x)
    grad = tape.gradient(y, x).numpy()
    assert np.count_nonzero(grad) > 0.3 * grad.size
    # f is linear in the image: central differences are exact up to rounding.
    for (r, c) in [(64, 64), (30, 90), (100, 20), (5, 5)]:
        e = np.zeros_like(img)
        e[0, r, c, 0] = 1e-3
        fd = (f(tf.constant(img + e)).numpy() - f(tf.constant(img - e)).numpy()) / 2e-3
        assert grad[0, r, c, 0] == pytest.approx(fd, rel=1e-6, abs=1e-9)
    assert np.abs(grad[0, 64, 64, 0]) > 0


# --------------------------------------------------------------------------------------------
# HomographyMerge
# --------------------------------------------------------------------------------------------
def test_merge_equals_numpy_product(rng):
    prev = np.stack([to_bar(paper_homography(rng)) for _ in range(5)])
    res = np.stack([to_bar(paper_homography(rng)) for _ in range(5)])
    ref = prev @ res
    ref = ref / ref[:, 2:3, 2:3]
    v = lambda h: h.reshape(-1, 9)[:, :8]
    out8 = keras.ops.convert_to_numpy(HomographyMerge()([v(prev), v(res)]))
    assert out8.shape == (5, 8)
    np.testing.assert_allclose(out8, v(ref), rtol=1e-5, atol=1e-5)
    out33 = keras.ops.convert_to_numpy(HomographyMerge(output_matrix=True)([v(prev), v(res)]))
    assert out33.shape == (5, 3, 3)
    np.testing.assert_allclose(out33, ref, rtol=1e-5, atol=1e-5)
    # [B, 3, 3] inputs with arbitrary scale.
    out_m = keras.ops.convert_to_numpy(HomographyMerge()([3.0 * prev, 0.5 * res]))
    np.testing.assert_allclose(out_m, v(ref), rtol=1e-5, atol=1e-5)
    # Order matters: H_prev @ H_res, not H_res @ H_prev.
    swapped = res @ prev
    assert np.abs(v(swapped / swapped[:, 2:3, 2:3]) - out8).max() > 1e-3
    # Warping with the merged H equals warping by H_prev then by H_res (pixel frame, OpenCV).
    m = norm_matrix()
    pix = lambda hb: np.linalg.inv(m) @ hb @ m
    pts = rng.uniform(0, 128, size=(1, 6, 2))
    via_merge = cv2.perspectiveTransform(pts, pix(out33[0]).astype(np.float64))
    via_two = cv2.perspectiveTransform(cv2.perspectiveTransform(pts, pix(res[0])), pix(prev[0]))
    np.testing.assert_allclose(via_merge, via_two, atol=1e-2)


def test_merge_gradient_flows_to_both_inputs(rng):
    prev = tf.Variable(np.stack([to_bar(paper_homography(rng)).reshape(9)[:8] for _ in range(3)]))
    res = tf.Variable(np.stack([to_bar(paper_homography(rng)).reshape(9)[:8] for _ in range(3)]))
    layer = HomographyMerge(dtype="float64")
    w = tf.constant(rng.normal(size=(3, 8)))

    def f(a, b):
        return tf.reduce_sum(layer([a, b]) * w)

    with tf.GradientTape() as tape:
        y = f(prev, res)
    g_prev, g_res = tape.gradient(y, [prev, res])
    assert g_prev is not None and g_res is not None
    assert np.all(np.abs(g_prev.numpy()).sum(-1) > 0) and np.all(np.abs(g_res.numpy()).sum(-1) > 0)
    eps = 1e-6
    for var, grad in ((prev, g_prev.numpy()), (res, g_res.numpy())):
        base = var.numpy()
        for (b, i) in [(0, 0), (1, 5), (2, 7)]:
            e = np.zeros_like(base)
            e[b, i] = eps
            var.assign(base + e)
            fp = f(prev, res).numpy()
            var.assign(base - e)
            fm = f(prev, res).numpy()
            var.assign(base)
            assert grad[b, i] == pytest.approx((fp - fm) / (2 * eps), rel=1e-5, abs=1e-8)


# --------------------------------------------------------------------------------------------
# Serialization
# --------------------------------------------------------------------------------------------
def test_save_load_round_trip(tmp_path, photo_patches, rng):
    image = keras.Input((128, 128, 1), name="image")
    h = keras.Input((8,), name="h")
    h2 = keras.Input((8,), name="h2")
    merged = HomographyMerge(name="merge")([h, h2])
    merged_m = HomographyMerge(output_matrix=True, name="merge_m")([h, h2])
    warped = SpatialTransformer(fill="reflect", name="stn")([image, merged])
    model = keras.Model([image, h, h2], [warped, merged_m])
    path = tmp_path / "m.keras"
    model.save(path)
    loaded = keras.models.load_model(path)
    assert isinstance(loaded.get_layer("stn"), SpatialTransformer)
    assert loaded.get_layer("stn").fill == "reflect"
    assert isinstance(loaded.get_layer("merge"), HomographyMerge)
    assert loaded.get_layer("merge_m").output_matrix is True
    assert loaded.get_layer("merge").output_matrix is False
    x = [np.stack([photo_patches["camera"], photo_patches["coffee"]])[..., None],
         np.stack([to_bar(paper_homography(rng)).reshape(9)[:8]
                   for _ in range(2)]).astype(np.float32),
         np.stack([to_bar(paper_homography(rng)).reshape(9)[:8]
                   for _ in range(2)]).astype(np.float32)]
    a, b = model.predict(x, verbose=0), loaded.predict(x, verbose=0)
    for u, v in zip(a, b):
        np.testing.assert_array_equal(u, v)
    assert np.abs(a[0]).sum() > 0


# --------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("img_shape, h_shape, shown", [
    ((128, 128, 1), (1, 8), r"\(128, 128, 1\)"),
    ((1, 128, 128, 1), (1, 7), r"\(1, 7\)"),
    ((1, 128, 128, 1), (1, 3, 4), r"\(1, 3, 4\)"),
    ((1, 128, 128, 1), (8,), r"\(8,\)"),
    ((2, 128, 128, 1), (3, 8), r"\(2, 128, 128, 1\)"),
])
def test_stn_bad_shapes_raise(img_shape, h_shape, shown):
    with pytest.raises(ValueError, match=shown):
        SpatialTransformer()([np.zeros(img_shape, np.float32), np.zeros(h_shape, np.float32)])


def test_stn_bad_call_structure_raises():
    with pytest.raises(ValueError):
        SpatialTransformer()(np.zeros((1, 8, 8, 1), np.float32))


@pytest.mark.parametrize("shape", [(2, 7), (2, 3, 4), (8,)])
def test_merge_bad_shapes_raise(shape):
    with pytest.raises(ValueError, match=str(shape).replace("(", r"\(").replace(")", r"\)")):
        HomographyMerge()([np.zeros(shape, np.float32), np.zeros((2, 8), np.float32)])


# --------------------------------------------------------------------------------------------
# Mixed precision
# --------------------------------------------------------------------------------------------
@pytest.fixture
def mixed_bfloat16():
    with keras_policy("mixed_bfloat16"):
        yield


def test_stn_mixed_bfloat16_matches_opencv(mixed_bfloat16, photo_patches, rng):
    layer = SpatialTransformer()
    assert layer.compute_dtype == "bfloat16"
    patches = list(photo_patches.values())
    bars = [to_bar(paper_homography(rng)) for _ in patches]
    # The image arrives in bfloat16 (as from a mixed-precision model); the homography in float32.
    imgs = tf.cast(np.stack(patches)[..., None], tf.bfloat16)
    out = layer([imgs, np.stack(bars).astype(np.float32)])
    assert keras.backend.standardize_dtype(out.dtype) == "bfloat16"
    out = keras.ops.convert_to_numpy(keras.ops.cast(out, "float32"))
    src = keras.ops.convert_to_numpy(keras.ops.cast(imgs, "float32"))
    for i in range(len(bars)):
        _assert_matches_cv2(out[i, ..., 0], src[i, ..., 0], bars[i])


def test_merge_mixed_bfloat16_keeps_float32(mixed_bfloat16, rng):
    prev = np.stack([to_bar(paper_homography(rng)) for _ in range(4)]).astype(np.float32)
    res = np.stack([to_bar(paper_homography(rng)) for _ in range(4)]).astype(np.float32)
    out = HomographyMerge(output_matrix=True)([prev, res])
    ref = prev.astype(np.float64) @ res
    np.testing.assert_allclose(keras.ops.convert_to_numpy(out), ref / ref[:, 2:3, 2:3], atol=1e-5)


def test_keras_policy_is_restored_after_its_block():
    """conftest's keras_policy (the mixed-precision tests' fixture) leaves the global policy
    float32 after its block, also when the block raises, so later tests build float32 layers."""
    assert keras.mixed_precision.global_policy().name == "float32"
    with keras_policy("mixed_bfloat16"):
        assert SpatialTransformer().compute_dtype == "bfloat16"
    assert keras.mixed_precision.global_policy().name == "float32"
    with pytest.raises(RuntimeError, match="inside"):
        with keras_policy("mixed_bfloat16"):
            raise RuntimeError("inside")
    assert keras.mixed_precision.global_policy().name == "float32"
    assert SpatialTransformer().compute_dtype == "float32"


# --------------------------------------------------------------------------------------------
# Benchmark binary smoke test (subprocess: its absl flags must not clash with other binaries')
# --------------------------------------------------------------------------------------------
@pytest.mark.slow  # (a binary end to end, 6-15 s; make test-all)
def test_benchmark_binary_smoke(tmp_path):
    """The benchmark's inputs are paper-protocol homographies at its size (H_bar recomputed here
    with the paper's M), its reported difference from OpenCV is the one computed here from those
    inputs (the layer against conftest's OpenCV warp, every pixel), and its speed-ups are the
    ratios of its timings."""
    import json
    import os
    import subprocess
    import sys

    from stnh_tf.evaluation import benchmarks

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    out = tmp_path / "bench.json"
    res = subprocess.run(
        [sys.executable, "-m", "experiments.benchmark_layers", "--batch_size=2", "--size=32",
         "--iterations=1", "--warmup=0", "--compare_jit", f"--json_out={out}"],
        cwd=root, capture_output=True, text=True, timeout=180)
    assert res.returncode == 0, res.stderr[-3000:]
    result = json.loads(out.read_text())
    assert (result["batch_size"], result["size"], result["iterations"], result["seed"]) == (
        2, 32, 1, 0)
    images, h_bar, h_pix = benchmarks.stn_inputs(2, 32, 0)
    assert images.shape == (2, 32, 32, 1) and images.max() > 100  # photograph patches, 0..255
    for h, hb in zip(h_pix, h_bar):
        np.testing.assert_allclose(hb, to_bar(h, 32).ravel()[:8], atol=1e-6)
        moved = cv2.perspectiveTransform(np.array([[[0, 0], [32, 0], [32, 32], [0, 32]]],
                                                  np.float64), h)[0]
        assert np.abs(moved - [[0, 0], [32, 0], [32, 32], [0, 32]]).max() <= 8.0  # rho = 32 / 4
    warped = _stn(images, h_bar)
    ref = np.stack([cv2_warp(images[i, ..., 0], h_pix[i]) for i in range(2)])
    diff = float(np.abs(warped[..., 0] - ref).mean())
    wrong = float(np.abs(warped[..., 0] - np.stack([cv2_warp(images[i, ..., 0],
                                                             np.linalg.inv(h_pix[i]))
                                                    for i in range(2)])).mean())
    assert diff < 0.5 and wrong > 20 * diff  # the reported number tells the direction apart
    assert set(result["stn"]) == {"no_jit", "jit"}
    for key, r in result["stn"].items():
        # the same warp in a tf.function: measured equal without XLA, 1.5e-8 apart with it
        assert r["mean_abs_diff_vs_cv2_all_pixels"] == pytest.approx(diff, abs=1e-5), key
        assert r["forward_ms"] > 0 and r["forward_backward_ms"] > 0
    nj, j = result["stn"]["no_jit"], result["stn"]["jit"]
    assert result["jit_speedup"] == pytest.approx(
        {"forward": nj["forward_ms"] / j["forward_ms"],
         "forward_backward": nj["forward_backward_ms"] / j["forward_backward_ms"]})
    assert result["machine"]["cpu_count"] == os.cpu_count() and result["cv2_loop_forward_ms"] > 0


def test_degenerate_homography_gives_finite_output_and_gradient(photo_patches):
    """A homography sending points to infinity (w = 0 on a line through the patch) or NaN must
    not poison a training batch: samples out there are zero, gradients finite."""
    patch = photo_patches["camera"][None, ..., None]
    h_pix = np.array([[1.0, 0, 0], [0, 1, 0], [-1.0 / 100, 0, 1]])  # w = 0 on the column x = 100
    h_bar = tf.Variable(to_bar(h_pix)[None].astype(np.float32))
    layer = SpatialTransformer()
    with tf.GradientTape() as tape:
        out = layer([patch, h_bar])
        loss = tf.reduce_sum(out)
    grad = tape.gradient(loss, h_bar).numpy()
    out = out.numpy()
    assert np.all(np.isfinite(out)) and np.all(np.isfinite(grad))
    # Columns x >= 101 map to negative coordinates (outside) and sample zero, as in OpenCV.
    ref = cv2_warp(patch[0, ..., 0], h_pix)
    np.testing.assert_array_equal(out[0, :, 101:, 0], 0.0)
    np.testing.assert_array_equal(ref[:, 101:], 0.0)
    assert np.abs(out[0, :, :90, 0] - ref[:, :90]).mean() < 0.5
    nan_out = layer([patch, np.full((1, 8), np.nan, np.float32)]).numpy()
    np.testing.assert_array_equal(nan_out, 0.0)


@pytest.mark.parametrize("name", ("stnh_tf.modeling.losses", "stnh_tf.modeling.layers",
                                  "stnh_tf.inference.shipped_weights", "stnh_tf.paper.tables"))
def test_doctests_of_modules_with_a_backend(name):
    """The examples in the docstrings of modules that need Keras (test_layout runs those that
    need no backend): a test audit found them never run, and PatchStandardization's stale."""
    import doctest
    import importlib

    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0, f"{name} has no doctest"
    assert result.failed == 0, f"{result.failed} of {name}'s doctests failed"


def test_warp_validity_leaves_out_points_behind_the_horizon():
    """A predicted H whose horizon crosses the patch (w < 0 beyond x = 50 here): the warp, as
    OpenCV's, samples those points where the division by their negative w puts them, and
    WarpValidity marked 113 of them valid, so the photometric loss of unlabeled pairs scored
    them. Now 1 exactly where the point lies inside the input on the output centre's side of
    the horizon (a NumPy reference), for the homography and for it scaled by -2 (the same
    projective map)."""
    from stnh_tf.modeling.layers import WarpValidity

    size = 64
    h_pix = np.array([[-1.0, 0.0, 54.0], [0.0, -1.0, 0.0], [-0.02, 0.0, 1.0]])
    ys, xs = np.mgrid[0:size, 0:size]
    q = h_pix @ np.stack([xs.ravel(), ys.ravel(), np.ones(size * size)])
    centre_w = (h_pix @ [(size - 1) / 2, (size - 1) / 2, 1.0])[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = q[0] / q[2], q[1] / q[2]
    want = ((x >= 0) & (x <= size - 1) & (y >= 0) & (y <= size - 1) & (q[2] * centre_w > 0))
    assert ((q[2] < 0) & (x >= 0) & (x <= size - 1) & (y >= 0) & (y <= size - 1)).sum() > 100
    m = norm_matrix(size, size)
    for scale in (1.0, -2.0):
        h_bar = m @ (scale * h_pix) @ np.linalg.inv(m)
        mask = keras.ops.convert_to_numpy(WarpValidity()([
            np.zeros((1, size, size, 1), "float32"), h_bar[None].astype("float32")]))
        assert np.array_equal(mask[0, ..., 0].ravel() > 0, want), scale


def test_merge_of_a_product_sending_the_centre_to_infinity_stays_finite():
    """A product whose [2, 2] is 0 (the patch centre sent to infinity) made the merged H, the
    loss and every gradient of the batch NaN: the merge divides by a safe denominator, as the
    warp does, so one degenerate pair leaves the others' gradients finite; elsewhere the merge
    is the NumPy product scaled to [2, 2] = 1, as before."""
    h_prev = np.array([[1.0, 0.1, 0.2], [0.0, 1.0, 0.1], [0.3, 0.2, 1.0]])
    degenerate = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.1, 0.1, 0.0]])
    degenerate[2] -= (h_prev @ degenerate)[2, 2] * np.linalg.inv(h_prev)[2]  # [2, 2] -> 0
    ordinary = np.array([[1.02, 0.01, 0.03], [-0.01, 0.98, 0.02], [0.01, -0.02, 1.0]])
    assert abs((h_prev @ degenerate)[2, 2]) < 1e-12
    a = tf.constant(np.stack([h_prev, h_prev]).astype("float32"))
    b = tf.Variable(np.stack([degenerate, ordinary]).astype("float32"))
    with tf.GradientTape() as tape:
        merged = HomographyMerge(output_matrix=True)([a, b])
        loss = tf.reduce_sum(tf.square(merged))
    grad = tape.gradient(loss, b).numpy()
    assert np.isfinite(merged.numpy()).all() and np.isfinite(grad).all()
    want = h_prev @ ordinary
    np.testing.assert_allclose(merged.numpy()[1], want / want[2, 2], rtol=1e-6, atol=1e-6)
