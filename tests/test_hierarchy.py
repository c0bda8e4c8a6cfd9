"""Hierarchical composition: context re-cropping, residual targets, oracle stages, the
degenerate-prediction rule. References are computed here with OpenCV on the full 320x240 image."""

import cv2
import numpy as np
import pytest

from conftest import paper_homography, photo_pairs
from stnh_tf import geometry, hierarchy

M = 32  # context margin
S = 128


def _mace(h_pred, h_true):
    """Independent MACE: corners through both homographies with OpenCV."""
    c = np.array([[[0, 0], [S, 0], [S, S], [0, S]]], np.float64)
    errs = [np.linalg.norm(cv2.perspectiveTransform(c, p)[0] - cv2.perspectiveTransform(c, t)[0],
                           axis=1).mean()
            for p, t in zip(h_pred, h_true)]
    return float(np.mean(errs))


@pytest.fixture(scope="module")
def pairs():
    """Paper-protocol pairs made here: image, square, H_ba (patch frame), context, patch_b."""
    return photo_pairs(np.random.default_rng(3), 8, margin=M)


def test_crop_warped_context_equals_full_image_warp(pairs, rng):
    for i in range(4):
        x0, y0 = pairs["xy"][i]
        h_prev = paper_homography(rng)
        t = np.array([[1, 0, x0], [0, 1, y0], [0, 0, 1.0]])
        full = cv2.warpPerspective(pairs["image"][i].astype(np.float32),
                                   t @ h_prev @ np.linalg.inv(t),
                                   (320, 240), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
        ref = full[y0:y0 + S, x0:x0 + S]
        got = hierarchy.crop_warped_context(pairs["context"][i], h_prev)
        assert got.shape == (S, S)
        # Corners move by at most 32 px, so every source point lies inside the context.
        np.testing.assert_allclose(got, ref, atol=1e-3)


def test_context_warped_by_true_h_reproduces_patch_b(pairs):
    for i in range(len(pairs["h_ba"])):
        got = hierarchy.crop_warped_context(pairs["context"][i], pairs["h_ba"][i])
        diff = np.abs(got - pairs["patch_b"][i].astype(np.float32))
        assert diff.mean() < 0.6 and diff.max() <= 1.0  # uint8 rounding of patch_b only


def test_patch_a_is_the_centre_of_the_context(pairs):
    got = hierarchy.crop_warped_context(pairs["context"][0], np.eye(3))
    np.testing.assert_array_equal(got, pairs["context"][0][M:M + S, M:M + S].astype(np.float32))


def test_residual_target(rng):
    h_prev, h_ba = paper_homography(rng), paper_homography(rng)
    res = hierarchy.residual_target(h_prev, h_ba)
    composed = h_prev @ res
    np.testing.assert_allclose(composed / composed[2, 2], h_ba / h_ba[2, 2], atol=1e-9)
    assert res[2, 2] == pytest.approx(1.0)


def test_stage_pairs_of_a_batch_equal_opencv_pair_by_pair(pairs, rng):
    """The batched stage-pair maker against the pairs built here one at a time with OpenCV and
    NumPy (re-crop, residual, normalized target, warp by the residual, rounding): equal to the
    bit, and each row the same as :func:`stage_pair` of that row alone."""
    n = len(pairs["h_ba"])
    h_prev = np.stack([paper_homography(rng) for _ in range(n)])
    got = hierarchy.stage_pairs(pairs["context"], pairs["h_ba"], h_prev)
    m = np.array([[2 / S, 0, -1], [0, 2 / S, -1], [0, 0, 1.0]])
    for i in range(n):
        crop = cv2.warpPerspective(pairs["context"][i].astype(np.float32),
                                   np.array([[1, 0, M], [0, 1, M], [0, 0, 1.0]]) @ h_prev[i],
                                   (S, S), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
        residual = np.linalg.inv(h_prev[i]) @ pairs["h_ba"][i]
        residual /= residual[2, 2]
        warped = cv2.warpPerspective(crop, residual, (S, S),
                                     flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
        h_bar = m @ residual @ np.linalg.inv(m)
        np.testing.assert_array_equal(got["patch_a"][i], np.clip(np.rint(crop), 0, 255))
        np.testing.assert_array_equal(got["patch_a_t"][i], np.clip(np.rint(warped), 0, 255))
        np.testing.assert_allclose(got["h_bar"][i], (h_bar / h_bar[2, 2]).reshape(9)[:8],
                                   rtol=1e-6, atol=1e-7)
        one = hierarchy.stage_pair(pairs["context"][i], pairs["h_ba"][i], h_prev[i])
        for key in got:
            np.testing.assert_array_equal(one[key], got[key][i])
    assert got["patch_a"].dtype == got["patch_a_t"].dtype == np.uint8


class _Oracle:
    """Stage k returns a fixed matrix per sample (precomputed from the truth), recording the
    patches it was shown."""

    def __init__(self, outputs):
        self.outputs, self.seen = outputs, None

    def __call__(self, patch_a, patch_b):
        self.seen = (patch_a, patch_b)
        return self.outputs


@pytest.mark.parametrize("num_stages", [1, 2, 3])
def test_oracle_stages_give_zero_mace(pairs, num_stages, rng):
    h_true = pairs["h_ba"]
    n = len(h_true)
    # Stages 1..n-1 return deliberately wrong estimates; the last returns the exact residual.
    wrong = [np.stack([paper_homography(rng) for _ in range(n)]) * 0.1 + np.eye(3) * 0.9
             for _ in range(num_stages - 1)]
    prev = np.repeat(np.eye(3)[None], n, 0)
    outputs = []
    for w in wrong:
        outputs.append(w)
        prev = prev @ w
    outputs.append(np.linalg.inv(prev) @ h_true)
    run = hierarchy.run_hierarchy([_Oracle(o) for o in outputs], pairs["context"], pairs["patch_b"])
    assert run["h"].shape == (n, 3, 3) and len(run["per_stage"]) == num_stages
    assert _mace(run["h"], h_true) < 1e-6
    assert all(sum(r.values()) == 0 for r in run["rejected"])
    if num_stages > 1:
        # the intermediate estimate is the product of the wrong stages, not the truth
        assert _mace(run["per_stage"][0], h_true) == pytest.approx(_mace(wrong[0], h_true),
                                                                   rel=1e-9)
        assert _mace(run["per_stage"][0], h_true) > 1.0


def test_stage_two_sees_the_warped_context(pairs):
    """With a perfect stage 1, stage 2's patch_a equals patch_b (up to uint8 rounding)."""
    h_true = pairs["h_ba"]
    o1, o2 = _Oracle(h_true), _Oracle(np.repeat(np.eye(3)[None], len(h_true), 0))
    run = hierarchy.run_hierarchy([o1, o2], pairs["context"], pairs["patch_b"])
    patch_a_2, patch_b = o2.seen
    assert patch_a_2.shape == (len(h_true), S, S, 1) and patch_a_2.max() <= 1.0
    assert np.abs(patch_a_2 - patch_b).mean() < 0.6 / 255
    # Stage 1 saw the centre of the context, scaled to [0, 1].
    np.testing.assert_allclose(o1.seen[0][..., 0], pairs["context"][:, M:M + S, M:M + S] / 255.0,
                               atol=1e-6)
    assert _mace(run["h"], h_true) < 1e-6


def test_degenerate_rule():
    eye = np.eye(3)
    assert hierarchy.rejection_reason(eye) is None
    assert hierarchy.rejection_reason(np.full((3, 3), np.nan)) == "non_finite"
    assert hierarchy.rejection_reason(np.diag([1e-4, 1e-4, 1.0])) == "singular"
    behind = np.array([[1, 0, 0], [0, 1, 0], [-0.02, 0, 1.0]])  # w <= 0 for x >= 50
    assert hierarchy.rejection_reason(behind) == "singular"
    assert hierarchy.rejection_reason(geometry.translation(33, 0)) == "outside_context"
    assert hierarchy.rejection_reason(geometry.translation(32, -32)) is None  # on the boundary
    # A batch: rejected samples keep the previous estimate; accepted ones compose.
    h_prev = np.stack([geometry.translation(5, 0)] * 3)
    h_stage = np.stack([geometry.translation(2, 1), np.full((3, 3), np.inf),
                        geometry.translation(40, 0)])
    out, reasons = hierarchy.accept_or_reject(h_prev, h_stage)
    assert reasons == [None, "non_finite", "outside_context"]
    np.testing.assert_allclose(out[0], geometry.translation(7, 1))
    np.testing.assert_allclose(out[1], h_prev[1])
    # Translation by 45 px: the right corners (x = 173) are clipped onto the border x = 160, the
    # left ones (x = 45) stay: x' = 45 + (115 / 128) x.
    np.testing.assert_allclose(out[2], [[115 / 128, 0, 45], [0, 1, 0], [0, 0, 1]], atol=1e-6)
    # A perspective estimate with one corner 10 px outside keeps its other three corners.
    corners = geometry.patch_corners().astype(np.float32)
    target = corners + np.array([[-42, 3], [-5, 4], [6, -7], [2, 8]], np.float32)
    h = cv2.getPerspectiveTransform(corners, target).astype(np.float64)
    out, reasons = hierarchy.accept_or_reject(np.eye(3)[None], h[None])
    assert reasons == ["outside_context"]
    mapped = cv2.perspectiveTransform(corners[None].astype(np.float64), out[0])[0]
    np.testing.assert_allclose(mapped,
                               target.astype(np.float64) + [[10, 0], [0, 0], [0, 0], [0, 0]],
                               atol=1e-3)


def test_inputs_are_scaled_by_their_own_dtype(pairs):
    """uint8 context with float patch_b in [0, 1] (as stnh_tf.data.tfrecords.load_arrays returns
    them) must show the stage the same patches as all-uint8 inputs."""
    o_u8, o_mixed = _Oracle(pairs["h_ba"]), _Oracle(pairs["h_ba"])
    hierarchy.run_hierarchy([o_u8], pairs["context"], pairs["patch_b"])
    hierarchy.run_hierarchy([o_mixed], pairs["context"],
                            pairs["patch_b"].astype(np.float32) / 255.0)
    for a, b in zip(o_u8.seen, o_mixed.seen):
        np.testing.assert_allclose(a, b, atol=1e-6)
    assert 0.2 < o_mixed.seen[1].mean() < 0.8  # patch_b in [0, 1], not divided twice


def test_no_clip_keeps_the_composition_that_clipping_changes():
    """A composition whose corners leave the context: the rule refits it onto the border; with
    ``clip_to_context=False`` it is ``h_prev @ h_stage`` as predicted (still counted)."""
    h_prev = np.stack([geometry.translation(5, 0)] * 3)
    h_stage = np.stack([geometry.translation(40, 0), geometry.translation(2, 1),
                        np.full((3, 3), np.nan)])
    clipped, reasons = hierarchy.accept_or_reject(h_prev, h_stage)
    raw, raw_reasons = hierarchy.accept_or_reject(h_prev, h_stage, clip_to_context=False)
    assert reasons == raw_reasons == ["outside_context", None, "non_finite"]
    np.testing.assert_allclose(raw[0], geometry.translation(45, 0), atol=1e-12)
    np.testing.assert_allclose(clipped[0], [[115 / 128, 0, 45], [0, 1, 0], [0, 0, 1]], atol=1e-6)
    np.testing.assert_allclose(raw[1:], clipped[1:])  # the rest of the rule is unchanged
    np.testing.assert_allclose(raw[2], h_prev[2])


def test_no_clip_through_the_hierarchy_and_its_evaluation(pairs, monkeypatch):
    """Stage 1 overshoots by 45 px (outside the 32-px context), stage 2 returns a fixed matrix:
    without clipping the estimates are exactly their products, stage 2 reads zeros beyond the
    context, and ``evaluate_hierarchy`` scores those products."""
    from stnh_tf.evaluation import mace as evaluation
    from stnh_tf.modeling import runner

    n = len(pairs["h_ba"])
    t45 = np.repeat(geometry.translation(45, 0)[None], n, 0)
    second = np.repeat(geometry.translation(-3, 2)[None], n, 0)
    o1, o2 = _Oracle(t45), _Oracle(second)
    run = hierarchy.run_hierarchy([o1, o2], pairs["context"], pairs["patch_b"],
                                  clip_to_context=False)
    np.testing.assert_allclose(run["per_stage"][0], t45, atol=1e-12)
    np.testing.assert_allclose(run["h"], t45 @ second, atol=1e-12)
    assert run["rejected"][0]["outside_context"] == n
    # patch_a_2(p) = patch_a(p + 45): columns with x + 45 > 160 lie beyond the context.
    assert np.all(o2.seen[0][:, :, 116:, 0] == 0) and o2.seen[0][:, :, :100].mean() > 0.05
    clipped = hierarchy.run_hierarchy([o1, o2], pairs["context"], pairs["patch_b"])
    assert _mace(clipped["h"], t45 @ second) > 1.0  # clipping changes the composition here

    monkeypatch.setattr(runner, "predictor", lambda stage, batch_size=64: stage)
    samples = {"context_a": pairs["context"], "patch_b": pairs["patch_b"], "h_ba": pairs["h_ba"]}
    for clip, h in ((False, t45 @ second), (True, clipped["h"])):
        result = evaluation.evaluate_hierarchy([o1, o2], samples, clip_to_context=clip)
        assert result["clip_to_context"] is clip
        assert result["mace"] == pytest.approx(_mace(h, pairs["h_ba"]), rel=1e-9)
        worse = (geometry.corner_errors(h, pairs["h_ba"])
                 > geometry.corner_errors(np.broadcast_to(np.eye(3), h.shape), pairs["h_ba"]))
        assert result["worse_than_identity"] == int(worse.sum())
        assert result["stages"]["after_2_stages"]["worse_than_identity"] == int(worse.sum())
    assert 0 < result["worse_than_identity"] <= n
    assert result["rejected"][0]["outside_context"] == n


def test_error_summary_counts_pairs_worse_than_the_identity():
    from stnh_tf.evaluation import mace as evaluation

    got = evaluation.error_summary([1.0, 5.0, 3.0, 0.5], identity_errors=[2.0, 2.0, 3.0, 0.4])
    assert got["worse_than_identity"] == 2  # 5 > 2 and 0.5 > 0.4; a tie is not worse
    assert got["mace"] == pytest.approx(2.375) and got["count"] == 4
    # the standard error of the mean: sample std (n - 1) over sqrt(n), by hand
    deviations = [e - 2.375 for e in (1.0, 5.0, 3.0, 0.5)]
    assert got["mace_se"] == pytest.approx((sum(d * d for d in deviations) / 3) ** 0.5 / 2)
    one = evaluation.error_summary([1.0])
    assert "worse_than_identity" not in one and one["mace_se"] is None


def test_no_clip_needs_a_hierarchy():
    from stnh_tf.evaluation import mace as evaluation

    with pytest.raises(ValueError, match="changes only a hierarchy"):
        evaluation.evaluate(["runs/stage1"], "no_such_data", clip_to_context=False)


def test_latency_records_the_policy_the_models_ran_in(tmp_path):
    """Loaded models keep the policy they were saved with, whatever ``policy`` asks for."""
    from conftest import keras_policy
    from stnh_tf.evaluation import mace as evaluation
    from stnh_tf.modeling import models

    with keras_policy("mixed_bfloat16"):
        models.build_stn_homography().save(tmp_path / "stage1.keras")
    loaded = evaluation.latency([str(tmp_path / "stage1.keras")], runs=1, warmup=0,
                                policy="float32", sequence=False)
    assert loaded["policy"] == "mixed_bfloat16" and set(loaded["hierarchy"]) == {"1"}
    built = evaluation.latency((), max_stages=1, runs=1, warmup=0, policy="float32",
                               sequence=False)
    assert built["policy"] == "float32"
