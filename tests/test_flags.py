"""The training binaries' flags are generated from TrainConfig's fields: every field is a flag of
a binary, and every flag given on the command line reaches the config unchanged."""

import dataclasses
import os
import subprocess
import sys

import pytest
from absl import flags

from experiments import flags_common
from stnh_tf.training import config as train_config
from stnh_tf.training.config import SEQUENCE, STAGE, TrainConfig

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _names(scope):
    return {f.name for f in flags_common.training_fields(scope)}


def test_every_field_is_a_flag_of_a_binary():
    every = {f.name for f in dataclasses.fields(TrainConfig)}
    assert _names(STAGE) | _names(SEQUENCE) == every
    assert {"model", "stage"} <= _names(STAGE) - _names(SEQUENCE)
    assert {"num_stages", "stage_loss_weights"} <= _names(SEQUENCE) - _names(STAGE)
    assert {"val_seed", "init_from"} <= _names(STAGE) & _names(SEQUENCE)


def _other_value(field):
    """A command-line value different from the field's default, and the config value it gives."""
    meta, default = field.metadata, field.default
    if meta["required"]:
        return "out/run", "out/run"
    if meta["comma_list"]:
        return "a,b", "a,b"
    if isinstance(default, tuple):
        return ("1.5,2", (1.5, 2.0)) if meta["item"] is float else ("p,q", ("p", "q"))
    if isinstance(default, bool):
        return str(not default).lower(), not default
    if isinstance(default, int):
        return str(default + 3), default + 3
    if isinstance(default, float):
        return str(default + 0.25), default + 0.25
    if meta["choices"]:
        other = [c for c in meta["choices"] if c != default and c != "sequence"][0]
        return other, other
    return f"x_{field.name}", f"x_{field.name}"


@pytest.mark.parametrize("scope", [STAGE, SEQUENCE])
def test_every_flag_reaches_the_config(scope):
    flag_values = flags.FlagValues()
    flags_common.define_training_flags(scope, flag_values=flag_values)
    argv, expected = ["binary"], {}
    for field in flags_common.training_fields(scope):
        text, value = _other_value(field)
        argv.append(f"--{field.name}={text}")
        expected[field.name] = value
    flag_values(argv)
    cfg = flags_common.config_from_flags(scope, flag_values=flag_values)
    got = {name: getattr(cfg, name) for name in expected}
    assert got == expected
    assert expected["recipe"] == "fast"  # every recipe field was given explicitly: none preset


def test_defaults_are_the_configs_and_presets_fill_only_what_is_not_given():
    flag_values = flags.FlagValues()
    flags_common.define_training_flags(STAGE, flag_values=flag_values)
    flag_values(["binary", "--model_dir=m", "--recipe=fast", "--learning_rate=5e-4"])
    cfg = flags_common.config_from_flags(STAGE, flag_values=flag_values)
    fast = train_config.RECIPES["fast"]
    want = dataclasses.replace(TrainConfig(model_dir="m", recipe="fast"),
                               **{**fast, "learning_rate": 5e-4})
    assert cfg == want


def test_a_list_value_of_the_wrong_type_is_a_clear_error():
    flag_values = flags.FlagValues()
    flags_common.define_training_flags(SEQUENCE, flag_values=flag_values)
    flag_values(["binary", "--model_dir=m", "--stage_loss_weights=1,heavy"])
    with pytest.raises(ValueError, match="stage_loss_weights takes float values"):
        flags_common.config_from_flags(SEQUENCE, flag_values=flag_values)


@pytest.mark.parametrize("binary, wanted", [
    ("train_stage", ["--train_steps", "--learning_rate", "--time_limit_s", "--[no]overwrite"]),
    ("predict", ["--search", "--tta", "--image_a"]),
])
def test_help_lists_the_binarys_own_flags(binary, wanted):
    """``--help`` (absl's key flags of the main module) shows the flags defined for the binary in
    experiments.flags_common, not only the few it defines itself."""
    out = subprocess.run([sys.executable, "-m", f"experiments.{binary}", "--helpshort"], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    text = out.stdout + out.stderr
    assert all(flag in text for flag in wanted), text[-2000:]


def test_every_flag_problem_in_one_message_before_tensorflow_starts():
    code = ("import sys\n"
            "sys.argv = ['train_stage', '--model_dir=x', '--image_dir=y', '--train_steps=100',\n"
            "            '--warmup_steps=200', '--checkpoint_every=30', '--dropout=2']\n"
            "from absl import app\n"
            "from experiments import train_stage\n"
            "try:\n"
            "    app.run(train_stage.main)\n"
            "except SystemExit as e:\n"
            "    print(e)\n"
            "print('tensorflow' in sys.modules, 'keras' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                         timeout=120)
    lines = out.stdout.strip().splitlines()
    assert lines[-1] == "False False", out.stderr[-2000:]
    assert lines[0].startswith("train_stage: 3 problems: (1) need 0 <= warmup_steps")
    assert "dropout must be in [0, 1)" in lines[0] and "multiple of checkpoint_every" in lines[0]
