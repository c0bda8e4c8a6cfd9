"""DeTone et al.'s HomographyNet recipe as a training option: the step learning-rate schedule, the
presets by model kind (and so the binaries' defaults), the model kinds' dispatch."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from stnh_tf.training import config as train_config
from stnh_tf.training import loop as training
from stnh_tf.training import model_kinds, presets

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _step_cfg(train_steps, lr=0.005):
    return train_config.TrainConfig(data_dir="d", model_dir="m", model="homographynet",
                                    batch_norm="conv", lr_schedule="step", learning_rate=lr,
                                    warmup_steps=0, train_steps=train_steps, checkpoint_every=1)


def test_step_schedule_divides_by_ten_after_each_third():
    """DeTone et al.: lr 0.005, /10 every 30,000 of 90,000 iterations. Keras evaluates the schedule
    at the 0-based step before each update, so updates 0..29,999 use 0.005 (Caffe's "step"
    policy: lr * 0.1 ** floor(i / 30000))."""
    cfg = _step_cfg(90_000)
    cfg.validate()
    schedule = training.learning_rate_schedule(cfg)
    expected = {0: 5e-3, 29_999: 5e-3, 30_000: 5e-4, 59_999: 5e-4, 60_000: 5e-5, 89_999: 5e-5}
    for step, lr in expected.items():
        assert float(schedule(step)) == pytest.approx(lr, rel=1e-6), step
    # The optimizer applies the same rate at its iteration count.
    optimizer = training.build_optimizer(cfg)
    for step, lr in expected.items():
        optimizer.iterations.assign(step)
        assert float(np.asarray(optimizer.learning_rate)) == pytest.approx(lr, rel=1e-6), step
    # train_steps not a multiple of 3: the thirds end at floor(T / 3) and floor(2 T / 3).
    schedule = training.learning_rate_schedule(_step_cfg(4_000, lr=1.0))
    assert [float(schedule(s)) for s in (1_332, 1_333, 2_665, 2_666, 3_999)] == pytest.approx(
        [1.0, 0.1, 0.1, 0.01, 0.01])


def test_cosine_stays_the_default_schedule():
    cfg = train_config.TrainConfig(data_dir="d", model_dir="m", warmup_steps=0, train_steps=100)
    assert cfg.lr_schedule == "cosine"
    schedule = training.learning_rate_schedule(cfg)
    assert float(schedule(0)) == pytest.approx(0.05) and float(schedule(50)) == pytest.approx(0.025)


@pytest.mark.parametrize("changes, message", [
    ({"lr_schedule": "exponential"}, "lr_schedule must be one of"),
    ({"warmup_steps": 100}, "has no warm-up"),
    ({"batch_norm": "none"}, "batch_norm must be 'conv'"),
])
def test_bad_homographynet_settings_are_clear_errors(changes, message):
    cfg = _step_cfg(90_000)
    for k, v in changes.items():
        setattr(cfg, k, v)
    with pytest.raises(ValueError, match=message):
        cfg.validate()


def test_presets_by_model_kind_and_recipe():
    detone = {"batch_norm": "conv", "learning_rate": 0.005, "lr_schedule": "step",
              "warmup_steps": 0, "train_steps": 90_000}
    assert presets.preset_fields("paper", "homographynet") == detone
    assert presets.preset_fields("paper", "sequence") == {"train_steps": 90_000}
    assert presets.preset_fields("paper", "stn") == {}
    assert presets.preset_fields("paper", "homographynet_gap") == {}
    # The fast recipe replaces DeTone's schedule (its own warm-up needs the cosine schedule).
    fast = presets.preset_fields("fast", "homographynet")
    assert fast["lr_schedule"] == "cosine" and fast["optimizer"] == "adamw"
    assert fast["batch_norm"] == "conv"
    # ... and leaves out what only the STN kinds use (their L2 sum, per-patch input).
    assert not set(presets.STN_ONLY_FIELDS) & set(fast)
    stn = presets.preset_fields("fast", "stn")
    assert stn == presets.RECIPES["fast"]
    assert (stn["l2_reduction"], stn["input_norm"]) == ("sum", "patch")
    cfg = train_config.TrainConfig(data_dir="d", model_dir="m", model="homographynet", **fast)
    cfg.validate()
    for recipe, model in (("turbo", "stn"), ("paper", "vgg")):
        with pytest.raises(ValueError, match="must be one of"):
            presets.preset_fields(recipe, model)


def test_model_kinds_build_their_networks():
    for cfg, params in ((_step_cfg(3), 34_194_568),
                        (train_config.TrainConfig(data_dir="d", model_dir="m",
                                                  model="homographynet_gap"), 768_904)):
        model = model_kinds.build_model(cfg)
        assert model.count_params() == params
        losses, weights, _ = model_kinds.loss_spec(cfg)
        assert losses == {"offsets": "mse"} and weights == {"offsets": 1.0}
        assert model_kinds.targets_for(cfg) is model_kinds.targets_for(_step_cfg(3))


FLAGS_SCRIPT = r"""
import json, sys
from absl import flags
from experiments import flags_common
from stnh_tf.training import config as train_config
flags_common.define_training_flags(train_config.STAGE)
out = []
for argv in json.loads(sys.argv[1]):
    flags.FLAGS.unparse_flags()
    flags.FLAGS(["binary", "--model_dir=m", *argv])
    out.append({m: flags_common.config_from_flags(train_config.STAGE, model=m).to_json()
                for m in ("stn", "sequence", "homographynet")})
print(json.dumps(out))
"""


def test_binaries_default_to_each_model_kinds_recipe():
    """``config_from_flags``: DeTone's recipe for homographynet and 90,000 steps for the sequence
    model unless the flags say otherwise; the stage keeps the paper's 91,000 cosine steps."""
    cases = [[], ["--train_steps=600", "--learning_rate=0.01", "--lr_schedule=cosine",
                  "--warmup_steps=10"]]
    res = subprocess.run([sys.executable, "-c", FLAGS_SCRIPT, json.dumps(cases)], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    default, explicit = json.loads(res.stdout.strip().splitlines()[-1])
    stn, seq, hnet = default["stn"], default["sequence"], default["homographynet"]
    assert (stn["train_steps"], stn["warmup_steps"], stn["learning_rate"], stn["lr_schedule"]) == (
        91_000, 1_000, 0.05, "cosine")
    assert (seq["train_steps"], seq["warmup_steps"], seq["lr_schedule"]) == (
        90_000, 1_000, "cosine")
    assert (hnet["train_steps"], hnet["warmup_steps"], hnet["learning_rate"], hnet["lr_schedule"],
            hnet["batch_norm"], hnet["optimizer"], hnet["momentum"], hnet["batch_size"]) == (
        90_000, 0, 0.005, "step", "conv", "sgd", 0.9, 64)
    for m in ("sequence", "homographynet"):  # flags given explicitly win over the presets
        got = explicit[m]
        assert (got["train_steps"], got["learning_rate"], got["lr_schedule"],
                got["warmup_steps"]) == (600, 0.01, "cosine", 10), m
