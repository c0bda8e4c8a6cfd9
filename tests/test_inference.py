"""Tests of HomographyEstimator, the SavedModel export and the predict/export binaries.

References are computed here with NumPy/OpenCV (conftest's ``norm_matrix``, ``cv2_warp``), from
the Keras models called directly; models are fresh builds whose weights are perturbed so that
their output depends on the input (a lost weight would change the numbers), or models whose
last layer is set so that they output a chosen ``H_bar`` (conftest's narrow network: their
width does not reach the output).
"""

import json
import os
import re
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import cv2
import keras
import numpy as np
import pytest
import skimage.data

from conftest import (constant_stage, cv2_warp, inside_mask, keras_policy, ncc_reference,
                      norm_matrix, paper_homography, to_bar)
from stnh_tf import geometry
from stnh_tf.inference.options import EstimateOptions, Thresholds
from stnh_tf.inference.search import search_translations
from stnh_tf.inference import export, image_input, model_files
from stnh_tf.modeling import models
from stnh_tf.inference.estimator import HomographyEstimator

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
S = 128


# --------------------------------------------------------------------------------------------
# Helpers (independent references)
# --------------------------------------------------------------------------------------------
def _randomize(regressor, seed):
    """Perturb every layer with weights so that the outputs depend on each of them (a weight lost
    on the way changes the numbers): the convolutions' and fc1's biases (zero at the start) get
    small random values and their kernels a random gain, BatchNorm layers (batch_norm="conv"
    builds only) random statistics, and fc2 (zero kernel at the start) a random kernel. Asserts
    that each of those layers changed."""
    rng = np.random.default_rng(seed)
    changed = []
    for layer in regressor.layers:
        before = layer.get_weights()
        if not before:
            continue
        if isinstance(layer, keras.layers.BatchNormalization):
            gamma, beta, mean, var = before
            after = [rng.uniform(0.8, 1.2, gamma.shape), rng.normal(0, 0.1, beta.shape),
                     rng.normal(0, 0.1, mean.shape), rng.uniform(0.5, 1.5, var.shape)]
        elif layer.name == "fc2":
            kernel, bias = before
            after = [rng.normal(0, 2e-3, kernel.shape), bias]
        else:  # Conv2D, Dense
            kernel, bias = before
            after = [kernel * rng.uniform(0.9, 1.1, kernel.shape), rng.normal(0, 0.02, bias.shape)]
        layer.set_weights([w.astype("float32") for w in after])
        assert all(not np.array_equal(b, a) for b, a in zip(before, layer.get_weights())
                   if b.size > 8 or layer.name != "fc2"), layer.name
        changed.append(layer.name)
    assert changed[-1] == "fc2" and {f"conv{k}" for k in range(1, 9)} <= set(changed), changed


def _random_stage(seed, name):
    """A single stage whose every weight reaches the output (the paper's widths: at conftest's
    narrow widths the zero and mirror fills of stage 2 differed by less than the comparisons'
    tolerance)."""
    model = models.build_stn_homography(name=name)
    _randomize(model.get_layer("regression"), seed)
    return model


def _spy_stage(gain, h_const, name):
    """Tiny model with H_bar = to_bar(h_const) + gain * mean(patch_a) on the x-translation entry,
    so its output reveals what patch_a it was given."""
    a = keras.Input((S, S, 1), name="patch_a")
    b = keras.Input((S, S, 1), name="patch_b")
    means = keras.layers.Concatenate()([keras.layers.GlobalAveragePooling2D()(a),
                                        keras.layers.GlobalAveragePooling2D()(b)])
    kernel = np.zeros((2, 8), np.float32)
    kernel[0, 2] = gain
    dense = keras.layers.Dense(8, name="fc")
    h = keras.layers.Identity(name="h_bar")(dense(means))
    model = keras.Model({"patch_a": a, "patch_b": b}, {"h_bar": h}, name=name)
    dense.set_weights([kernel, to_bar(h_const).ravel()[:8].astype(np.float32)])
    return model


def _spy_expected_h(h_const, gain, patch_a_seen):
    hb = to_bar(h_const)
    hb[0, 2] += gain * float(np.mean(patch_a_seen, dtype=np.float64))
    m = norm_matrix()
    h = np.linalg.inv(m) @ hb @ m
    return h / h[2, 2]


def _direct(model, a_f32, b_f32, output="h_bar"):
    """Run the Keras model itself; convert its H_bar with geometry.denormalize_homography."""
    out = model.predict({"patch_a": a_f32, "patch_b": b_f32}, verbose=0)
    return geometry.denormalize_homography(
        geometry.vector_to_matrix(np.asarray(out[output], np.float64)))


def _unit(h):
    return h / h[..., 2:3, 2:3]


# --------------------------------------------------------------------------------------------
# Fixtures
# --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def pairs(photo_patches):
    """Four uint8 [4, 128, 128, 1] pairs: real photographs and paper-protocol warps of them."""
    rng = np.random.default_rng(7)
    a, b, hs = [], [], []
    for patch in photo_patches.values():
        h = paper_homography(rng)
        a.append(np.clip(np.rint(patch), 0, 255).astype(np.uint8))
        b.append(np.clip(np.rint(cv2_warp(patch, h)), 0, 255).astype(np.uint8))
        hs.append(h)
    return np.stack(a)[..., None], np.stack(b)[..., None], np.stack(hs)


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """Perturbed single-stage, 2-stage hierarchy and 2-stage sequence models, saved to disk."""
    root = tmp_path_factory.mktemp("models")
    single = _random_stage(1, "single")
    single.save(root / "single.keras")
    os.makedirs(root / "run")
    single.save(root / "run" / "model.keras")  # training-run layout

    stage1, stage2 = _random_stage(2, "stage_one"), _random_stage(3, "stage_two")
    os.makedirs(root / "hier" / "stage1")
    stage1.save(root / "hier" / "stage1" / "model.keras")
    stage2.save(root / "hier" / "stage2.keras")
    manifest = {"format": "stnh_tf.hierarchy", "version": 1,
                "stages": ["stage1", "stage2.keras"], "description": "test hierarchy"}
    (root / "hier" / "hierarchy.json").write_text(json.dumps(manifest))

    seq = models.build_sequence_stn_homography(2)
    _randomize(seq.get_layer("regression_1"), 4)
    _randomize(seq.get_layer("regression_2"), 5)
    seq.save(root / "seq.keras")
    return {"root": root, "single": single, "stage1": stage1, "stage2": stage2, "seq": seq}


@pytest.fixture(scope="module")
def identity_model_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("identity") / "identity.keras"
    constant_stage(np.eye(3), "identity").save(path)
    return str(path)


# --------------------------------------------------------------------------------------------
# load: round trips of every kind
# --------------------------------------------------------------------------------------------
def _hierarchy_reference(stage1, stage2, a_u8, b_u8, border=cv2.BORDER_REFLECT_101):
    """Stage 2 on patch_a warped by stage 1 (OpenCV, mirrored beyond the patch as estimate's
    default fill="reflect"; cv2.BORDER_CONSTANT for fill="zeros")."""
    a, b = a_u8.astype(np.float32) / 255.0, b_u8.astype(np.float32) / 255.0
    h1 = _direct(stage1, a, b)
    a2 = np.stack([cv2_warp(p[..., 0], h, border) for p, h in zip(a, h1)])[..., None]
    h2 = _direct(stage2, a2, b)
    return _unit(h1 @ h2), h1


def test_load_single_stage_round_trip(saved, pairs):
    a, b, _ = pairs
    ref = _direct(saved["single"], a.astype(np.float32) / 255, b.astype(np.float32) / 255)
    assert np.std(ref[:, 0, 2]) > 0.05  # the output depends on the input: a real comparison
    for path in (saved["root"] / "single.keras", saved["root"] / "run"):
        est = HomographyEstimator.load(path)
        assert (est.kind, est.num_stages) == ("single", 1)
        h = est.estimate(a, b, EstimateOptions(search="none"))
        np.testing.assert_allclose(h, ref, rtol=1e-5, atol=1e-4)


def test_load_hierarchy_manifest_round_trip(saved, pairs):
    a, b, _ = pairs
    ref, h1 = _hierarchy_reference(saved["stage1"], saved["stage2"], a, b)
    assert np.max(geometry.corner_errors(ref, h1)) > 0.5  # stage 2 changes the estimate
    for path in (saved["root"] / "hier" / "hierarchy.json", saved["root"] / "hier"):
        est = HomographyEstimator.load(path)
        assert (est.kind, est.num_stages) == ("hierarchy", 2)
        np.testing.assert_allclose(
            est.estimate(a, b, EstimateOptions(gate_stages=False, search="none")),
            ref, rtol=1e-5, atol=1e-4)
    zeros, _ = _hierarchy_reference(saved["stage1"], saved["stage2"], a, b, cv2.BORDER_CONSTANT)
    assert np.max(geometry.corner_errors(zeros, ref)) > 0.01  # the fill reaches stage 2
    np.testing.assert_allclose(
        est.estimate(a, b, EstimateOptions(gate_stages=False, fill="zeros", search="none")),
        zeros,
        rtol=1e-5, atol=1e-4)
    with pytest.raises(ValueError, match="fill must be one of"):
        est.estimate(a, b, EstimateOptions(fill="edge", search="none"))


def test_load_numbered_stage_directory(saved, pairs, tmp_path):
    """A folder holding stage1/, stage2.keras (no manifest) is a hierarchy in numeric order."""
    os.makedirs(tmp_path / "stage1")
    saved["stage1"].save(tmp_path / "stage1" / "model.keras")
    saved["stage2"].save(tmp_path / "stage2.keras")
    assert model_files.resolve_model_paths(tmp_path) == [str(tmp_path / "stage1"),
                                                        str(tmp_path / "stage2.keras")]
    a, b, _ = pairs
    ref, _ = _hierarchy_reference(saved["stage1"], saved["stage2"], a[:2], b[:2])
    np.testing.assert_allclose(
        HomographyEstimator.load(tmp_path).estimate(
            a[:2], b[:2], EstimateOptions(gate_stages=False, search="none")),
        ref, rtol=1e-5, atol=1e-4)


def test_load_sequence_round_trip(saved, pairs):
    a, b, _ = pairs
    est = HomographyEstimator.load(saved["root"] / "seq.keras")
    assert (est.kind, est.num_stages) == ("sequence", 1)
    af, bf = a.astype(np.float32) / 255, b.astype(np.float32) / 255
    ref = _direct(saved["seq"], af, bf, "h_bar_2")
    assert np.max(geometry.corner_errors(ref, _direct(saved["seq"], af, bf, "h_bar_1"))) > 0.5
    np.testing.assert_allclose(est.estimate(a, b, EstimateOptions(search="none")), ref,
                               rtol=1e-5, atol=1e-4)


def test_write_manifest_round_trip(saved, tmp_path):
    path = model_files.write_manifest(tmp_path / "h.json", [tmp_path / "a.keras",
                                                            tmp_path / "sub" / "x.keras"])
    doc = json.loads(open(path).read())
    assert doc["format"] == "stnh_tf.hierarchy" and doc["version"] == 1
    assert doc["stages"] == ["a.keras", "sub/x.keras"]
    assert model_files.read_manifest(path) == [str(tmp_path / "a.keras"),
                                               str(tmp_path / "sub" / "x.keras")]
    with pytest.raises(ValueError, match="outside the manifest's folder"):
        model_files.write_manifest(tmp_path / "h2.json", [saved["root"] / "single.keras"])
    assert not (tmp_path / "h2.json").exists()


def test_manifest_stages_must_stay_inside_its_folder(saved, tmp_path):
    """A manifest naming stages with '../' or an absolute path is refused: it could make the
    loader read models from anywhere."""
    folder = tmp_path / "m"
    folder.mkdir()
    shutil.copy(saved["root"] / "single.keras", folder / "stage1.keras")
    shutil.copy(saved["root"] / "single.keras", tmp_path / "single.keras")
    for stage in ("../single.keras", str(saved["root"] / "single.keras"), "sub/../../x.keras"):
        (folder / "h.json").write_text(json.dumps(
            {"format": "stnh_tf.hierarchy", "version": 1, "stages": ["stage1.keras", stage]}))
        with pytest.raises(ValueError, match="stage 2: .* is not a path inside"):
            HomographyEstimator.load(folder / "h.json")
    (folder / "h.json").write_bytes(b"\xff\xfe not text")
    with pytest.raises(ValueError, match="hierarchy manifest .*h.json.* is not valid JSON"):
        HomographyEstimator.load(folder / "h.json")


def test_load_of_a_file_that_is_not_a_model_says_so(tmp_path):
    (tmp_path / "notes.keras").write_text("a text file named .keras")
    with pytest.raises(ValueError) as info:
        HomographyEstimator.load(tmp_path / "notes.keras")
    assert "notes.keras exists but is not a Keras model" in str(info.value)
    assert "File not found" not in str(info.value)


def test_load_default_weights(monkeypatch, tmp_path, identity_model_path):
    monkeypatch.setattr(model_files, "default_weights_dir", lambda: str(tmp_path))
    with pytest.raises(FileNotFoundError, match="no shipped weights"):
        HomographyEstimator.load()
    os.link(identity_model_path, tmp_path / "default.keras")
    assert HomographyEstimator.load().kind == "single"
    model_files.write_manifest(tmp_path / "default.json", [tmp_path / "default.keras"] * 2)
    assert HomographyEstimator.load().kind == "hierarchy"  # the manifest wins


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="holds no model"):
        HomographyEstimator.load(tmp_path)
    with pytest.raises(FileNotFoundError, match="no model at"):
        HomographyEstimator.load(tmp_path / "missing.keras")
    (tmp_path / "bad.json").write_text(json.dumps({"stages": ["a.keras"]}))
    with pytest.raises(ValueError, match="not a hierarchy manifest"):
        HomographyEstimator.load(tmp_path / "bad.json")
    (tmp_path / "empty.json").write_text(json.dumps(
        {"format": "stnh_tf.hierarchy", "version": 1, "stages": []}))
    with pytest.raises(ValueError, match="non-empty list"):
        HomographyEstimator.load(tmp_path / "empty.json")
    (tmp_path / "junk.keras").write_text("not a model")
    with pytest.raises(ValueError, match="junk.keras"):
        HomographyEstimator.load(tmp_path / "junk.keras")


# --------------------------------------------------------------------------------------------
# estimate: shape, dtype, direction, composition, input types
# --------------------------------------------------------------------------------------------
def test_estimate_known_output_shape_dtype_and_direction(pairs, rng):
    a, _, _ = pairs
    h_true = paper_homography(rng)
    est = HomographyEstimator([constant_stage(h_true)])
    # patch_b(p) = patch_a(H p): the estimate must be H itself (patch_b -> patch_a).
    b = np.stack([np.clip(np.rint(cv2_warp(p[..., 0], h_true)), 0, 255)
                  for p in a]).astype(np.uint8)
    h = est.estimate(a, b)
    assert h.shape == (4, 3, 3) and h.dtype == np.float64
    m = norm_matrix()
    expected = np.linalg.inv(m) @ to_bar(h_true) @ m
    np.testing.assert_allclose(h, np.broadcast_to(expected / expected[2, 2], h.shape), atol=1e-5)
    np.testing.assert_allclose(h[0], h_true, atol=2e-3)
    # Direction: warping patch_a with the estimate reproduces patch_b where both are defined.
    mask = inside_mask(h[0])
    assert mask.mean() > 0.3
    diff = np.abs(cv2_warp(a[0, ..., 0], h[0]) - b[0].astype(np.float64))[mask]
    assert diff.mean() < 1.0
    # ...and the inverse direction does not.
    wrong = np.abs(cv2_warp(a[0, ..., 0], np.linalg.inv(h[0])) - b[0].astype(np.float64))[mask]
    assert wrong.mean() > 5.0
    # One pair in: still [1, 3, 3].
    single = est.estimate(a[0, ..., 0], b[0])
    assert single.shape == (1, 3, 3)


def test_hierarchy_of_constant_stages_is_the_product(pairs, rng):
    a, b, _ = pairs
    h1, h2 = paper_homography(rng), paper_homography(rng)
    est = HomographyEstimator([constant_stage(h1, "c1"), constant_stage(h2, "c2")])
    assert est.kind == "hierarchy"
    got = est.estimate(a, b, EstimateOptions(gate_stages=False, search="none"))
    want = h1 @ h2
    np.testing.assert_allclose(got, np.broadcast_to(want / want[2, 2], got.shape), atol=1e-4)
    other = h2 @ h1
    assert np.max(np.abs(other / other[2, 2] - want / want[2, 2])) > 0.5  # order matters


def test_degenerate_stage_predictions_are_skipped_and_counted(pairs, rng, caplog):
    """A stage whose prediction makes the composition non-finite or singular is skipped (the
    estimate so far kept), as in evaluation; the others compose as usual."""
    a, b, _ = pairs
    h1, h3 = paper_homography(rng), paper_homography(rng)
    est = HomographyEstimator([constant_stage(np.eye(3), f"c{k}") for k in (1, 2, 3)])
    bad = {0: np.full((3, 3), np.nan), 1: np.diag([1e-4, 1e-4, 1.0])}  # non-finite, singular
    outputs = {0: h1, 2: h3}

    def fake_stage(k, patch_a, patch_b, batch_size):
        h = np.repeat(outputs.get(k, np.eye(3))[None], len(patch_a), 0)
        if k == 1:  # pair 0 non-finite, pair 1 singular, the others the identity
            h[0], h[1] = bad[0], bad[1]
        return h

    est._predict_stage = fake_stage
    with caplog.at_level("WARNING"):
        got = est.estimate(a, b, EstimateOptions(gate_stages=False, search="none"))
    want = h1 @ h3
    np.testing.assert_allclose(got, np.broadcast_to(want / want[2, 2], got.shape), atol=1e-9)
    assert est.last_rejected == {"non_finite": 1, "singular": 1}
    assert "degenerate" in caplog.text
    est._predict_stage = lambda k, pa, pb, bs: np.repeat(outputs.get(k, np.eye(3))[None],
                                                         len(pa), 0)
    est.estimate(a, b, EstimateOptions(search="none"))
    assert est.last_rejected == {"non_finite": 0, "singular": 0}


def test_alignment_ncc_against_numpy(pairs):
    from stnh_tf.inference import estimator as inference

    a, b, hs = pairs
    for k in range(len(a)):
        ncc = inference.alignment_ncc(a[k, ..., 0], b[k, ..., 0], hs[k])
        assert ncc == pytest.approx(ncc_reference(a[k, ..., 0], b[k, ..., 0], hs[k]), abs=1e-6)
        assert ncc > 0.95  # true H: aligned up to uint8 rounding
        # gain and offset of patch_b do not change it
        assert inference.alignment_ncc(a[k, ..., 0], 0.5 * b[k, ..., 0] + 40.0, hs[k]) == \
            pytest.approx(ncc, abs=1e-9)
    # unrelated content
    assert abs(inference.alignment_ncc(a[0, ..., 0], a[1, ..., 0], hs[1])) < 0.3
    # a translation leaving 20% of patch_b inside patch_a: undefined
    shift = np.array([[1.0, 0, 102.4], [0, 1, 0], [0, 0, 1]])
    assert np.isnan(inference.alignment_ncc(a[0, ..., 0], b[0, ..., 0], shift))
    # with a context holding patch_a at (50, 50), every warped pixel is defined: the NCC over
    # the whole patch of the OpenCV warp of the context
    context = np.random.default_rng(3).uniform(0, 255, (240, 320)).astype(np.float32)
    context[50:178, 50:178] = a[0, ..., 0]
    t = np.array([[1.0, 0, 50], [0, 1, 50], [0, 0, 1]])
    for h in (hs[0], shift):
        x = cv2.warpPerspective(context, t @ h, (S, S),
                                flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
        x = x.astype(np.float64).ravel() - x.mean()
        y = b[0, ..., 0].astype(np.float64).ravel() - b[0].mean()
        assert inference.alignment_ncc(context, b[0, ..., 0], h, (50, 50)) == pytest.approx(
            float((x * y).sum() / np.sqrt((x * x).sum() * (y * y).sum())), abs=1e-6)


def test_implausible_estimates_are_flagged_per_pair(pairs):
    """A pair whose estimate moves a patch corner beyond 1.5 x 32 px, one with a stage skipped as
    degenerate, and one whose estimate leaves patch_a warped onto patch_b uncorrelated with it
    (patch_b from another photograph) are flagged in ``last_info``; the true H of an ordinary pair
    is not. The corner shift is checked against OpenCV's perspectiveTransform, the NCC against a
    NumPy reference."""
    import cv2

    from stnh_tf.inference import estimator as inference

    a, b, hs = pairs
    n = len(a)
    assert n == 4
    b = b.copy()
    b[3] = a[0]  # another photograph: unrelated to patch_a of pair 3
    corners = np.array([[0, 0], [128, 0], [128, 128], [0, 128]], np.float64)
    beyond = cv2.getPerspectiveTransform(corners.astype(np.float32),
                                         (corners + [[60, 0], [0, 0], [0, 0], [0, 0]])
                                         .astype(np.float32))
    est = HomographyEstimator([constant_stage(np.eye(3), f"c{k}") for k in (1, 2)])

    def fake_stage(k, patch_a, patch_b, batch_size):
        h = hs.copy() if k == 0 else np.repeat(np.eye(3)[None], len(patch_a), 0)
        if k == 0:
            h[1] = beyond
        if k == 1:
            h[2] = np.full((3, 3), np.nan)  # skipped as degenerate; the estimate stays the true H
        return h

    est._predict_stage = fake_stage
    est.estimate(a, b, EstimateOptions(search="none"))
    info = est.last_info
    np.testing.assert_array_equal(info["implausible"], [False, True, True, True])
    np.testing.assert_array_equal(info["rejected_stages"], [0, 0, 1, 0])
    moved = cv2.perspectiveTransform(corners[None], hs[0])[0]
    assert info["max_corner_shift_px"][0] == pytest.approx(
        np.linalg.norm(moved - corners, axis=1).max(), abs=1e-6)
    assert info["max_corner_shift_px"][1] == pytest.approx(60.0, abs=1e-6)
    assert EstimateOptions().thresholds.implausible_corner_shift == 48.0
    assert info["max_corner_shift_px"][[0, 2, 3]].max() < 48.0
    for k in (0, 2, 3):
        # (OpenCV quantizes warp positions to 1/32 px: border pixels may differ from the mask)
        assert info["alignment_ncc"][k] == pytest.approx(
            ncc_reference(a[k, ..., 0], b[k, ..., 0], hs[k]), abs=1e-3)
    assert info["alignment_ncc"][[0, 2]].min() > 0.95
    assert info["alignment_ncc"][3] < EstimateOptions().thresholds.min_alignment_ncc


def test_flat_patch_gives_the_flagged_identity(pairs, identity_model_path, tmp_path):
    """A pair with a flat patch (intensity std below MIN_PATCH_STD, NumPy reference: a patch_b an
    exposure change clipped to black, a patch_a with one grey level on 10% of its pixels) gets the
    identity, flagged implausible with an undefined NCC, whatever the stages predict; the other
    pairs keep the stages' estimate. estimate_images and the predict CLI's library call do the
    same for a black image_b."""
    from stnh_tf.inference import image_files as alignment
    from stnh_tf.inference import estimator as inference

    a, b, hs = pairs
    a, b = a.copy(), b.copy()
    b[1] = 0
    a[2] = 100
    a[2].reshape(-1)[::10] = 101
    std = lambda p: (p.astype(np.float64) / 255).std()  # noqa: E731
    min_std = EstimateOptions().thresholds.min_patch_std
    assert std(b[1]) < min_std and std(a[2]) < min_std
    assert min(min(std(a[i]), std(b[i])) for i in (0, 3)) > 10 * min_std
    est = HomographyEstimator([constant_stage(np.eye(3), f"c{k}") for k in (1, 2)])
    est._predict_stage = lambda k, pa, pb, bs: hs.copy() if k == 0 else np.repeat(
        np.eye(3)[None], len(pa), 0)
    got = est.estimate(a, b)
    info = est.last_info
    np.testing.assert_array_equal(info["flat"], [False, True, True, False])
    np.testing.assert_array_equal(info["implausible"], [False, True, True, False])
    for i in (1, 2):
        np.testing.assert_allclose(got[i], np.eye(3), atol=1e-12)
        assert np.isnan(info["alignment_ncc"][i]) and info["max_corner_shift_px"][i] < 1e-9
    for i in (0, 3):
        np.testing.assert_allclose(got[i], hs[i] / hs[i, 2, 2], atol=1e-9)
        assert info["alignment_ncc"][i] > 0.95

    image = cv2.resize(np.squeeze(pairs[0][0]), (320, 240))
    h = est.estimate_images(image, np.zeros_like(image))
    np.testing.assert_allclose(h, np.eye(3), atol=1e-12)
    assert est.last_info["flat"][0] and est.last_info["implausible"][0]
    cv2.imwrite(str(tmp_path / "a.png"), image)
    cv2.imwrite(str(tmp_path / "black.png"), np.zeros_like(image))
    warnings = []
    result = alignment.align_image_files(str(tmp_path / "a.png"), str(tmp_path / "black.png"),
                                         model=identity_model_path,
                                         output_dir=str(tmp_path / "out"), warn=warnings.append)
    assert result["implausible"] is True and result["flat"] is True
    assert result["alignment_ncc"] is None
    assert len(warnings) == 1 and "flat" in warnings[0]


def test_stage_gate_keeps_later_updates_that_do_not_lower_the_alignment(pairs):
    """estimate's gate (the default): a later stage's update is kept where the NCC of patch_b and
    the warped patch_a (NumPy reference) does not drop, dropped where it does; stage 1 is always
    kept; gate_stages=False composes every stage."""
    a, b, hs = pairs
    off = geometry.translation(6.0, -5.0)
    # per pair: stage 1, 2, 3 predictions
    plans = [(hs[0], off, np.eye(3)),                  # stage 2 moves a true estimate away
             (hs[1] @ np.linalg.inv(off), off, off),   # stage 2 corrects stage 1, stage 3 errs
             (hs[2] @ off, np.linalg.inv(off), np.eye(3)),
             (np.eye(3), hs[3], np.eye(3))]            # stage 1 sees nothing, stage 2 finds it
    est = HomographyEstimator([constant_stage(np.eye(3), f"c{k}") for k in (1, 2, 3)])
    est._predict_stage = lambda k, pa, pb, bs: np.stack([p[k] for p in plans])
    got = est.estimate(a, b, EstimateOptions(search="none"))
    for i, plan in enumerate(plans):
        total, gated = plan[0], 0
        for h in plan[1:]:
            before = ncc_reference(a[i, ..., 0], b[i, ..., 0], total)
            after = ncc_reference(a[i, ..., 0], b[i, ..., 0], total @ h)
            if not np.allclose(h, np.eye(3)):
                assert abs(after - before) > 0.05  # no near tie the two NCCs could rank apart
            if after >= before:
                total = total @ h
            else:
                gated += 1
        np.testing.assert_allclose(got[i], total / total[2, 2], atol=1e-9)
        np.testing.assert_allclose(total / total[2, 2], hs[i] / hs[i, 2, 2], atol=1e-9)
        assert est.last_info["gated_stages"][i] == gated
    np.testing.assert_array_equal(est.last_info["gated_stages"], [1, 1, 0, 0])
    plain = est.estimate(a, b, EstimateOptions(gate_stages=False, search="none"))
    for i, plan in enumerate(plans):
        want = plan[0] @ plan[1] @ plan[2]
        np.testing.assert_allclose(plain[i], want / want[2, 2], atol=1e-9)
    np.testing.assert_array_equal(est.last_info["gated_stages"], [0, 0, 0, 0])


def test_ecc_refinement_recovers_the_true_homography(pairs, monkeypatch):
    """refine="ecc" started from estimates 3-5 px off the true H (known from the OpenCV warp that
    made each pair) lands within 0.5 px of it (the pairs are rounded to uint8), also when patch_b's
    gain and offset change; refine="none" returns the start unchanged; a refinement moving the
    corners by more than MAX_REFINE_MOVE is dropped for the start; an unknown refine is an error."""
    from stnh_tf.inference import estimator as inference

    a, b, hs = pairs
    off = geometry.translation(3.0, -2.0) @ np.array([[1.02, 0.01, 0], [-0.01, 0.99, 0], [0, 0, 1]])
    starts = np.stack([h @ off for h in hs])
    est = HomographyEstimator([constant_stage(np.eye(3))])
    est._predict_stage = lambda k, pa, pb, bs: starts.copy()
    start_error = geometry.corner_errors(starts, hs)
    assert start_error.min() > 3.0
    b_exposed = np.clip(np.rint(0.7 * b.astype(np.float64) + 40), 0, 255).astype(np.uint8)
    for patch_b in (b, b_exposed):
        got = est.estimate(a, patch_b, EstimateOptions(refine="ecc", search="none"))
        assert geometry.corner_errors(got, hs).max() < 0.5
        assert est.last_info["refined"].all()
        # the flags follow the refined estimate: its NCC (NumPy reference) is near 1
        for i in range(len(a)):
            assert est.last_info["alignment_ncc"][i] == pytest.approx(
                ncc_reference(a[i, ..., 0], patch_b[i, ..., 0], got[i]), abs=1e-3)
        assert not est.last_info["implausible"].any()
    np.testing.assert_allclose(est.estimate(a, b, EstimateOptions(search="none")),
                               starts / starts[:, 2:, 2:], atol=1e-12)
    assert not est.last_info["refined"].any()
    short = EstimateOptions(refine="ecc", search="none",
                            thresholds=Thresholds(max_refine_move=1.0))
    np.testing.assert_allclose(est.estimate(a, b, short),
                               starts / starts[:, 2:, 2:],
                               atol=1e-12)
    assert not est.last_info["refined"].any()
    with pytest.raises(ValueError, match="refine must be one of"):
        est.estimate(a, b, EstimateOptions(refine="sift", search="none"))


# The symmetries of a 128 x 128 patch written out (pixel centres at integers, c = 127): pixel
# (x, y) of the patch lands at G @ (x, y, 1) once the patch is transformed.
_C = S - 1.0
_PATCH_SYMMETRIES = {
    "identity": np.eye(3),
    "flip_x": np.array([[-1, 0, _C], [0, 1, 0], [0, 0, 1]]),
    "flip_y": np.array([[1, 0, 0], [0, -1, _C], [0, 0, 1]]),
    "rotate_180": np.array([[-1, 0, _C], [0, -1, _C], [0, 0, 1]]),
    "rotate_90_cw": np.array([[0, -1, _C], [1, 0, 0], [0, 0, 1]]),
    "anti_transpose": np.array([[0, -1, _C], [-1, 0, _C], [0, 0, 1]])}


def _symmetry_pairs(pairs, names):
    """The photographs' patches a, and b made (OpenCV warp) from pair i's a with
    inv(G_i) @ H_c @ G_i for G_i = the symmetry names[i]: what a stage that always predicts H_c
    estimates on pair i transformed by G_i. Returns (a, b, those homographies, H_c)."""
    a, _, _ = pairs
    h_c = geometry.translation(7.0, -4.0) @ np.array([[1.03, 0.02, 0], [-0.02, 0.98, 0],
                                                      [1e-4, 2e-4, 1]])
    want = np.stack([np.linalg.inv(_PATCH_SYMMETRIES[n]) @ h_c @ _PATCH_SYMMETRIES[n]
                     for n in names])
    want /= want[:, 2:, 2:]
    b = np.stack([np.clip(np.rint(cv2_warp(x[..., 0], h)), 0, 255).astype(np.uint8)
                  for x, h in zip(a, want)])[..., None]
    return a, b, want, h_c


def test_tta_keeps_the_estimate_that_aligns_the_pair_best(pairs):
    """A stage that always predicts H_c estimates inv(G) @ H_c @ G on the pair transformed by G;
    pair i is made (OpenCV warp) with that homography for a different G, so tta="dihedral" must
    return it exactly and name G; tta="none" returns H_c; "flips" cannot reach the rotations; the
    flags' NCC is the kept estimate's (NumPy reference); an unknown tta is an error."""
    names = ["rotate_90_cw", "identity", "flip_y", "anti_transpose"]
    a, b, want, h_c = _symmetry_pairs(pairs, names)
    est = HomographyEstimator([constant_stage(h_c, "c")])
    got = est.estimate(a, b, EstimateOptions(tta="dihedral", search="none"))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)  # H_c passes through float32
    assert est.last_info["tta_choice"].tolist() == names
    ncc = [ncc_reference(x[..., 0], y[..., 0], h) for x, y, h in zip(a, b, got)]
    np.testing.assert_allclose(est.last_info["alignment_ncc"], ncc, atol=3e-3)
    assert min(ncc) > 0.99
    np.testing.assert_allclose(est.estimate(a, b, EstimateOptions(search="none")),
                               np.broadcast_to(h_c / h_c[2, 2], (4, 3, 3)),
                               rtol=1e-5, atol=1e-5)
    assert est.last_info["tta_choice"].tolist() == ["identity"] * 4
    got = est.estimate(a, b, EstimateOptions(tta="flips", search="none"))
    assert est.last_info["tta_choice"][0] in ("identity", "flip_x", "flip_y", "rotate_180")
    assert geometry.corner_errors(got[:1], want[:1])[0] > 1.0
    np.testing.assert_allclose(got[1:3], want[1:3], rtol=1e-5, atol=1e-5)
    for bad in ("rotations", ["dihedral"]):  # a list named, not an unhashable-type TypeError
        with pytest.raises(ValueError, match=r"^tta must be one of .*received "):
            est.estimate(a, b, EstimateOptions(tta=bad, search="none"))


def test_flagged_estimates_are_retried_with_test_time_augmentation(pairs):
    """estimate(retry_tta="dihedral") on pairs made as in the tta test: the constant stage aligns
    one of them, the plain estimate flags the other three as implausible; each flagged pair gets
    the estimate and every last_info entry of tta="dihedral" (its true H, the OpenCV warp that made
    it), the other keeps the plain estimate's. With a second stage whose predictions are all
    skipped as degenerate (every pair flagged and retried), last_rejected counts the kept
    estimates' skips (one per pair), not those of both passes. A retry_tta that runs no more
    symmetries than tta does nothing; an unknown one is an error."""
    names = ["rotate_90_cw", "identity", "flip_y", "rotate_180"]
    a, b, want, h_c = _symmetry_pairs(pairs, names)
    est = HomographyEstimator([constant_stage(h_c, "c")])
    plain = est.estimate(a, b, EstimateOptions(search="none"))
    plain_info = est.last_info
    flagged = np.array([True, False, True, True])
    np.testing.assert_array_equal(plain_info["implausible"], flagged)
    assert not plain_info["retried"].any()
    full = est.estimate(a, b, EstimateOptions(tta="dihedral", search="none"))
    full_info = est.last_info
    np.testing.assert_allclose(full, want, rtol=1e-5, atol=1e-5)  # H_c passes through float32
    got = est.estimate(a, b, EstimateOptions(retry_tta="dihedral", search="none"))
    info = est.last_info
    np.testing.assert_array_equal(info["retried"], flagged)
    np.testing.assert_allclose(got[flagged], full[flagged], atol=1e-12)
    np.testing.assert_allclose(got[~flagged], plain[~flagged], atol=1e-12)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
    assert info["tta_choice"].tolist() == names
    for key in plain_info:
        if key != "retried":
            np.testing.assert_array_equal(info[key][flagged], full_info[key][flagged], key)
            np.testing.assert_array_equal(info[key][~flagged], plain_info[key][~flagged], key)
    assert not info["implausible"].any()
    est.estimate(a, b, EstimateOptions(tta="dihedral", retry_tta="flips", search="none"))
    assert not est.last_info["retried"].any()
    for bad in ("rotations", ["dihedral"]):
        with pytest.raises(ValueError, match="retry_tta must be one of"):
            est.estimate(a, b, EstimateOptions(retry_tta=bad, search="none"))

    two = HomographyEstimator([constant_stage(h_c, "c1"), constant_stage(np.eye(3), "c2")])
    predict = two._predict_stage
    two._predict_stage = lambda k, pa, pb, bs: (predict(k, pa, pb, bs) if k == 0
                                                else np.full((len(pa), 3, 3), np.nan))
    two.estimate(a, b, EstimateOptions(retry_tta="dihedral", search="none"))
    assert two.last_info["retried"].all() and two.last_info["implausible"].all()
    np.testing.assert_array_equal(two.last_info["rejected_stages"], [1, 1, 1, 1])
    assert two.last_rejected == {"non_finite": 4, "singular": 0}


def _wall_pair(rng, a_from_b):
    """A texture whose columns repeat every 20 px (a brick wall's), made unique by noise, and
    patch_b made from it by OpenCV: ``b(p) = a(a_from_b @ p)`` (uint8)."""
    cell = rng.random((S, 20))
    wall = np.tile(cell, (1, S // 20 + 1))[:, :S]
    a = cv2.GaussianBlur(wall + 0.6 * rng.random(wall.shape), (0, 0), 1.5)
    a = np.rint(255 * (a - a.min()) / (a.max() - a.min())).astype(np.uint8)
    return a, cv2.warpPerspective(a, a_from_b, (S, S),
                                  flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)


def test_search_finds_the_alignment_a_network_put_a_period_off(pairs, rng, monkeypatch):
    """search="ecc" (the default): a pair whose estimate is one 20-px period of a repeating
    texture off the true H (known from the OpenCV warp that made it) gets, from the search, an
    estimate within 0.5 px of it, with its NCC (NumPy reference); a pair the network aligns well
    is not searched, and one with patch_b from another texture is searched without result: both
    keep the network's estimate. search="none" returns the network's estimates; with a verified
    NCC no alignment can reach, nothing is replaced."""
    from stnh_tf.inference import estimator as inference

    a_s, b_s, hs = pairs
    h_wall = geometry.translation(6.0, -4.0) @ np.array([[1.03, 0.02, 0], [-0.01, 0.98, 0],
                                                        [1e-4, -5e-5, 1]])
    wall_a, wall_b = _wall_pair(rng, h_wall)
    a = np.stack([wall_a, a_s[0, ..., 0], a_s[1, ..., 0]])
    b = np.stack([wall_b, b_s[0, ..., 0], b_s[0, ..., 0]])  # pair 2: patch_b of another texture
    starts = np.stack([h_wall @ geometry.translation(20.0, 0.0), hs[0], np.eye(3)])
    est = HomographyEstimator([constant_stage(np.eye(3))])
    est._predict_stage = lambda k, pa, pb, bs: starts.copy()

    network = est.estimate(a, b, EstimateOptions(search="none"))
    np.testing.assert_allclose(network, starts / starts[:, 2:, 2:], atol=1e-12)
    assert est.last_info["alignment_ncc"][0] < EstimateOptions().thresholds.search_below_ncc
    assert not est.last_info["searched"].any() and not est.last_info["search_found"].any()
    assert geometry.corner_errors(network[:1], h_wall[None])[0] > 15.0

    got = est.estimate(a, b)
    info = est.last_info
    assert geometry.corner_errors(got[:1], h_wall[None])[0] < 0.5
    np.testing.assert_allclose(got[1:], network[1:], atol=1e-12)
    np.testing.assert_array_equal(info["searched"], [True, False, True])
    np.testing.assert_array_equal(info["search_found"], [True, False, False])
    np.testing.assert_array_equal(info["implausible"], [False, False, True])
    assert info["alignment_ncc"][0] >= EstimateOptions().thresholds.verified_ncc
    assert info["alignment_ncc"][0] == pytest.approx(
        ncc_reference(a[0] / 255.0, b[0] / 255.0, got[0]), abs=1e-3)

    strict = EstimateOptions(thresholds=Thresholds(verified_ncc=1.01))
    assert search_translations(a[0] / 255.0, b[0] / 255.0, starts[0],
                               thresholds=strict.thresholds) is None
    np.testing.assert_allclose(est.estimate(a, b, strict), network, atol=1e-12)
    np.testing.assert_array_equal(est.last_info["searched"], [True, False, True])
    assert not est.last_info["search_found"].any()
    with pytest.raises(ValueError, match="search must be one of"):
        est.estimate(a, b, EstimateOptions(search="sift"))


def test_estimate_images_tta_transforms_the_image_context():
    """tta with image context: stage 2 (a spy whose output reveals the mean of the patch_a it
    sees) of the pair rotated by 90 degrees must see the crop of the rotated, warped 320 x 240
    image_a, i.e. (a pixel permutation) the crop of image_a warped by the estimate so far mapped
    back (OpenCV reference); image_b is made so that this hypothesis aligns exactly. The plain
    estimate is flagged, and retry_tta="dihedral" gives the same as tta="dihedral"."""
    image = cv2.resize(skimage.data.camera().astype(np.float32) / 255, (320, 240),
                       interpolation=cv2.INTER_AREA)
    h1, gain = geometry.translation(-30.0, 20.0), 0.8
    g = _PATCH_SYMMETRIES["rotate_90_cw"]
    t = geometry.translation(96, 56)
    h1_back = np.linalg.inv(g) @ h1 @ g
    warped = cv2.warpPerspective(image, t @ h1_back @ np.linalg.inv(t), (320, 240),
                                 flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    seen = warped[56:56 + S, 96:96 + S]
    h_patch = np.linalg.inv(g) @ h1 @ _spy_expected_h(np.eye(3), gain, seen) @ g
    h_image = t @ h_patch @ np.linalg.inv(t)
    image_b = cv2.warpPerspective(image, h_image, (320, 240),
                                  flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    est = HomographyEstimator([constant_stage(h1, "c1"), _spy_stage(gain, np.eye(3), "spy")])
    got = est.estimate_images(image, image_b, EstimateOptions(tta="dihedral", search="none"))
    assert est.last_info["tta_choice"][0] == "rotate_90_cw"
    np.testing.assert_allclose(got, h_image / h_image[2, 2], rtol=1e-5, atol=1e-4)
    # the plain estimate is flagged; retry_tta re-runs the pair with its context the same way
    est.estimate_images(image, image_b, EstimateOptions(search="none"))
    assert est.last_info["implausible"][0] and not est.last_info["retried"][0]
    np.testing.assert_allclose(
        est.estimate_images(image, image_b,
                            EstimateOptions(retry_tta="dihedral", search="none")),
        got,
        atol=1e-12)
    assert est.last_info["retried"][0] and est.last_info["tta_choice"][0] == "rotate_90_cw"
    # the spy's reading matters: the crop without context would give another estimate
    zero_filled = cv2_warp(image[56:56 + S, 96:96 + S], h1_back)
    assert abs(seen.mean() - zero_filled.mean()) > 0.02


def test_estimate_images_ecc_refinement_uses_the_whole_image(rng):
    """estimate_images(refine="ecc") with a stage that always predicts the identity: image_b is
    camera() warped by a known H (about 12 px at the image corners); the refined estimate's corner
    error in image_a's 512 x 512 frame, extrapolated from the central 128 x 128 square of the
    320 x 240 work image, is below 1.5 px."""
    image = skimage.data.camera()
    h_true = np.array([[1.0, 0.03, 10.0], [-0.02, 1.0, -8.0], [0.0, 0.0, 1.0]])
    image_b = cv2.warpPerspective(image, h_true, (512, 512), flags=cv2.WARP_INVERSE_MAP)
    corners = np.array([[0, 0], [511, 0], [511, 511], [0, 511]], np.float64)[None]

    def corner_error(h):
        return float(np.linalg.norm(geometry.warp_points(h[None], corners)
                                    - geometry.warp_points(h_true[None], corners), axis=-1).mean())

    est = HomographyEstimator([constant_stage(np.eye(3))])
    assert corner_error(est.estimate_images(image, image_b, EstimateOptions(search="none"))) > 10.0
    assert corner_error(est.estimate_images(
        image, image_b, EstimateOptions(refine="ecc", search="none"))) < 1.5
    assert est.last_info["refined"][0]


@pytest.mark.parametrize("fill, border", [("reflect", cv2.BORDER_REFLECT_101),
                                          ("zeros", cv2.BORDER_CONSTANT)])
def test_hierarchy_later_stage_sees_warped_patch_without_context(pairs, fill, border):
    """estimate (patches only): stage 2 sees patch_a(H_1 p), mirrored about the patch border
    outside it (the default fill) or zero there."""
    a, b, _ = pairs
    h1 = geometry.translation(20.0, -12.0) @ np.diag([1.1, 0.95, 1.0])
    gain = 0.8
    est = HomographyEstimator([constant_stage(h1, "c1"), _spy_stage(gain, np.eye(3), "spy")])
    got = est.estimate(a, b, EstimateOptions(gate_stages=False, fill=fill, search="none"))
    for i in range(len(a)):
        seen = cv2_warp(a[i, ..., 0].astype(np.float32) / 255, h1, border)
        want = h1 @ _spy_expected_h(np.eye(3), gain, seen)
        np.testing.assert_allclose(got[i], want / want[2, 2], atol=1e-4)


def test_uint8_and_float_inputs_agree(saved, pairs):
    a, b, _ = pairs
    est = HomographyEstimator([saved["single"]])
    h_u8 = est.estimate(a, b, EstimateOptions(search="none"))
    h_f32 = est.estimate(a.astype(np.float32) / 255, b.astype(np.float32) / 255,
                         EstimateOptions(search="none"))
    h_f64 = est.estimate(a / 255.0, b / 255.0, EstimateOptions(search="none"))
    np.testing.assert_allclose(h_f32, h_u8, rtol=0, atol=1e-9)
    np.testing.assert_allclose(h_f64, h_u8, rtol=1e-6, atol=1e-5)
    # Every accepted layout of the same pair gives the same answer.
    for pa, pb in ((a[1, ..., 0], b[1, ..., 0]), (a[1], b[1]), (a[1:2, ..., 0], b[1:2, ..., 0])):
        np.testing.assert_allclose(est.estimate(pa, pb, EstimateOptions(search="none")),
                                   h_u8[1:2], rtol=1e-5, atol=1e-4)
    # Chunking does not change the answer.
    np.testing.assert_allclose(est.estimate(a, b, EstimateOptions(search="none"), batch_size=3),
                               h_u8, rtol=1e-5, atol=1e-4)


# --------------------------------------------------------------------------------------------
# estimate_images: resizing rule and context
# --------------------------------------------------------------------------------------------
def _resize_ref(src_wh, dst_wh):
    """Pixel map src -> dst of cv2.resize (centres at integers): x' = s (x + 1/2) - 1/2."""
    sx, sy = dst_wh[0] / src_wh[0], dst_wh[1] / src_wh[1]
    return np.array([[sx, 0, (sx - 1) / 2], [0, sy, (sy - 1) / 2], [0, 0, 1.0]])


def test_estimate_images_pure_rescaling(identity_model_path):
    est = HomographyEstimator.load(identity_model_path)
    image_a = skimage.data.astronaut()  # 512 x 512 RGB
    image_b = cv2.resize(image_a, (1024, 1024), interpolation=cv2.INTER_LINEAR)  # 2x
    h = est.estimate_images(image_a, image_b, EstimateOptions(search="none"))
    assert h.shape == (3, 3) and h.dtype == np.float64
    expected = np.array([[0.5, 0, -0.25], [0, 0.5, -0.25], [0, 0, 1]])
    np.testing.assert_allclose(h, expected, atol=1e-9)
    # The half-pixel offset is real: warping image_a by H reproduces cv2's 2x resize.
    gray_a = cv2.cvtColor(image_a, cv2.COLOR_RGB2GRAY).astype(np.float32)
    gray_b = cv2.resize(gray_a, (1024, 1024), interpolation=cv2.INTER_LINEAR)
    warped = cv2.warpPerspective(gray_a, h, (1024, 1024),
                                 flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    inner = (slice(2, -2), slice(2, -2))
    assert np.abs(warped - gray_b)[inner].max() < 1.0
    # Images of different sizes and aspect ratios, colour vs gray, float vs uint8.
    image_c = cv2.resize(image_a, (300, 700), interpolation=cv2.INTER_AREA)
    h_ca = est.estimate_images(image_c[..., 0] / 255.0, image_a, EstimateOptions(search="none"))
    np.testing.assert_allclose(h_ca, np.linalg.inv(_resize_ref((300, 700), (512, 512))), atol=1e-9)


def test_prepare_image_gray_conversion():
    rgb = skimage.data.astronaut()[:50, :60]
    ref = (rgb.astype(np.float64) @ [0.299, 0.587, 0.114]) / 255  # ITU-R 601 luma
    np.testing.assert_allclose(image_input.prepare_image(rgb), ref, atol=2e-3)
    np.testing.assert_allclose(
        image_input.prepare_image(rgb[..., ::-1].copy(), channel_order="bgr"),
        ref, atol=2e-3)
    alpha = np.random.default_rng(0).integers(0, 256, rgb.shape[:2], dtype=np.uint8)
    rgba = np.concatenate([rgb, alpha[..., None]], axis=-1)
    np.testing.assert_allclose(image_input.prepare_image(rgba), ref * alpha / 255, atol=2e-3)
    np.testing.assert_allclose(image_input.prepare_image(rgb[..., :1] / 255.0), rgb[..., 0] / 255,
                               atol=1e-6)


def test_estimate_images_maps_patch_estimate_to_image_frames(rng):
    h_patch = paper_homography(rng)
    est = HomographyEstimator([constant_stage(h_patch)])
    image = skimage.data.camera()  # 512 x 512 gray
    image_b = cv2.resize(image, (640, 480), interpolation=cv2.INTER_AREA)
    got = est.estimate_images(image, image_b, EstimateOptions(search="none"))  # the network's path
    t = np.array([[1, 0, 96.0], [0, 1, 56.0], [0, 0, 1]])  # central 128 square of 320 x 240
    s_a, s_b = _resize_ref((512, 512), (320, 240)), _resize_ref((640, 480), (320, 240))
    want = np.linalg.inv(s_a) @ t @ h_patch @ np.linalg.inv(t) @ s_b
    np.testing.assert_allclose(got, want / want[2, 2], rtol=1e-5, atol=1e-5)


def test_estimate_images_hierarchy_uses_image_context():
    """Stage 2 gets the patch cropped from the warped 320 x 240 image_a (not zero-filled)."""
    image = skimage.data.camera()
    h1 = geometry.translation(-30.0, 20.0)  # brings 30 px of image beyond the patch border in
    gain = 0.8
    est = HomographyEstimator([constant_stage(h1, "c1"), _spy_stage(gain, np.eye(3), "spy")])
    # same size: S_a = S_b = 320 x 240 resize
    got = est.estimate_images(image, image, EstimateOptions(search="none"))
    # (a uint8 image is resized in uint8, as the training data: issue 48 item 6)
    work = cv2.resize(image, (320, 240), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
    t = geometry.translation(96, 56)
    full = cv2.warpPerspective(work, t @ h1 @ np.linalg.inv(t), (320, 240),
                               flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    seen = full[56:56 + S, 96:96 + S]
    zero_filled = cv2_warp(work[56:56 + S, 96:96 + S], h1)
    assert abs(seen.mean() - zero_filled.mean()) > 0.02  # the two readings are distinguishable
    h_patch = h1 @ _spy_expected_h(np.eye(3), gain, seen)
    s = _resize_ref((512, 512), (320, 240))
    want = np.linalg.inv(s) @ t @ h_patch @ np.linalg.inv(t) @ s
    np.testing.assert_allclose(got, want / want[2, 2], rtol=1e-5, atol=1e-4)


# --------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def identity_estimator():
    return HomographyEstimator([constant_stage(np.eye(3), "ident")])


_OK = np.zeros((S, S), np.uint8)


@pytest.mark.parametrize("patch_a, patch_b, fragment", [
    (np.zeros((64, 64), np.uint8), _OK, "(64, 64)"),
    (np.zeros((S, S, 3), np.uint8), _OK, "(128, 128, 3)"),
    (_OK, np.zeros((2, S, S, 2), np.uint8), "(2, 128, 128, 2)"),
    (np.zeros((1, 1, S, S, 1), np.uint8), _OK, "(1, 1, 128, 128, 1)"),
    (np.zeros((S,), np.uint8), _OK, "(128,)"),
    (np.zeros((0, S, S), np.uint8), np.zeros((0, S, S), np.uint8), "(0, 128, 128)"),
    (np.zeros((2, S, S), np.uint8), np.zeros((3, S, S), np.uint8), "(3, 128, 128)"),
    (np.full((S, S), 200.0), _OK, "(128, 128)"),          # float outside [0, 1]
    (np.full((S, S), np.nan, np.float32), _OK, "(128, 128)"),
    (np.zeros((S, S), np.int64), _OK, "int64"),
    (np.array([["a"]]), _OK, "<U1"),
    (None, _OK, "None"),
])
def test_estimate_bad_input(identity_estimator, patch_a, patch_b, fragment):
    with pytest.raises(ValueError) as info:
        identity_estimator.estimate(patch_a, patch_b)
    assert fragment in str(info.value)


@pytest.mark.parametrize("image, fragment", [
    (np.zeros((10, 12, 2), np.uint8), "(10, 12, 2)"),
    (np.zeros((1, 10, 12, 3), np.uint8), "(1, 10, 12, 3)"),
    (np.zeros((0, 12), np.uint8), "(0, 12)"),
    (np.zeros((12,), np.uint8), "(12,)"),
    (np.full((10, 12), 2.0), "(10, 12)"),
])
def test_estimate_images_bad_input(identity_estimator, image, fragment):
    with pytest.raises(ValueError) as info:
        identity_estimator.estimate_images(image, np.zeros((10, 12), np.uint8))
    assert fragment in str(info.value)


def test_bad_model_is_rejected():
    x = keras.Input((S, S, 2), name="pair")
    with pytest.raises(ValueError, match="patch_a and patch_b"):
        HomographyEstimator([keras.Model(x, keras.layers.Dense(8)(keras.layers.Flatten()(x)))])


# --------------------------------------------------------------------------------------------
# SavedModel export (once per module) and the binaries
# --------------------------------------------------------------------------------------------
def _run(module, *args, cwd=None):
    env = dict(os.environ, TF_CPP_MIN_LOG_LEVEL="2", PYTHONPATH=REPO)
    return subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True,
                          env=env, cwd=cwd or REPO, timeout=300)


@pytest.fixture(scope="module")
def exported(saved, tmp_path_factory):
    """The single-stage model exported by the library (in this process: the fast suite)."""
    out = tmp_path_factory.mktemp("export") / "saved_model"
    return Path(export.export_saved_model(HomographyEstimator([saved["single"]]), out))


@pytest.fixture(scope="module")
def exported_by_binary(saved, tmp_path_factory):
    """The single-stage model exported with the export binary (a new process importing
    TensorFlow: the slow suite)."""
    out = tmp_path_factory.mktemp("export_binary") / "saved_model"
    proc = _run("experiments.export", f"--model={saved['root'] / 'single.keras'}",
                f"--output={out}", "--check_pairs=3")
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out, json.loads(proc.stdout), proc


@pytest.mark.slow
def test_export_binary_reports_agreement(exported_by_binary):
    _, report, proc = exported_by_binary
    assert report["ok"] is True and report["kind"] == "single" and report["pairs"] == 3
    assert report["max_abs_diff"] <= 1e-3 and report["max_abs_diff_estimate"] <= 1e-3
    assert "export: export check passed" in proc.stderr  # issue 62: the wording


def test_saved_model_matches_keras_model(exported, saved, pairs):
    import tensorflow as tf

    path = exported
    a, b, _ = pairs
    fn = tf.saved_model.load(str(path)).signatures["serving_default"]
    specs = fn.structured_input_signature[1]
    assert {k: (v.dtype, tuple(v.shape)) for k, v in specs.items()} == {
        "patch_a": (tf.uint8, (None, S, S, 1)), "patch_b": (tf.uint8, (None, S, S, 1))}
    out = fn(patch_a=tf.constant(a), patch_b=tf.constant(b))["homography"]
    assert out.dtype == tf.float32 and tuple(out.shape) == (4, 3, 3)
    ref = _direct(saved["single"], a.astype(np.float32) / 255, b.astype(np.float32) / 255)
    np.testing.assert_allclose(out.numpy(), ref, rtol=1e-4, atol=1e-3)
    # Refuses to overwrite without the flag, and never deletes a non-SavedModel folder.
    with pytest.raises(FileExistsError, match="overwrite"):
        export.export_saved_model(HomographyEstimator([saved["single"]]), path)
    with pytest.raises(FileExistsError, match="not a SavedModel"):
        export.export_saved_model(HomographyEstimator([saved["single"]]), path.parent.parent,
                                  overwrite=True)


def test_export_overwrite_keeps_the_users_files_and_a_failed_write_keeps_the_old_export(
        saved, pairs, tmp_path, monkeypatch):
    """--overwrite replaces only what an export writes (the user's own files in the folder stay),
    and a write that fails midway (here: a partial file, then TensorFlow's disk-full error)
    leaves the old export whole and loadable, raises OSError naming the folder and the cause,
    and leaves no temporary folder behind."""
    import tensorflow as tf

    a, b, _ = pairs
    out = tmp_path / "out"
    export.export_saved_model(HomographyEstimator([saved["single"]]), out)
    (out / "README.md").write_text("mine")
    (out / "client").mkdir()
    (out / "client" / "app.py").write_text("print('mine')")
    export.export_saved_model(HomographyEstimator([saved["stage1"]]), out, overwrite=True)
    assert (out / "README.md").read_text() == "mine"
    assert (out / "client" / "app.py").read_text() == "print('mine')"

    def serve(path):
        fn = tf.saved_model.load(str(path)).signatures["serving_default"]
        return fn(patch_a=tf.constant(a), patch_b=tf.constant(b))["homography"].numpy()

    ref = _direct(saved["stage1"], a.astype(np.float32) / 255, b.astype(np.float32) / 255)
    np.testing.assert_allclose(serve(out), ref, rtol=1e-4, atol=1e-3)  # the new model's
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}

    def disk_full(estimator, path):  # the archive's write, failing midway
        (Path(path) / "saved_model.pb").write_bytes(b"partial")
        raise tf.errors.ResourceExhaustedError(None, None, "No space left on device")

    monkeypatch.setattr(export, "_write_archive", disk_full)
    with pytest.raises(OSError, match=f"cannot write the SavedModel to {out}: .*No space left"):
        export.export_saved_model(HomographyEstimator([saved["single"]]), out, overwrite=True)
    monkeypatch.undo()
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    np.testing.assert_allclose(serve(out), ref, rtol=1e-4, atol=1e-3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_load_refuses_an_unknown_compute_dtype(identity_model_path):
    """A float32 model (nothing to rebuild) still refuses a precision that is not one."""
    with pytest.raises(ValueError, match=r"compute_dtype must be None .*'bogus'"):
        HomographyEstimator.load(identity_model_path, compute_dtype="bogus")
    assert HomographyEstimator.load(identity_model_path, compute_dtype="bfloat16").num_stages == 1


@pytest.mark.parametrize("tolerance", ["-1", "nan", "inf"])
def test_export_binary_refuses_a_bad_tolerance_before_writing(tmp_path, tolerance):
    proc = _run("experiments.export", f"--output={tmp_path / 'out'}", f"--tolerance={tolerance}")
    assert proc.returncode == 1
    assert "--tolerance must be a finite number >= 0" in proc.stderr
    assert not (tmp_path / "out").exists()


BAD_REQUESTS_SCRIPT = r"""
import json, sys
import numpy as np
import tensorflow as tf
fn = tf.saved_model.load(sys.argv[1]).signatures["serving_default"]
good = np.zeros((2, 128, 128, 1), np.uint8)
requests = {"rank 3": (np.zeros((1, 128, 128), np.uint8),) * 2,
            "64x64": (np.zeros((1, 64, 64, 1), np.uint8),) * 2,
            "rank 5": (np.zeros((1, 1, 128, 128, 1), np.uint8),) * 2,
            "3 channels": (np.zeros((1, 128, 128, 3), np.uint8),) * 2,
            "float32": (good.astype(np.float32),) * 2,
            "batch 2 vs 1": (good, good[:1])}
out = {}
for name, (a, b) in requests.items():
    try:
        fn(patch_a=tf.constant(a), patch_b=tf.constant(b))
        out[name] = "accepted"
    except tf.errors.InvalidArgumentError as e:
        out[name] = "InvalidArgumentError"
    except Exception as e:
        out[name] = type(e).__name__
out["good"] = list(fn(patch_a=tf.constant(good), patch_b=tf.constant(good))["homography"].shape)
print(json.dumps(out))
"""


@pytest.mark.slow
def test_saved_model_rejects_bad_requests_without_crashing(exported):
    """serving_default checks rank, size, channels, dtype and batch in the graph: a [1, 128, 128]
    request used to abort the whole process (SIGABRT in oneDNN), [1, 64, 64, 1] and
    [1, 1, 128, 128, 1] returned a homography. Run in a subprocess: an abort fails this test."""
    path = exported
    env = dict(os.environ, TF_CPP_MIN_LOG_LEVEL="2")
    proc = subprocess.run([sys.executable, "-c", BAD_REQUESTS_SCRIPT, str(path)],
                          capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-3000:])
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out.pop("good") == [2, 3, 3]
    assert out == {name: "InvalidArgumentError" for name in out}, out


@pytest.mark.slow  # (5 s: a hierarchy's SavedModel export; make test-all)
def test_saved_model_hierarchy_matches_estimator(saved, pairs, tmp_path):
    a, b, _ = pairs
    est = HomographyEstimator([saved["stage1"], saved["stage2"]])
    path = export.export_saved_model(est, tmp_path / "hier")
    got = export.run_saved_model(path, a, b)
    ref, _ = _hierarchy_reference(saved["stage1"], saved["stage2"], a, b)
    # TF bilinear warp vs OpenCV's 1/32-px quantized one between stages: tiny corner differences.
    assert np.max(geometry.corner_errors(got.astype(np.float64), ref)) < 0.05
    report = export.verify_export(path, est, a, b)
    assert report["ok"] and report["max_abs_diff"] < 1e-3


def test_mixed_precision_model_estimates_and_exports_in_float32(pairs, tmp_path):
    """A model saved in mixed bfloat16 (as the shipped weights were trained) is rebuilt to
    compute in float32 on load: the estimate equals a float32 build with the same weights, does
    not depend on the batch size, and the SavedModel export passes its own check (in bfloat16 the
    eager estimate and the graph differed by ~0.1 on the shipped stage 1's H entries)."""
    a, b, _ = pairs
    with keras_policy("mixed_bfloat16"):
        mixed = _random_stage(11, "stn_homography")
    mixed.save(tmp_path / "mixed.keras")
    reference = models.build_stn_homography()
    reference.set_weights(mixed.get_weights())
    ref = _direct(reference, a.astype(np.float32) / 255, b.astype(np.float32) / 255)

    est = HomographyEstimator.load(tmp_path / "mixed.keras")
    assert {layer.dtype_policy.name for layer in est.stages[0]._flatten_layers()} == {"float32"}
    got = est.estimate(a, b, EstimateOptions(search="none"))
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(est.estimate(a, b, EstimateOptions(search="none"), batch_size=1),
                               got, rtol=1e-5, atol=1e-5)
    assert np.max(geometry.corner_errors(got, np.broadcast_to(np.eye(3), got.shape))) > 0.1

    kept = HomographyEstimator.load(tmp_path / "mixed.keras", compute_dtype=None)
    assert "mixed_bfloat16" in {layer.dtype_policy.name
                                for layer in kept.stages[0]._flatten_layers()}
    assert np.max(geometry.corner_errors(kept.estimate(a, b, EstimateOptions(search="none")),
                  ref)) < 0.5  # bfloat16 rounding only

    report = export.verify_export(export.export_saved_model(est, tmp_path / "exported"), est, a, b)
    assert report["ok"] and report["max_abs_diff"] < 1e-3 and report["max_abs_diff_estimate"] < 1e-3
    with pytest.raises(ValueError, match="batch_size"):
        est.estimate(a, b, EstimateOptions(search="none"), batch_size=0)


@pytest.mark.slow  # (a binary end to end, 6-15 s; make test-all)
def test_benchmark_estimator_binary(tmp_path):
    """The estimator and the latency benchmark time the model they are given, in the precision
    asked for: a 2-stage hierarchy saved in mixed bfloat16 is reported with its 2 stages and,
    with --compute_dtype=as_saved, its saved policy (float32 by default); the ratio is the ratio
    of the two timings."""
    with keras_policy("mixed_bfloat16"):
        stages = [constant_stage(np.eye(3), f"c{k}") for k in (1, 2)]
    for k, stage in enumerate(stages, start=1):
        stage.save(tmp_path / f"stage{k}.keras")
    manifest = model_files.write_manifest(tmp_path / "h.json", [tmp_path / "stage1.keras",
                                                                tmp_path / "stage2.keras"])
    out = tmp_path / "bench.json"
    res = subprocess.run([sys.executable, "-m", "experiments.benchmark_estimator",
                          f"--model={manifest}", "--compute_dtype=as_saved", "--runs=1",
                          "--warmup=0", "--large_batch=2", "--seed=3", f"--json_out={out}"],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    result = json.loads(out.read_text())
    assert result["model"] == str(manifest) and result["stages"] == 2
    assert result["policy"] == "mixed_bfloat16"
    assert (result["runs"], result["seed"], result["tta"], result["search"]) == (
        1, 3, "none", "none")
    for key in ("estimate_batch1_ms", "benchmark_d_e_ms", "estimate_batch2_ms_per_pair",
                "benchmark_l_m_ms"):
        assert result[key] > 0, key
    assert result["ratio"] == pytest.approx(result["estimate_batch1_ms"]
                                            / result["benchmark_d_e_ms"])


@pytest.mark.slow  # (a binary end to end, 6-15 s; make test-all)
def test_predict_binary(identity_model_path, tmp_path):
    image_a = skimage.data.coffee()  # 600 x 400 RGB
    image_b = cv2.resize(image_a, (300, 200), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(tmp_path / "a.png"), image_a[..., ::-1])
    cv2.imwrite(str(tmp_path / "b.png"), image_b[..., ::-1])
    # the network's path (no whole-image ECC, which moves the estimate off the exact resize map
    # by up to 0.07 in H on this resampled pair): the frames alone, to float rounding
    proc = _run("experiments.predict", f"--image_a={tmp_path / 'a.png'}",
                f"--image_b={tmp_path / 'b.png'}", f"--model={identity_model_path}",
                f"--output_dir={tmp_path / 'out'}", "--refine=none")
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout)
    np.testing.assert_allclose(result["homography"],
                               np.linalg.inv(_resize_ref((600, 400), (300, 200))), atol=1e-9)
    assert result["image_a_size"] == [600, 400] and result["image_b_size"] == [300, 200]
    png = cv2.imread(result["overlay_png"])
    top = png.shape[0] - 400  # the captions' band above both panels
    assert png is not None and png.shape[1:] == (600 + 8 + 300 + 8, 3) and 10 < top < 60
    assert png[:top, :600].max() > 200 and png[:top, 608:908].max() > 200  # captions written
    np.testing.assert_array_equal(png[top + 50, 300], image_a[50, 300, ::-1])  # panel 1: image_a
    assert json.loads((tmp_path / "out" / "a__b_homography.json").read_text()) == result
    # With the identity model, image_a warped onto image_b equals image_b (gray overlay):
    blend = png[top:top + 200, 608:908].astype(np.float64)
    assert np.abs(blend[..., 1] - blend[..., 0])[4:-4, 4:-4].mean() < 3.0
    assert result["implausible"] is False and result["max_corner_shift_px"] < 1e-6
    assert "implausible" not in proc.stderr
    assert result["refine"] == "none" and result["refined"] is False
    assert result["retry_tta"] == "none" and result["retried"] is False
    # A model whose estimate moves a patch corner by 60 px (trained range: 32) gets a warning;
    # with --retry_tta it is estimated again (each symmetry's estimate moves a corner 60 px too).
    # --search=none: the network's estimate is what is tested (the search could align the pair);
    # --features=none --coarse=none --refine=none --verify=none: EstimateOptions()' path, not
    # photographs()' (whose feature start would align the pair: a with itself).
    far = np.eye(3)
    far[0, 2] = 60.0
    constant_stage(far, "far").save(tmp_path / "far.keras")
    proc = _run("experiments.predict", f"--image_a={tmp_path / 'a.png'}",
                f"--image_b={tmp_path / 'a.png'}", f"--model={tmp_path / 'far.keras'}",
                f"--output_dir={tmp_path / 'far'}", "--retry_tta=flips", "--search=none",
                "--features=none", "--coarse=none", "--refine=none", "--verify=none")
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout)
    assert result["implausible"] is True and result["retried"] is True
    assert result["retry_tta"] == "flips" and result["search"] == "none"
    assert result["searched"] is False
    # the kept estimate is the 60-px shift seen through the chosen flip G, inv(G) @ far @ G,
    # mapped from the central patch to the 600 x 400 image (estimate_images' rule, written above)
    g = _PATCH_SYMMETRIES[result["tta_choice"]]
    s_a, t = _resize_ref((600, 400), (320, 240)), geometry.translation(96, 56)
    want = np.linalg.inv(s_a) @ t @ np.linalg.inv(g) @ far @ g @ np.linalg.inv(t) @ s_a
    np.testing.assert_allclose(result["homography"], want / want[2, 2], atol=1e-4)
    assert abs(result["homography"][0][2]) == pytest.approx(60.0 * 600 / 320, abs=1e-3)
    assert "warning: the estimate is implausible" in proc.stderr and "60.0 px" in proc.stderr
    assert "note: the estimate was flagged and estimated again" in proc.stderr
    # a network 8 px off on a pair of identical images: by default the feature start (SIFT
    # matches) finds the identity and says so (the network's estimate was replaced); without it
    # (--features=none) the search does, and says so
    off = geometry.translation(8.0, 0.0)
    constant_stage(off, "off").save(tmp_path / "off.keras")
    for flags, found, note in (([], "feature_start", "the estimate was made from a start found "
                                                     "by OpenCV SIFT matches, which aligned"),
                               (["--features=none"], "search_found",
                                "the network's estimate aligned the images poorly; the search")):
        proc = _run("experiments.predict", f"--image_a={tmp_path / 'a.png'}",
                    f"--image_b={tmp_path / 'a.png'}", f"--model={tmp_path / 'off.keras'}",
                    f"--output_dir={tmp_path / ('off' + ''.join(flags))}", *flags)
        assert proc.returncode == 0, proc.stderr[-3000:]
        result = json.loads(proc.stdout)
        assert result[found] is True
        assert result["feature_start" if found == "search_found" else "search_found"] is False
        assert np.abs(np.array(result["homography"]) - np.eye(3)).max() < 0.05
        assert f"predict: note: {note}" in proc.stderr
    # issue 64: the network's own estimate (8 px in the 320 x 240 work frame, 8 x 600 / 320 px
    # in image_a's) and how far the result is from it at the work image's corners
    assert result["network_homography"][0][2] == pytest.approx(8.0 * 600 / 320, abs=1e-3)
    assert result["network_move_px"] == pytest.approx(8.0, abs=0.5)

    (tmp_path / "junk.png").write_text("not an image")
    for bad, what in ((tmp_path / "junk.png", "cannot read image_a"),
                      (tmp_path / "missing.png", "does not exist")):
        proc = _run("experiments.predict", f"--image_a={bad}", f"--image_b={tmp_path / 'b.png'}",
                    f"--model={identity_model_path}", f"--output_dir={tmp_path / 'out2'}")
        assert proc.returncode != 0
        assert what in proc.stderr and str(bad) in proc.stderr
        assert "Traceback" not in proc.stderr


@pytest.mark.slow
def test_predict_takes_the_thresholds_flag(identity_model_path, tmp_path):
    """--thresholds changes the numbers of the checks as in benchmark_camera_pairs: with
    max_corner_std below the pair's corner precision the estimate is flagged, and the JSON's
    thresholds say so (the others the defaults'); a bad item is a clear error."""
    image_a = skimage.data.coffee()
    noise = np.random.default_rng(0).normal(0, 4, image_a.shape)  # a residual: a std above 0
    image_b = np.clip(image_a + noise, 0, 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "a.png"), image_a[..., ::-1])
    cv2.imwrite(str(tmp_path / "b.png"), image_b[..., ::-1])
    args = ("experiments.predict", f"--image_a={tmp_path / 'a.png'}",
            f"--image_b={tmp_path / 'b.png'}", f"--model={identity_model_path}", "--refine=none")
    proc = _run(*args, f"--output_dir={tmp_path / 'out'}", "--thresholds=max_corner_std=1e-12")
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout)
    assert result["corner_std_px"] > 1e-12 and result["implausible"] is True
    assert result["thresholds"]["max_corner_std"] == 1e-12 and result["verify"] == "ecc"
    assert {k: v for k, v in result["thresholds"].items() if k != "max_corner_std"} == {
        k: v for k, v in json.loads(json.dumps(EstimateOptions().to_json()["thresholds"])).items()
        if k != "max_corner_std"}
    proc = _run(*args, f"--output_dir={tmp_path / 'bad'}", "--thresholds=max_corner_std")
    assert proc.returncode != 0 and "--thresholds takes name=value" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_predict_checks_its_output_dir_first(identity_model_path, tmp_path):
    """An --output_dir that is a file, or under one, is a clear error before any work."""
    image = tmp_path / "a.png"
    cv2.imwrite(str(image), skimage.data.camera())
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    for out in (blocker, blocker / "sub"):
        proc = _run("experiments.predict", f"--image_a={image}", f"--image_b={image}",
                    f"--model={identity_model_path}", f"--output_dir={out}")
        assert proc.returncode != 0 and "Traceback" not in proc.stderr
        assert "predict: --output_dir: output directory" in proc.stderr and str(out) in proc.stderr


def test_predict_outputs_of_pairs_with_the_same_names_do_not_collide(identity_model_path,
                                                                     tmp_path):
    """Two pairs whose images share base names used to overwrite each other's outputs in one
    --output_dir; a re-run of the same pair still replaces its own. (The predict binary's own
    call of ``align_image_files`` is tested above; here the library call, in-process.)"""
    from stnh_tf.inference import image_files as alignment

    photos = {"one": skimage.data.camera(), "two": skimage.data.coffee()[..., ::-1]}
    for name, photo in photos.items():
        (tmp_path / name).mkdir()
        cv2.imwrite(str(tmp_path / name / "a.png"), photo)
        cv2.imwrite(str(tmp_path / name / "b.png"), photo)
    out = tmp_path / "out"
    results = []
    for name in ("one", "two", "one"):
        results.append(alignment.align_image_files(
            str(tmp_path / name / "a.png"), str(tmp_path / name / "b.png"),
            model=identity_model_path, output_dir=str(out)))
    assert [os.path.basename(r["overlay_png"]) for r in results] == \
        ["a__b_overlay.png", "a__b-2_overlay.png", "a__b_overlay.png"]
    assert sorted(p.name for p in out.iterdir() if p.name != alignment.PREDICT_LOCK) == [
        "a__b-2_homography.json", "a__b-2_overlay.png", "a__b_homography.json", "a__b_overlay.png"]
    assert json.loads((out / "a__b-2_homography.json").read_text())["image_a"] == \
        str(tmp_path / "two" / "a.png")
    assert json.loads((out / "a__b_homography.json").read_text())["image_a"] == \
        str(tmp_path / "one" / "a.png")
    assert cv2.imread(str(out / "a__b-2_overlay.png")).shape[0] > photos["two"].shape[0]
    # the first pair's outputs deleted: a re-run of the second still replaces its own (it took
    # the free a__b and left a stale a__b-2 before; a review's find)
    for end in ("_homography.json", "_overlay.png"):
        (out / f"a__b{end}").unlink()
    again = alignment.align_image_files(str(tmp_path / "two" / "a.png"),
                                        str(tmp_path / "two" / "b.png"),
                                        model=identity_model_path, output_dir=str(out))
    assert os.path.basename(again["overlay_png"]) == "a__b-2_overlay.png"
    assert sorted(p.name for p in out.iterdir() if p.name != alignment.PREDICT_LOCK) == [
        "a__b-2_homography.json", "a__b-2_overlay.png"]


@pytest.mark.slow  # (predict's subprocess: the make test time)
def test_predict_overlay_cut_short_keeps_the_earlier_one(identity_model_path, tmp_path,
                                                        monkeypatch):
    """A re-run of a pair wrote its overlay PNG in place (``cv2.imwrite``): a failure while
    writing it (a full disk, the process killed) left a truncated overlay beside the earlier
    JSON; later, a failure while writing the JSON left the new overlay beside the earlier JSON
    (a review's find). Both are now written to temporary files first and renamed together: where
    writing either fails, the earlier overlay and JSON are left byte for byte, no temporary file
    stays, and the error is an ``AlignmentError`` naming the files."""
    from stnh_tf import paths
    from stnh_tf.inference import image_files as alignment

    a, b, out = tmp_path / "a.png", tmp_path / "b.png", tmp_path / "out"
    cv2.imwrite(str(a), skimage.data.camera())
    cv2.imwrite(str(b), skimage.data.camera())
    alignment.align_image_files(str(a), str(b), model=identity_model_path, output_dir=str(out))
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    cv2.imwrite(str(b), skimage.data.camera()[::-1])  # another image_b: another overlay
    write = paths.write_synced
    for failing in (".png", ".json"):
        def disk_full(path, data):
            write(path, data[:10])
            if failing in str(path):
                raise OSError(28, "No space left on device")

        monkeypatch.setattr(paths, "write_synced", disk_full)
        with pytest.raises(alignment.AlignmentError,
                           match=re.escape(str(out / "a__b_overlay.png"))):
            alignment.align_image_files(str(a), str(b), model=identity_model_path,
                                        output_dir=str(out))
        assert {p.name: p.read_bytes() for p in out.iterdir()} == before, failing
    monkeypatch.undo()
    alignment.align_image_files(str(a), str(b), model=identity_model_path, output_dir=str(out))
    assert (out / "a__b_overlay.png").read_bytes() != before["a__b_overlay.png"]


def test_implausibility_check_with_the_identity_model(identity_model_path):
    """``evaluation.implausibility_check`` on the bundled pairs with the identity model: the
    ordinary MACE is the identity's and every case's flagged fraction is the fraction of pairs
    whose plain NumPy NCC of patch_a and that case's patch_b is below the threshold."""
    from stnh_tf.inference import estimator as inference
    from stnh_tf.inference import shipped_weights
    from stnh_tf.evaluation import mace as evaluation

    result = evaluation.implausibility_check(identity_model_path,
                                            options=EstimateOptions(search="none"))
    arrays = shipped_weights.bundled_pairs()
    a = arrays["patch_a"][..., 0].astype(np.float64)
    b = arrays["patch_b"][..., 0].astype(np.float64)
    cases = {"ordinary": b, "other_photograph": np.roll(b, len(b) // 2, axis=0),
             "rotated_180": b[:, ::-1, ::-1], "moved_80px": np.roll(a, (80, 80), axis=(1, 2))}

    def ncc(x, y):
        x, y = x - x.mean(), y - y.mean()
        return (x * y).sum() / np.sqrt((x * x).sum() * (y * y).sum())

    for case, patches_b in cases.items():
        expected = np.mean([ncc(x, y) < EstimateOptions().thresholds.min_alignment_ncc
                            for x, y in zip(a, patches_b)])
        assert result[case]["count"] == len(a) == 60
        assert result[case]["flagged"] == pytest.approx(expected, abs=1e-9), case
    assert result["moved_80px"]["flagged"] > 0.5
    corners = np.array([[0, 0, 1], [128, 0, 1], [128, 128, 1], [0, 128, 1]], np.float64).T
    moved = np.einsum("nij,jk->nik", arrays["h_ba"].astype(np.float64), corners)
    moved = moved[:, :2] / moved[:, 2:]
    identity_errors = np.linalg.norm(moved - corners[None, :2], axis=1).mean(axis=1)
    assert result["ordinary"]["mace"] == pytest.approx(identity_errors.mean(), rel=1e-9)
    assert result["ordinary"]["mace_median"] == pytest.approx(np.median(identity_errors), rel=1e-9)
    assert result["ordinary"]["worse_than_identity"] == 0  # the identity itself
    assert result["refine"] == "none" and result["ordinary"]["refined"] == 0.0
    assert result["retry_tta"] == "none" and result["ordinary"]["retried"] == 0.0
    assert result["search"] == "none" and result["ordinary"]["searched"] == 0.0


@pytest.mark.slow  # (4 s: the search on both OpenCV paths; make test-all)
def test_search_stability_measures_both_opencv_paths_and_moved_starts(pairs, identity_model_path):
    """stnh_tf.evaluation.search_stability with the identity model: every pair's identity estimate
    aligns it poorly (NCC recomputed here below 0.9), so every pair is searched; the search's
    results agree between OpenCV's two paths and from starts moved by 0.1 px, and beat the
    identity."""
    from stnh_tf.evaluation import search_stability

    a, b, hs = pairs
    a, b = a.astype(np.float32) / 255.0, b.astype(np.float32) / 255.0
    est = HomographyEstimator.load(identity_model_path)
    out = search_stability.search_stability(est, a, b, hs, perturbations=(0.1,))
    poorly = sum(ncc_reference(x[..., 0], y[..., 0], np.eye(3)) < 0.9 for x, y in zip(a, b))
    assert out["pairs"] == 4 and out["searched_network"] == poorly == 4
    assert out["optimized"]["searched"] == out["unoptimized"]["searched"] == 4
    assert out["differ_between_paths"] == 0 and out["differ_moved_0.1px"] == 0
    identity = float(geometry.mean_corner_error(np.broadcast_to(np.eye(3), hs.shape), hs))
    assert out["optimized"]["mace"] < identity
    assert out["optimized"]["mace"] == pytest.approx(out["unoptimized"]["mace"], abs=0.01)
    assert cv2.useOptimized()  # restored


def _smooth_patch(seed):
    return cv2.GaussianBlur(np.random.default_rng(seed).random((128, 128), np.float32), (0, 0), 2)


def test_legacy_keywords_warn_and_equal_the_options(identity_model_path):
    est = HomographyEstimator.load(identity_model_path)
    a = _smooth_patch(5)
    b = cv2_warp(a, geometry.translation(1.0, 0.0))
    with pytest.warns(DeprecationWarning, match="options=EstimateOptions"):
        legacy = est.estimate(a, b, search="none", refine="ecc")
    new = est.estimate_with_info(a, b, EstimateOptions(search="none", refine="ecc"))
    np.testing.assert_allclose(legacy, new.homography, atol=0)
    with pytest.warns(DeprecationWarning, match="last_info"):
        info = est.last_info
    np.testing.assert_array_equal(info["refined"], new.refined)
    with pytest.raises(TypeError, match="batch_size"):
        est.estimate(a, b, 64)
    with pytest.raises(TypeError, match="unexpected"):
        est.estimate(a, b, serach="none")
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        est.estimate(a, b, EstimateOptions(search="none"), batch_size=1)


# --------------------------------------------------------------------------------------------
# Issue 64, item 4: what the network did (Estimate.network_homography / network_move_px)
# --------------------------------------------------------------------------------------------
def _cv2_corner_distance(h1, h2, width, height):
    """Mean distance between where h1 and h2 map the corners (0,0), (w,0), (w,h), (0,h):
    cv2.perspectiveTransform (independent of stnh_tf.geometry)."""
    corners = np.array([[[0, 0], [width, 0], [width, height], [0, height]]], np.float64)
    p1 = cv2.perspectiveTransform(corners, np.asarray(h1, np.float64))[0]
    p2 = cv2.perspectiveTransform(corners, np.asarray(h2, np.float64))[0]
    return float(np.linalg.norm(p1 - p2, axis=1).mean())


def test_estimate_says_how_far_the_result_is_from_the_networks_own(pairs):
    """Patches: a network 3-5 px off the true H, refined by ECC: network_homography is the
    network's output and network_move_px the mean distance (cv2.perspectiveTransform) at the
    patch corners between it and the refined result (several px); without refinement both are
    the network's and the move is 0. Whole images: a network 8 px off on identical images, the
    search finds the identity: the move is measured at the 320 x 240 work image's corners."""
    a, b, hs = pairs
    off = geometry.translation(3.0, -2.0) @ np.array([[1.02, 0.01, 0], [-0.01, 0.99, 0],
                                                      [0, 0, 1]])
    starts = np.stack([h @ off for h in hs])
    starts = starts / starts[:, 2:, 2:]
    est = HomographyEstimator([constant_stage(np.eye(3))])
    est._predict_stage = lambda k, pa, pb, bs: starts.copy()
    got = est.estimate_with_info(a, b, EstimateOptions(refine="ecc", search="none"))
    assert got.refined.all()
    np.testing.assert_allclose(got.network_homography, starts, atol=1e-12)
    want = [_cv2_corner_distance(h, n, S, S) for h, n in zip(got.homography, starts)]
    assert min(want) > 2.0
    np.testing.assert_allclose(got.network_move_px, want, rtol=1e-9)
    plain = est.estimate_with_info(a, b, EstimateOptions.network_only())
    np.testing.assert_array_equal(plain.network_move_px, np.zeros(len(a)))

    image = skimage.data.camera()[100:340, 80:400]  # 320 x 240: work frame = image frame
    est = HomographyEstimator([constant_stage(geometry.translation(8.0, 0.0))])
    res = est.estimate_images_with_info(image, image, EstimateOptions())
    assert res.found[0] and np.abs(res.homography[0] - np.eye(3)).max() < 0.05
    np.testing.assert_allclose(res.network_homography[0], geometry.translation(8.0, 0.0),
                               atol=1e-4)
    assert res.network_move_px[0] == pytest.approx(
        _cv2_corner_distance(res.homography[0], res.network_homography[0], 320, 240), rel=1e-6)
    assert res.network_move_px[0] == pytest.approx(8.0, abs=0.5)


# --------------------------------------------------------------------------------------------
# Issue 62, item 3: the export binary's documents, its check line and its quiet log
# --------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_export_binary_writes_its_documents_and_one_plain_check_line(exported_by_binary, saved):
    """The export binary (the module's export of a single-stage model without a model card)
    writes README.md and signature.json beside saved_model.pb, says in one line on stderr what
    it compared and that the check passed, and prints none of TensorFlow's INFO lines (the
    SavedModel writer's "Assets written to ..." in absl's format, shown before the fix)."""
    import re

    path, report, proc = exported_by_binary
    assert sorted(report["documents"]) == [str(path / "README.md"), str(path / "signature.json")]
    assert report["kept_user_files"] == []
    document = json.loads((path / "signature.json").read_text())
    assert document["model"] == {"source": str(saved["root"] / "single.keras"), "kind": "single",
                                 "num_stages": 1}
    assert document["model_card"] is None
    assert "No model card" in (path / "README.md").read_text()
    lines = [line for line in proc.stderr.splitlines() if "export check" in line]
    assert len(lines) == 1 and lines[0].startswith("export: export check passed: ")
    assert f"max |dH| {report['max_abs_diff']:.2g} <= tolerance 0.001: ok." in lines[0]
    # INFO lines in absl's format (_run sets TF_CPP_MIN_LOG_LEVEL=2: C++ errors such as cuInit's
    # may show; the Python INFO lines did, whatever that level)
    assert re.findall(r"^I\d{4} \d\d:\d\d:\d+\.\d+ +\d+ \S+:\d+\]", proc.stderr,
                      re.MULTILINE) == [], proc.stderr[-3000:]

