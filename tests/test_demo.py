"""The demo (the README's main job) and the figure helpers."""

import json
import os

import numpy as np
import pytest

from conftest import paper_homography, photo_pairs
from stnh_tf.paper import figures


def test_quadrilateral_is_h_applied_to_the_corners(rng):
    h = paper_homography(rng)
    q = figures.quadrilateral(h, offset=32)
    assert q.shape == (5, 2)
    np.testing.assert_allclose(q[0], q[-1])
    c = np.array([[0, 0, 1], [128, 0, 1], [128, 128, 1], [0, 128, 1]], np.float64) @ h.T
    np.testing.assert_allclose(q[:4], c[:, :2] / c[:, 2:] + 32, atol=1e-9)


def test_figures_write_pngs(tmp_path, rng):
    n = 3
    ctx = rng.integers(0, 256, (n, 192, 192), dtype=np.uint8)
    pb = rng.integers(0, 256, (n, 128, 128, 1), dtype=np.uint8)
    h_true = np.stack([paper_homography(rng) for _ in range(n)])
    png = figures.prediction_examples(ctx, pb, h_true, h_true, str(tmp_path / "f5.png"))
    bars = figures.mace_bars({"identity": 24.6, "ours": 5.0}, str(tmp_path / "f4.png"),
                             paper={"ours": 5.83})
    for p in (png, bars):
        with open(p, "rb") as f:
            assert f.read(8) == b"\x89PNG\r\n\x1a\n"
        assert os.path.getsize(p) > 5000


def test_image_b_window_is_image_b_around_the_square(rng):
    """Re-made from the context, the window's centre is patch_b (up to uint8 rounding), and with
    the identity it is the context itself; a stored patch_b replaces the centre exactly."""
    pairs = photo_pairs(rng, 4)
    for ctx, h, pb in zip(pairs["context"], pairs["h_ba"], pairs["patch_b"]):
        window = figures.image_b_window(ctx, h)
        assert window.shape == (192, 192) and window.dtype == np.uint8
        diff = np.abs(window[32:160, 32:160].astype(int) - pb.astype(int))
        assert diff.mean() < 0.6 and diff.max() <= 1
        np.testing.assert_array_equal(figures.image_b_window(ctx, h, pb)[32:160, 32:160], pb)
        np.testing.assert_array_equal(
            figures.image_b_window(ctx, h, pb[..., None] / 255.0)[32:160, 32:160], pb)
    np.testing.assert_array_equal(figures.image_b_window(pairs["context"][0], np.eye(3)),
                                  pairs["context"][0])


def test_fig5_draws_truth_in_both_images_and_the_prediction_in_image_a(rng):
    """The paper's Fig. 5: green boxes (truth) in image_a and image_b, red (prediction) in
    image_a."""
    from matplotlib import colors

    n = 2
    ctx = rng.integers(0, 256, (n, 192, 192), dtype=np.uint8)
    pb = rng.integers(0, 256, (n, 128, 128), dtype=np.uint8)
    h_true = np.stack([paper_homography(rng) for _ in range(n)])
    h_pred = np.stack([paper_homography(rng) for _ in range(n)])
    fig = figures.prediction_figure(ctx, pb, h_true, h_pred)
    try:
        axes = np.array(fig.axes).reshape(2, n)
        for i in range(n):
            top = {colors.to_hex(l.get_color()): l.get_xydata() for l in axes[0, i].lines}
            bottom = {colors.to_hex(l.get_color()): l.get_xydata() for l in axes[1, i].lines}
            assert set(top) == {"#00ff00", "#ff0000"} and set(bottom) == {"#00ff00"}
            np.testing.assert_allclose(top["#00ff00"], figures.quadrilateral(h_true[i], 32))
            np.testing.assert_allclose(top["#ff0000"], figures.quadrilateral(h_pred[i], 32))
            square = np.array([[0, 0], [128, 0], [128, 128], [0, 128], [0, 0]]) + 32.0
            np.testing.assert_allclose(bottom["#00ff00"], square)
            assert "image_a" in axes[0, i].get_title() and axes[1, i].get_title() == "image_b"
    finally:
        import matplotlib.pyplot as plt
        plt.close(fig)


def test_demo_self_check_passes_and_measures_the_stn_against_opencv():
    """The demo's first line: the conventions against OpenCV, on 8 paper-protocol warps."""
    from stnh_tf.paper import demo

    check = demo.self_check(seed=0)
    assert check["ok"] is True
    assert check["normalize_max_abs_error"] < 1e-9
    assert check["four_point_round_trip_max_abs_error"] < 1e-4
    assert 0 < check["stn_vs_opencv_mean_abs_gray_levels"] < 0.5


def _shipped_names() -> set:
    """The demo's names for the shipped weights, from the stage files each folder holds (a folder
    gains a row when a stage lands, e.g. the paper's schedule's stage 3)."""
    import glob

    import stnh_tf

    weights = os.path.join(os.path.dirname(stnh_tf.__file__), "weights")
    names = set()
    for label, folder in (("shipped default", weights),
                          ("paper recipe", os.path.join(weights, "paper_recipe")),
                          ("paper's schedule", os.path.join(weights, "paper_schedule"))):
        n = len(glob.glob(os.path.join(folder, "stage[0-9]*.keras")))
        if n:
            names.add(f"{label}, 1 stage")
        if n > 1:
            names.add(f"{label}, {n} stages")
    return names


SHIPPED = _shipped_names()


@pytest.mark.slow
def test_demo_runs_offline(tmp_path):
    from stnh_tf.paper import demo

    lines = []
    result = demo.run_demo(str(tmp_path / "out"), seed=0, samples_per_image=1, examples=2,
                           printer=lines.append)
    assert result["conventions"]["ok"]
    methods = result["methods"]
    assert {"Identity", "ORB + RANSAC", "SIFT + RANSAC"} <= set(methods)
    # Identity on the paper's protocol: 24.49 px in expectation (corners moved uniformly in
    # [-32, 32]).
    assert 18 < methods["Identity"]["mace"] < 31
    for name, r in methods.items():
        assert np.isfinite(r["mace"]) and r["ms_per_pair"] >= 0
    # The package ships three sets of weights (stnh_tf/weights, its paper_recipe and
    # paper_schedule): each is evaluated, beats the identity, and the best of them is drawn.
    shipped = demo.shipped_models()
    assert set(shipped) == SHIPPED
    assert {"shipped default, 3 stages", "paper recipe, 3 stages",
            "paper's schedule, 3 stages"} <= SHIPPED
    assert set(methods) == {"Identity", "ORB + RANSAC", "SIFT + RANSAC"} | SHIPPED
    for name in shipped:
        assert methods[name]["mace"] < methods["Identity"]["mace"]
    with open(result["figure"], "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    saved = json.loads((tmp_path / "out" / "results.json").read_text())
    assert saved["num_pairs"] == result["num_pairs"] > 0
    assert any("MACE" in l for l in lines)
