"""stnh_tf.training.early_steps: the traced steps are the steps ``fit`` takes, and the merge's
denominator is the product's [2,2] of the model ``fit`` trained (issue 78: the hour budget's
sequence model diverged)."""

import json
import os
import subprocess
import sys

import keras
import numpy as np
import pytest

from stnh_tf.data import stage1
from stnh_tf.modeling import runner
from stnh_tf.training import config as train_config
from stnh_tf.training import early_steps
from stnh_tf.training import loop as training
from stnh_tf.training import model_kinds, streams

pytestmark = pytest.mark.slow  # sequence models trained for a few steps (~1 min)
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = str(tmp_path_factory.mktemp("early_steps_data"))
    stage1.make_dataset("bundled", d, "train", seed=0, num_shards=1, max_images=4,
                        log=lambda *a, **k: None)
    return d


def _cfg(data, model_dir, **kw):
    # dropout 0: the forward pass is a function of the weights alone, so two runs compare.
    return train_config.TrainConfig(**{
        "data_dir": data, "model_dir": str(model_dir), "model": "sequence", "num_stages": 2,
        "train_steps": 4, "warmup_steps": 2, "batch_size": 4, "dropout": 0.0, "val_samples": 0,
        "checkpoint_every": 4, "log_every": 1, **kw})


def test_traced_steps_are_fits_and_the_merge_denominator_is_the_trained_models(data, tmp_path):
    # fit's running mean of the loss after each of the first 3 steps (one epoch of 4 steps)
    means = []
    record = keras.callbacks.LambdaCallback(
        on_train_batch_end=lambda batch, logs: means.append(float(logs["loss"])))
    training.train(_cfg(data, tmp_path / "fit"), printer=lambda *a: None,
                   extra_callbacks=[record])
    records = early_steps.trace(_cfg(data, tmp_path / "trace"), 3)
    losses = [r["loss"] for r in records]
    # eager (trace) against fit's compiled step, float32: measured 1e-7 relative here
    np.testing.assert_allclose(np.cumsum(losses) / np.arange(1, 4), means[:3], rtol=1e-4)
    # the warm-up: lr 0, then 0.025, then 0.05 (2 warm-up steps to lr 0.05)
    np.testing.assert_allclose([r["learning_rate"] for r in records], [0.0, 0.025, 0.05],
                               atol=1e-7)
    # step 3's batch through the model fit leaves after 2 updates (the same warm-up: its
    # schedule's first two learning rates are these): the merge's inputs there, in NumPy
    fit2 = _cfg(data, tmp_path / "fit2", train_steps=2, checkpoint_every=2)
    training.train(fit2, printer=lambda *a: None)
    model = runner.load_model(fit2.model_dir)
    x, _, _ = list(streams.training_stream(fit2, "train", 0).map(
        model_kinds.targets_for(fit2)).take(3))[2]
    h_prev, h_res = keras.Model(model.inputs, model.get_layer("merge_2").input)(x)
    want = float(np.min(early_steps.merge_denominators(h_prev, h_res)))
    assert abs(want - 1.0) > 1e-4  # the updates moved it: not the identity's 1
    assert records[2]["merge_min_w"]["merge_2"] == pytest.approx(want, rel=1e-4)
    assert set(records[0]["mace"]) == {"h_bar_1", "h_bar_2"}


def test_merge_denominators_is_what_the_merge_divides_by():
    rng = np.random.default_rng(0)
    h_prev, h_res = (np.array([1, 0, 0, 0, 1, 0, 0, 0]) + rng.normal(0, 0.3, (5, 8))
                     for _ in range(2))
    full = lambda v: np.append(v, 1.0).reshape(3, 3)  # noqa: E731
    want = [abs((full(a) @ full(b))[2, 2]) for a, b in zip(h_prev, h_res)]
    np.testing.assert_allclose(early_steps.merge_denominators(h_prev, h_res), want, rtol=1e-12)


def test_the_grad_norm_is_before_the_clip(data, tmp_path):
    """Step 1's update is 0 (the warm-up starts at lr 0), so both runs reach step 2 with the same
    weights: the same norms are recorded there although the clip then shrinks step 2's update,
    which step 3's loss shows."""
    plain = early_steps.trace(_cfg(data, tmp_path / "a"), 3)
    clipped = early_steps.trace(_cfg(data, tmp_path / "b", clipnorm=1e-3), 3)
    for k in (0, 1):
        assert clipped[k]["grad_norm"] == pytest.approx(plain[k]["grad_norm"], rel=1e-5)
        assert plain[k]["grad_norm"] > 1e-3
    assert abs(clipped[2]["loss"] - plain[2]["loss"]) > 1e-4


def test_refusals(data, tmp_path):
    with pytest.raises(ValueError, match="steps must be an integer >= 1"):
        early_steps.trace(_cfg(data, tmp_path), 0)
    with pytest.raises(ValueError, match="--image_dir"):
        early_steps.trace(_cfg(data, tmp_path, data_dir="", image_dir=data), 1)


def test_the_binary_writes_its_records(data, tmp_path):
    out = tmp_path / "run"
    env = dict(os.environ, TF_CPP_MIN_LOG_LEVEL="2", PYTHONPATH=ROOT)
    proc = subprocess.run(
        [sys.executable, "-m", "experiments.trace_early_steps", f"--model_dir={out}",
         f"--data_dir={data}", "--num_stages=2", "--train_steps=4", "--warmup_steps=2",
         "--checkpoint_every=4", "--batch_size=4", "--val_samples=0", "--steps=2"],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    saved = json.loads((out / "early_steps.json").read_text())
    assert [r["step"] for r in saved["steps"]] == [1, 2] and saved["steps"] == lines
    assert saved["config"]["clipnorm"] == 0.0 and saved["config"]["num_stages"] == 2
