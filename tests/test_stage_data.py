"""Stage-k data for the hierarchy: residual targets from an oracle with a known error, re-cropped
patches against OpenCV, round trip, determinism across worker counts, the degenerate rule, and
the binary with a real (untrained) stage model."""

import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from conftest import norm_matrix
from stnh_tf.data import stage1, stage_k
from stnh_tf import geometry
from stnh_tf.data import batches
from stnh_tf.data import tfrecords as data

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
QUIET = lambda *a, **k: None


@pytest.fixture(scope="module")
def stage1_data(tmp_path_factory):
    d = str(tmp_path_factory.mktemp("stage1"))
    stage1.make_dataset("bundled", d, "train", seed=0, num_shards=2, max_images=5, log=QUIET)
    stage1.make_dataset("bundled", d, "test", seed=1, num_shards=1, max_images=3, log=QUIET)
    return d


class Oracle:
    """Looks each pair up by its patch_b and returns ``H_ba @ E`` with a known per-pair error
    ``E`` (a small random homography), or the matrices in ``override`` for chosen pairs."""

    def __init__(self, arrays, seed=0, override=None, error_px=4.0):
        rng = np.random.default_rng(seed)
        self.table = {}
        self.errors = {}
        for i in range(len(arrays["h_ba"])):
            key = arrays["patch_b"][i].tobytes()
            corners = geometry.patch_corners().astype(np.float32)
            e = cv2.getPerspectiveTransform(
                corners, corners + rng.uniform(-error_px, error_px, (4, 2)).astype(np.float32))
            self.errors[int(arrays["index"][i])] = e
            self.table[key] = (override or {}).get(int(arrays["index"][i]), arrays["h_ba"][i] @ e)

    def __call__(self, patch_a, patch_b):
        return np.stack([self.table[b.tobytes()] for b in patch_b])

    def __repr__(self):
        return "Oracle()"


def _by_index(arrays):
    return {int(i): k for k, i in enumerate(arrays["index"])}


def test_oracle_with_known_error_gives_exact_residual_targets(stage1_data, tmp_path):
    a1 = data.load_arrays(stage1_data, "train")
    oracle = Oracle(a1)
    out = str(tmp_path / "stage2")
    meta = stage_k.make_stage_dataset(2, stage1_data, out, "train", predict=oracle, log=QUIET)
    assert meta["num_samples"] == len(a1["h_ba"])
    counts = meta["degenerate_predictions"]
    assert counts["non_finite"] == counts["singular"] == 0
    assert counts["accepted"] + counts["outside_context"] == len(a1["h_ba"])
    assert counts["accepted"] >= len(a1["h_ba"]) // 2
    assert data.read_metadata(out)["stage"] == 2
    a2 = data.load_arrays(out, "train")
    pos = _by_index(a1)
    m = norm_matrix()
    for k in range(len(a2["h_ba"])):
        i = pos[int(a2["index"][k])]
        e = oracle.errors[int(a2["index"][k])]
        h_ba = a1["h_ba"][i]
        np.testing.assert_allclose(a2["h_ba"][k], h_ba, atol=1e-6)  # the original truth is kept
        h_prev = h_ba @ e
        corners = cv2.perspectiveTransform(geometry.patch_corners()[None], h_prev)[0]
        if np.all(np.abs(corners - geometry.patch_corners()) <= 32):
            np.testing.assert_allclose(a2["h_prev"][k], h_prev / h_prev[2, 2], atol=1e-4)
        else:  # clipped onto the context border: corners inside, and the others unchanged
            h_prev = a2["h_prev"][k]
            got = cv2.perspectiveTransform(geometry.patch_corners()[None], h_prev)[0]
            np.testing.assert_allclose(got, np.clip(corners, -32, 160), atol=1e-2)
        # Residual target inv(H_prev) @ H_ba (= inv(E) where accepted), normalized with M.
        target = m @ np.linalg.inv(h_prev) @ h_ba @ np.linalg.inv(m)
        np.testing.assert_allclose(a2["h_bar"][k], (target / target[2, 2]).reshape(9)[:8],
                                   atol=1e-5)
        # patch_a_2 = context warped by T(32) @ H_prev, cropped: computed here with OpenCV.
        t = np.array([[1, 0, 32], [0, 1, 32], [0, 0, 1.0]])
        ref = cv2.warpPerspective(a1["context_a"][i].astype(np.float32), t @ h_prev, (128, 128),
                                  flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
        err = np.abs(a2["patch_a"][k, ..., 0] * 255 - ref)
        assert err.max() <= 1.5 and err.mean() < 0.3
        # patch_a_t_2 = patch_a_2 warped by the residual: it matches patch_b where both are defined.
        np.testing.assert_array_equal(a2["patch_b"][k], a1["patch_b"][i])
        np.testing.assert_array_equal(a2["context_a"][k], a1["context_a"][i])
        residual = np.linalg.inv(h_prev) @ h_ba
        ref_t = cv2.warpPerspective(ref, residual, (128, 128),
                                    flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
        # uint8 rounding plus OpenCV's 1/32-px interpolation bins (h_prev is stored in float32).
        err = np.abs(a2["patch_a_t"][k, ..., 0] * 255 - ref_t)
        assert err.max() <= 1.5 and err.mean() < 0.3
        # ... which resembles patch_b (two bilinear resamplings blur it a little).
        inside = ref_t > 0
        diff = np.abs(a2["patch_a_t"][k, ..., 0] - a2["patch_b"][k, ..., 0])[inside] * 255
        assert inside.mean() > 0.8 and np.median(diff) < 3.0


def test_stage_data_deterministic_across_workers_and_round_trip(stage1_data, tmp_path):
    a1 = data.load_arrays(stage1_data, "train")
    outs = []
    for w in (1, 2):
        d = str(tmp_path / f"w{w}")
        stage_k.make_stage_dataset(2, stage1_data, d, "train", predict=Oracle(a1), num_workers=w,
                                   log=QUIET)
        outs.append(d)
    names = sorted(n for n in os.listdir(outs[0]) if n.endswith(".tfrecord"))
    assert names == ["train-00000-of-00002.tfrecord", "train-00001-of-00002.tfrecord"]
    for n in names:
        with open(os.path.join(outs[0], n), "rb") as f, open(os.path.join(outs[1], n), "rb") as g:
            assert f.read() == g.read()
    # The training stream of stage-2 data parses (stage 2 reads it through the same pipeline).
    x, y, w = next(iter(data.load_split(outs[0], "train", 4, shuffle=False)))
    assert x["patch_a"].shape == (4, 128, 128, 1) and y["h_bar"].shape == (4, 8)


def test_degenerate_predictions_keep_previous_estimate_and_are_counted(stage1_data, tmp_path):
    a1 = data.load_arrays(stage1_data, "train")
    idx = [int(i) for i in a1["index"][:3]]
    override = {idx[0]: np.full((3, 3), np.nan), idx[1]: np.diag([1e-5, 1e-5, 1.0]),
                idx[2]: geometry.translation(60, 0)}
    out = str(tmp_path / "degenerate")
    meta = stage_k.make_stage_dataset(2, stage1_data, out, "train",
                                      predict=Oracle(a1, override=override, error_px=0.0),
                                      log=QUIET)
    counts = meta["degenerate_predictions"]
    assert counts == {"accepted": len(a1["h_ba"]) - 3, "non_finite": 1, "singular": 1,
                      "outside_context": 1}
    assert data.read_metadata(out)["splits"]["train"]["degenerate_predictions"] == counts
    a2 = data.load_arrays(out, "train")
    pos = _by_index(a2)
    # Translation by 60 px: the right corners (x = 188) are clipped onto the context border 160.
    np.testing.assert_allclose(a2["h_prev"][pos[idx[2]]],
                               [[100 / 128, 0, 60], [0, 1, 0], [0, 0, 1]], atol=1e-5)
    for i in idx[:2]:  # identity kept: patch_a is the original patch, the target the full H_ba
        k = pos[i]
        np.testing.assert_allclose(a2["h_prev"][k], np.eye(3), atol=1e-7)
        np.testing.assert_array_equal(a2["patch_a"][k], a1["patch_a"][_by_index(a1)[i]])
        np.testing.assert_allclose(a2["h_bar"][k], a1["h_bar"][_by_index(a1)[i]], atol=1e-5)


def test_in_memory_stage_pairs_equal_make_stage_dataset_records(stage1_data, tmp_path):
    """hierarchy.next_stage_arrays (stage-k pairs without TFRecords, for training from a folder)
    gives make_stage_dataset's stage-2 records field for field, degenerate cases included."""
    from stnh_tf import hierarchy

    a1 = data.load_arrays(stage1_data, "train")
    idx = [int(i) for i in a1["index"][:3]]
    override = {idx[0]: np.full((3, 3), np.nan), idx[1]: np.diag([1e-5, 1e-5, 1.0]),
                idx[2]: geometry.translation(60, 0)}
    oracle = Oracle(a1, override=override)
    meta = stage_k.make_stage_dataset(2, stage1_data, str(tmp_path / "s2"), "train",
                                      predict=oracle, log=QUIET)
    a2 = data.load_arrays(str(tmp_path / "s2"), "train")
    # The same stage-1 pairs generated in memory (same images, seed, protocol: make_dataset's).
    pair_batches = batches.PairBatches("bundled", 4, samples_per_image=3, seed=0, max_images=5)
    arrays = batches.materialize(pair_batches, workers=0, context=True)
    pairs, rejected = hierarchy.next_stage_arrays(arrays, [oracle], chunk=7, threads=3)
    serial, _ = hierarchy.next_stage_arrays(arrays, [oracle], chunk=7, threads=1)
    for name in pairs:  # chunks in threads write their own rows: the thread count does not matter
        np.testing.assert_array_equal(pairs[name], serial[name])
    own = {k: v.copy() for k, v in arrays.items()}  # in place: over the input's own patches
    in_place, _ = hierarchy.next_stage_arrays(own, [oracle], chunk=7, threads=2, in_place=True)
    for name in pairs:
        np.testing.assert_array_equal(in_place[name], pairs[name])
    assert all(in_place[k] is own[k] for k in ("patch_a", "patch_a_t", "h_bar", "patch_b"))
    assert rejected == {k: v for k, v in meta["degenerate_predictions"].items() if k != "accepted"}
    assert rejected == {"non_finite": 1, "singular": 1,
                        "outside_context": rejected["outside_context"]}
    pos = _by_index(a2)
    assert sorted(pos) == list(range(len(pairs["h_bar"])))
    for s in range(len(pairs["h_bar"])):
        k = pos[s]
        for name in ("patch_a", "patch_b"):
            np.testing.assert_array_equal(pairs[name][s], np.rint(a2[name][k, ..., 0] * 255))
        # Records hold H_ba in float32, the in-memory pairs the float64 original: the residual
        # differs by an ulp, which can move a pixel of patch_a_t across one of OpenCV's 1/32-px
        # interpolation bins, and h_bar by an ulp.
        diff = np.abs(pairs["patch_a_t"][s] - np.rint(a2["patch_a_t"][k, ..., 0] * 255))
        assert diff.max() <= 2 and np.mean(diff > 0) < 1e-3
        np.testing.assert_allclose(pairs["h_bar"][s], a2["h_bar"][k], rtol=0, atol=5e-7)
        np.testing.assert_allclose(pairs["h_prev"][s], a2["h_prev"][k], atol=1e-6)


def test_pairs_made_from_saved_estimates_equal_the_pairs_they_were_saved_with(stage1_data):
    """next_stage_arrays with estimates rounded to float32 (as a run saves them), then again from
    those estimates without the stages: the same pairs to the bit, degenerate cases included."""
    from stnh_tf import hierarchy

    a1 = data.load_arrays(stage1_data, "train")
    idx = [int(i) for i in a1["index"][:2]]
    oracle = Oracle(a1, override={idx[0]: np.full((3, 3), np.nan),
                                  idx[1]: geometry.translation(60, 0)})
    pair_batches = batches.PairBatches("bundled", 4, samples_per_image=3, seed=0, max_images=5)
    arrays = batches.materialize(pair_batches, workers=0, context=True)
    first, rejected = hierarchy.next_stage_arrays(arrays, [oracle], chunk=7, threads=2,
                                                  estimates_dtype=np.float32)
    exact, _ = hierarchy.next_stage_arrays(arrays, [oracle], chunk=7, threads=2)
    assert rejected["non_finite"] == 1 and rejected["outside_context"] >= 1
    saved = first["h_prev"].astype(np.float32)
    np.testing.assert_array_equal(saved, first["h_prev"])  # rounded before the pairs were made
    assert not np.array_equal(exact["h_prev"], first["h_prev"])
    np.testing.assert_allclose(exact["h_prev"], first["h_prev"], rtol=1e-6, atol=1e-6)

    def no_stage(patch_a, patch_b):
        raise AssertionError("a stage was called")

    again, counts = hierarchy.next_stage_arrays(arrays, [no_stage], chunk=5, threads=1,
                                                estimates=saved)
    for name in first:
        np.testing.assert_array_equal(again[name], first[name])
    assert sum(counts.values()) == 0
    with pytest.raises(ValueError, match=r"estimates of shape \(3, 3, 3\)"):
        hierarchy.next_stage_arrays(arrays, [], estimates=saved[:3])


def test_input_must_be_previous_stage(stage1_data, tmp_path):
    a1 = data.load_arrays(stage1_data, "train")
    with pytest.raises(ValueError, match="stage-1 data; stage 3"):
        stage_k.make_stage_dataset(3, stage1_data, str(tmp_path / "x"), "train",
                                   predict=Oracle(a1), log=QUIET)
    with pytest.raises(ValueError, match="stage must be >= 2"):
        stage_k.make_stage_dataset(1, stage1_data, str(tmp_path / "y"), "train",
                                   predict=Oracle(a1), log=QUIET)


@pytest.mark.slow
def test_binary_with_a_real_stage_model(stage1_data, tmp_path, narrow):
    """The binary makes both splits with an untrained stage (slow: the library call with a real
    model is tested in test_streams, the binary's error path below)."""
    import keras

    from stnh_tf.modeling import models

    keras.utils.set_random_seed(0)
    model_dir = tmp_path / "stage1_model"
    model_dir.mkdir()
    models.build_stn_homography().save(model_dir / "model.keras")
    out = tmp_path / "stage2"
    res = subprocess.run([sys.executable, "-m", "data_prep.make_stage_dataset", "--stage=2",
                          f"--input_dir={stage1_data}", f"--model_dir={model_dir}",
                          f"--output_dir={out}",
                          "--num_workers=1"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    meta = data.read_metadata(str(out))
    assert meta["stage"] == 2 and set(meta["splits"]) == {"train", "test"}
    # An untrained stage predicts the identity (identity-initialised output layer): stage-2 targets
    # equal stage-1 targets.
    a1, a2 = data.load_arrays(stage1_data, "test"), data.load_arrays(str(out), "test")
    np.testing.assert_allclose(a2["h_bar"], a1["h_bar"], atol=1e-5)


@pytest.mark.slow
def test_binary_without_a_trained_model_is_a_clear_error(stage1_data, tmp_path):
    missing = subprocess.run([sys.executable, "-m", "data_prep.make_stage_dataset", "--stage=2",
                              f"--input_dir={stage1_data}", f"--model_dir={tmp_path / 'none'}",
                              f"--output_dir={tmp_path / 'o2'}"], cwd=ROOT, capture_output=True,
                             text=True, timeout=300)
    assert missing.returncode != 0 and "make_stage_dataset: no trained model" in missing.stderr
    assert "Traceback" not in missing.stderr


def test_stage_pairs_benchmark_reports_equal_pairs_for_every_thread_count():
    """experiments.benchmark_stage_pairs' core: the pairs of 1 and 2 threads are equal to the bit,
    the oracle's errors reach the clipping rule, and ms/pair is the wall time per pair."""
    from stnh_tf.evaluation import data_benchmark

    r = data_benchmark.stage_pairs_benchmark(samples_per_image=2, threads=(1, 2), repeats=1,
                                             error_px=12.0)
    assert r["pairs"] == 40 and r["identical_across_threads"]
    assert [run["threads"] for run in r["runs"]] == [1, 2]
    cases = [run["degenerate_rule_cases"] for run in r["runs"]]
    assert cases[0] == cases[1] and cases[0]["outside_context"] > 0
    for run in r["runs"]:
        assert 0 < run["oracle_s"] < run["wall_s"]
        assert run["ms_per_pair"] * r["pairs"] == pytest.approx(1e3 * run["wall_s"], abs=0.6)
