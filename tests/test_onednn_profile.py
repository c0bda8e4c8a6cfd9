"""oneDNN's time per primitive of a training step (issue 77, item 5):
``stnh_tf.evaluation.onednn_profile`` reads the verbose lines as oneDNN writes them, and on this
machine finds the paper's eight convolutions in a stage's step."""

import pytest

from stnh_tf.evaluation import onednn_profile

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
    result = onednn_profile.profile_training_step("float32", batch_size=4, steps=2, warmup=1)
    convs = [r for r in result["primitives"] if r["kind"] == "convolution"]
    if not convs:
        pytest.skip("TensorFlow runs no oneDNN convolution on this machine")
    per_pass = {p: sum(r["calls_per_step"] for r in convs if r["propagation"] == p)
                for p in ("forward_training", "backward_data", "backward_weights")}
    assert per_pass == {"forward_training": 8, "backward_data": 7, "backward_weights": 8}
    assert {r["problem"].split("_ih")[0] for r in convs} == {
        "mb4_ic2oc64", "mb4_ic64oc64", "mb4_ic64oc128", "mb4_ic128oc128"}
    assert result["step_s"] > 0 and result["ms_per_step"] == pytest.approx(
        sum(result["ms_per_step_by_propagation"].values()))
