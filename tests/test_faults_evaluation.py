"""A hostile read of the evaluation path (2026-12-07), kept as tests: a ``--no_clip``
evaluation's note said the estimates outside the context were clipped onto it; the JSON did not
say in what precision the models ran (mixed-bfloat16 models run as saved unless
``--compute_dtype=float32``, and the cited numbers move with it); a hierarchy's
``ms_per_pair_batched`` counted building and tracing its stages.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from conftest import constant_stage, keras_policy
from stnh_tf.data import stage1
from stnh_tf.data import tfrecords as data
from stnh_tf.evaluation import mace, summaries
from stnh_tf.modeling import runner


@pytest.fixture(scope="module")
def pairs(tmp_path_factory):
    """Stage-1 test pairs of two bundled photographs (3 each)."""
    out = str(tmp_path_factory.mktemp("pairs"))
    stage1.make_dataset("bundled", out, "test", seed=1, max_images=2, num_shards=1,
                        num_workers=1, log=lambda *_: None)
    return data.load_arrays(out, "test")


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """A float32 and a mixed-bfloat16 constant stage (a 20-px shift), saved as .keras files."""
    folder = tmp_path_factory.mktemp("models")
    shift = np.array([[1.0, 0, 20], [0, 1, 0], [0, 0, 1]])
    out = {"float32": str(folder / "f32.keras"), "mixed_bfloat16": str(folder / "bf16.keras")}
    constant_stage(shift, "f32").save(out["float32"])
    with keras_policy("mixed_bfloat16"):
        constant_stage(shift, "bf16").save(out["mixed_bfloat16"])
    return out


def test_the_json_says_in_what_precision_the_models_ran(pairs, models):
    """Each model's compute policy (``runner.compute_policy``) is in the result: a mixed model
    as saved, and as float32 with ``compute_dtype="float32"``; a hierarchy's, stage by stage."""
    one = mace.evaluate_arrays(pairs, [models["mixed_bfloat16"]])["model"]
    assert one["compute_policy"] == "mixed_bfloat16"
    asked = mace.evaluate_arrays(pairs, [models["mixed_bfloat16"]], compute_dtype="float32")
    assert asked["model"]["compute_policy"] == "float32"
    both = mace.evaluate_arrays(pairs, [models["float32"], models["mixed_bfloat16"]])["model"]
    assert both["compute_policy"] == ["float32", "mixed_bfloat16"]


def test_a_no_clip_note_says_the_estimates_were_kept(pairs, models):
    """The table's note under a hierarchy said "clipped onto it" also for ``--no_clip`` runs,
    whose JSON says ``clip_to_context`` False: now it says they were kept as predicted. Two
    stages of a 20-px shift take the corners 40 px out: beyond the context's 32-px margin."""
    for clip, said, not_said in ((True, "clipped onto it", "kept as predicted"),
                                 (False, "kept as predicted: --no_clip", "clipped onto it")):
        result = {"count": len(pairs["h_ba"]), "data_dir": "D", "split": "test",
                  **mace.evaluate_arrays(pairs, [models["float32"]] * 2,
                                         clip_to_context=clip)}
        assert sum(sum(s.values()) for s in result["model"]["rejected"]) > 0
        table = summaries.evaluation_table(result)
        assert said in table and not_said not in table


def test_a_hierarchys_time_per_pair_leaves_out_its_first_call(pairs, models, monkeypatch):
    """``ms_per_pair_batched`` of a hierarchy timed the stages' first calls (building and
    tracing their functions: 129 against 69 ms a pair in the review); the single-model path
    ran one pair before starting the clock, and now so does the hierarchy: each stage's first
    call comes before the clock is read (the order of the calls, recorded; no timing)."""
    real, events, now, made = runner.predictor, [], time.perf_counter, []

    def recorded(model, batch_size=64, output=None):
        predict, k = real(model, batch_size, output), len(made)
        made.append(k)

        def call(patch_a, patch_b):
            events.append(("stage", k))
            return predict(patch_a, patch_b)
        return call

    def clock():
        events.append(("clock", None))
        return now()

    monkeypatch.setattr(runner, "predictor", recorded)
    monkeypatch.setattr(mace.time, "perf_counter", clock)
    mace.evaluate_arrays(pairs, [models["float32"]] * 2)
    first_clock = events.index(("clock", None))
    assert {e for e in events[:first_clock] if e[0] == "stage"} == {("stage", 0), ("stage", 1)}


def test_a_stage_k_models_mace_composes_it_after_the_earlier_estimate():
    """Nothing checked that a stage-k model's MACE on stage-k pairs is that of ``h_prev @ H_k``
    (a test audit: swapping the order, or dropping ``h_prev``, went unnoticed). A constant stage
    H_k on pairs with known, non-identity ``h_prev``: the MACE is recomputed here with
    ``cv2.perspectiveTransform`` at the patch corners, and the wrong order is far from it."""
    import cv2

    from conftest import constant_stage
    from stnh_tf.evaluation import mace

    rng = np.random.default_rng(5)
    square = np.float32([[0, 0], [128, 0], [128, 128], [0, 128]])

    def motion(scale):
        return cv2.getPerspectiveTransform(
            square, square + rng.uniform(-scale, scale, (4, 2)).astype(np.float32))

    n = 6
    h_prev = np.stack([motion(20) for _ in range(n)])
    h_k = motion(6)
    h_ba = np.stack([p @ h_k @ motion(1) for p in h_prev])  # the right composition, about 1 px off
    samples = {"patch_a": rng.random((n, 128, 128, 1), np.float32),  # (the output is constant)
               "patch_b": rng.random((n, 128, 128, 1), np.float32),
               "h_ba": h_ba, "h_prev": h_prev}
    got = mace.evaluate_model_on_arrays(constant_stage(h_k), samples)["mace"]

    def mean_corner_error(h_est):
        return np.mean([np.linalg.norm(
            cv2.perspectiveTransform(square.reshape(-1, 1, 2), e)
            - cv2.perspectiveTransform(square.reshape(-1, 1, 2), t), axis=-1).mean()
            for e, t in zip(h_est, h_ba)])

    expected = mean_corner_error(h_prev @ h_k)
    assert got == pytest.approx(expected, abs=0.01)  # (float32 H_bar: about 1e-3 px)
    assert abs(mean_corner_error(h_k @ h_prev) - expected) > 0.5
    assert abs(mean_corner_error(np.broadcast_to(h_k, h_ba.shape)) - expected) > 0.5
