"""experiments.ship_weights: the shipped files load as the hierarchy they were made from, and the
model card's bundled check (plain and photometric pairs) equals MACE computed here with NumPy for
stages with a known output.

Stage 1 outputs a chosen H whatever its input and is saved in mixed bfloat16 (as the shipped
CPU-budget weights were trained), stage 2 outputs the identity; so the k-stage estimates are that
H, and their MACE on the bundled pairs is a NumPy corner computation. (That the float32 rebuild
of a mixed-precision model changes input-dependent outputs is tested in test_inference.)
"""

import json
import os

import numpy as np
import pytest

from conftest import keras_policy, ncc_reference, to_bar
from stnh_tf.inference import shipped_weights
from stnh_tf.inference.options import EstimateOptions
from stnh_tf.inference import estimator as inference
from stnh_tf.modeling import models

S = 128


def _constant_run(run_dir, h_pix, mixed):
    with keras_policy("mixed_bfloat16" if mixed else "float32"):
        model = models.build_stn_homography()
    fc2 = model.get_layer("regression").get_layer("fc2")
    kernel, _ = fc2.get_weights()
    fc2.set_weights([np.zeros_like(kernel), to_bar(h_pix).ravel()[:8].astype("float32")])
    os.makedirs(run_dir)
    model.save(os.path.join(run_dir, "model.keras"))
    with open(os.path.join(run_dir, "config.json"), "w") as f:
        json.dump({"stage": 1, "mixed_precision": mixed}, f)
    with open(os.path.join(run_dir, "result.json"), "w") as f:
        json.dump({"final_step": 7, "history": {"loss": [1.0]}}, f)


def _mace_numpy(h, h_true):
    """Mean distance between the patch corners mapped by ``h`` and by each ``h_true``."""
    c = np.array([[0, 0, 1], [S, 0, 1], [S, S, 1], [0, S, 1]], np.float64).T
    p = h @ c
    p = p[:2] / p[2]
    q = np.einsum("nij,jk->nik", h_true, c)
    q = q[:, :2] / q[:, 2:]
    return float(np.linalg.norm(q - p[None], axis=1).mean())


@pytest.fixture(scope="module")
def bundled():
    return shipped_weights.bundled_pairs()


@pytest.mark.slow  # (make test-all)
def test_ship_refresh_check_and_replace_stage(tmp_path, bundled, monkeypatch, narrow):
    # the card's check of the network's estimates (the search would move the constant stages'
    # estimates); the check records that setting
    monkeypatch.setitem(shipped_weights.BUNDLED_CHECK, "search", "none")
    bundled_h_ba = bundled["h_ba"].astype(np.float64)
    h = np.array([[1.05, 0.02, -3.0], [-0.03, 0.97, 4.0], [1e-4, -2e-4, 1.0]])
    _constant_run(tmp_path / "s1", h, mixed=True)
    _constant_run(tmp_path / "s2", np.eye(3), mixed=False)
    out = tmp_path / "weights"
    card = shipped_weights.ship([str(tmp_path / "s1"), str(tmp_path / "s2")], str(out))

    assert sorted(os.listdir(out)) == ["default.json", "model_card.json", "stage1.keras",
                                       "stage2.keras"]
    assert [s["file"] for s in card["stages"]] == ["stage1.keras", "stage2.keras"]
    assert card["stages"][0]["config"]["mixed_precision"] is True
    assert card["stages"][0]["result"] == {"final_step": 7}  # history left out
    est = inference.HomographyEstimator.load(out / "default.json")
    assert est.num_stages == 2

    check = card["bundled_check"]
    assert check["compute_dtype"] == "float32" and check["count"] == len(bundled_h_ba) == 60
    assert check["search"] == "none"
    expected = _mace_numpy(h, bundled_h_ba)
    expected_flags = sum(ncc_reference(a[..., 0], b[..., 0], h) < 0.7
                         for a, b in zip(bundled["patch_a"], bundled["patch_b"]))
    assert check["identity_mace"] == pytest.approx(_mace_numpy(np.eye(3), bundled_h_ba), rel=1e-9)
    assert _mace_numpy(h, np.eye(3)[None]) > 3.0  # the constant H is far from the identity
    for k in (1, 2):
        assert check[f"estimate_mace_{k}_stages"] == pytest.approx(expected, abs=1e-3)
        # the constant H moves corners < 48 px: flagged are the pairs it leaves poorly aligned
        assert check[f"implausible_{k}_stages"] == expected_flags
    assert check["unsearched_estimate_mace_2_stages"] == pytest.approx(expected, abs=1e-3)

    # The photometric pairs: the same check on patch_b changed in brightness, contrast, gamma.
    h_photo = shipped_weights.bundled_pairs(photometric=True)["h_ba"].astype(np.float64)
    per_pair = [_mace_numpy(h, h_true[None]) for h_true in h_photo]
    per_pair_identity = [_mace_numpy(np.eye(3), h_true[None]) for h_true in h_photo]
    assert check["photometric_identity_mace"] == pytest.approx(np.mean(per_pair_identity), rel=1e-9)
    for k in (1, 2):
        assert check[f"photometric_estimate_mace_{k}_stages"] == pytest.approx(np.mean(per_pair),
                                                                               abs=1e-3)
        assert check[f"photometric_worse_than_identity_{k}_stages"] == int(
            np.sum(np.array(per_pair) > np.array(per_pair_identity)))

    # --refresh_check recomputes only the check, atomically, keeping the rest of the card.
    with open(out / "model_card.json") as f:
        stale = json.load(f)
    stale["bundled_check"]["estimate_mace_2_stages"] = -1.0
    stale["note"] = "kept"
    with open(out / "model_card.json", "w") as f:
        json.dump(stale, f)
    refreshed = shipped_weights.refresh_check(str(out))
    assert refreshed["note"] == "kept"
    for key, value in check.items():
        assert refreshed["bundled_check"][key] == (
            pytest.approx(value, rel=1e-6) if isinstance(value, float) else value)
    with open(out / "model_card.json") as f:
        assert json.load(f)["bundled_check"]["estimate_mace_2_stages"] == pytest.approx(
            expected, abs=1e-3)
    assert not os.path.exists(out / "model_card.json.tmp")

    # --replace_stage=2: a new stage 2 (a constant H2) in place of the identity; stage 1's file
    # and card entry stay, the replaced entry becomes the new one's init_from_run, the manifest
    # still names stage1.keras and stage2.keras, and the check follows the new stage.
    h2 = np.array([[0.98, -0.01, 2.0], [0.02, 1.03, -1.5], [-1e-4, 1e-4, 1.0]])
    _constant_run(tmp_path / "s2b", h2, mixed=False)
    before = refreshed
    replaced = shipped_weights.replace_stage(2, str(tmp_path / "s2b"), str(out),
                                             init_from_previous=True)
    assert replaced["stages"][0] == before["stages"][0]
    assert replaced["stages"][1]["source"] == str(tmp_path / "s2b")
    assert replaced["stages"][1]["init_from_run"] == before["stages"][1]
    assert replaced["note"] == "kept"
    assert sorted(os.listdir(out)) == ["default.json", "model_card.json", "stage1.keras",
                                       "stage2.keras"]
    new_check = replaced["bundled_check"]
    assert new_check["estimate_mace_1_stages"] == pytest.approx(expected, abs=1e-3)
    composed = h @ h2  # later stages compose on the right: H_1 @ H_2
    assert new_check["ungated_estimate_mace_2_stages"] == pytest.approx(
        _mace_numpy(composed / composed[2, 2], bundled_h_ba), abs=1e-3)
    est = inference.HomographyEstimator.load(out / "default.json")
    np.testing.assert_allclose(est.estimate(bundled["patch_a"][:2], bundled["patch_b"][:2],
                                            EstimateOptions(gate_stages=False, search="none"))[0],
                               composed / composed[2, 2],
                               atol=1e-3)
    with open(out / "model_card.json") as f:
        assert json.load(f) == replaced
    with pytest.raises(ValueError, match="1..2"):
        shipped_weights.replace_stage(3, str(tmp_path / "s2b"), str(out))
