"""oneDNN's time per primitive of a training step (issue 77, item 5):
``stnh_tf.evaluation.onednn_profile`` reads the verbose lines as oneDNN writes them, and on this
machine finds the paper's eight convolutions in a stage's step."""

import json
import os
import platform
import subprocess
import sys

import pytest

from stnh_tf.evaluation import onednn_profile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

EXEC = "onednn_verbose,v1,primitive,exec,cpu,{kind},{impl},{prop},src:bf16::blocked:acdb::f0,,alg,{problem},{ms}"


def _line(problem, ms, prop="forward_training", kind="convolution", impl="brg_conv_fwd:avx512"):
    return EXEC.format(kind=kind, impl=impl, prop=prop, problem=problem, ms=ms)


def test_parse_verbose_keeps_the_last_steps_of_each_primitive_and_counts_its_layers():
    steps = []
    for step in range(3):  # 3 runs: layers A (twice a step, one shape) and B; set-up lines once
        steps += [_line("A", 10 + step), _line("B", 1.0, prop="backward_weights"),
                  _line("A", 20 + step)]
    text = "\n".join(
        ["onednn_verbose,v1,info,oneDNN v3.7", _line("setup", 99.0, kind="reorder"),
         "onednn_verbose,v1,primitive,create:cache_miss,cpu,convolution,x,forward_training,,,,A,5",
         _line("A", "not-a-number")] + steps)
    rows = onednn_profile.parse_verbose(text, runs=3, timed=2)
    assert [r["problem"] for r in rows] == ["A", "B"]  # set-up and a bad time left out
    assert rows[0]["formats"] == "src:bf16::blocked:acdb::f0"
    a, b = rows
    assert a["calls_per_step"] == 2 and b["calls_per_step"] == 1
    assert a["ms_per_step"] == pytest.approx((11 + 21 + 12 + 22) / 2)  # the last two steps
    assert a["ms_per_call"] == pytest.approx((11 + 21 + 12 + 22) / 4)
    assert b["propagation"] == "backward_weights" and b["ms_per_step"] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="timed must be in 1..runs"):
        onednn_profile.parse_verbose(text, runs=3, timed=4)


@pytest.mark.slow
def test_a_stage_step_runs_the_papers_eight_convolutions_through_onednn():
    """The VGG-style network's 8 convolutions (conventions.md: 64 x 4 then 128 x 4) each run
    forward and backward-weights once a step, backward-data for all but the first (its input,
    the image pair, needs no gradient), in float32 (every x86 CPU)."""
    if platform.machine() not in ("x86_64", "AMD64") or os.environ.get(
            "TF_ENABLE_ONEDNN_OPTS") == "0":
        pytest.skip("TensorFlow uses oneDNN by default on x86 only, and not with it switched off")
    result = onednn_profile.profile_training_step("float32", batch_size=4, steps=2, warmup=1)
    convs = [r for r in result["primitives"] if r["kind"] == "convolution"]
    per_pass = {p: sum(r["calls_per_step"] for r in convs if r["propagation"] == p)
                for p in ("forward_training", "backward_data", "backward_weights")}
    assert per_pass == {"forward_training": 8, "backward_data": 7, "backward_weights": 8}
    assert {r["problem"].split("_ih")[0] for r in convs} == {
        "mb4_ic2oc64", "mb4_ic64oc64", "mb4_ic64oc128", "mb4_ic128oc128"}
    assert result["step_s"] > 0 and result["ms_per_step"] == pytest.approx(
        sum(result["ms_per_step_by_propagation"].values()))


def test_a_child_that_times_no_primitive_or_fails_is_an_error(monkeypatch):
    """No oneDNN line at all (a build without it) is an error, not an empty profile; so is a
    child that fails, with its last lines."""
    outputs = iter([subprocess.CompletedProcess([], 0, "STEP_S 1.5\n", ""),
                    subprocess.CompletedProcess([], 1, "", "Traceback\nMemoryError\n")])
    monkeypatch.setattr(onednn_profile.subprocess, "run", lambda *a, **k: next(outputs))
    with pytest.raises(RuntimeError, match="oneDNN timed no primitive"):
        onednn_profile.profile_training_step("float32")
    with pytest.raises(RuntimeError, match="(?s)exit 1.*MemoryError"):
        onednn_profile.profile_training_step("float32")


@pytest.mark.slow
def test_without_onednns_layers_the_profile_holds_eigens_matrix_products(monkeypatch):
    """With ``TF_ENABLE_ONEDNN_OPTS=0`` TensorFlow's own (Eigen) convolutions run: no oneDNN
    convolution in the profile, only the matrix products Eigen hands to oneDNN's gemm."""
    if platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip("TensorFlow uses oneDNN by default on x86 only")
    monkeypatch.setenv("TF_ENABLE_ONEDNN_OPTS", "0")
    result = onednn_profile.profile_training_step("float32", batch_size=4, steps=1, warmup=1)
    kinds = {r["kind"] for r in result["primitives"]}
    assert "convolution" not in kinds and "gemm_api" in kinds


@pytest.mark.slow
def test_benchmark_training_binary_records_its_settings_and_the_profile(tmp_path):
    """``benchmark_training --onednn_layers`` end to end on a tiny batch: the profile per
    policy beside the step times, and in ``environment`` the oneDNN variable it ran under but
    not another tool's ``TF_`` variable."""
    if platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip("TensorFlow uses oneDNN by default on x86 only")
    out = tmp_path / "b.json"
    env = dict(os.environ, ONEDNN_VERBOSE_TIMESTAMP="0", TF_CLI_CONFIG_FILE="/secret/.rc")
    done = subprocess.run(
        [sys.executable, "-m", "experiments.benchmark_training", "--batch_size=4", "--steps=1",
         "--warmup=1", "--latency_runs=1", "--policies=float32", "--onednn_layers",
         f"--json_out={out}"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(out.read_text())
    assert result["environment"].get("ONEDNN_VERBOSE_TIMESTAMP") == "0"
    assert "TF_CLI_CONFIG_FILE" not in result["environment"]
    assert list(result["onednn_layers"]) == ["float32"] == list(result["train_step_s"])
    profile = result["onednn_layers"]["float32"]
    assert profile["batch_size"] == 4 and profile["primitives"]
