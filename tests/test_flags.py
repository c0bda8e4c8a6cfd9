"""The training binaries' flags are generated from TrainConfig's fields: every field is a flag of
a binary, and every flag given on the command line reaches the config unchanged."""

import dataclasses
import os
import subprocess
import sys

import pytest
from absl import flags

from conftest import binary_flags
from experiments import flags_common
from stnh_tf.training import presets
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
    fast = presets.RECIPES["fast"]
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


# ------------------------------------------------------------------------------------------------
# Issue 62: --max_images wherever a binary reads a photograph folder (item 5); the training
# binaries say up front how many steps they train, and that the default is the paper's schedule
# ------------------------------------------------------------------------------------------------
PHOTO_FOLDER_BINARIES = (
    "data_prep.make_dataset", "experiments.make_camera_pairs", "experiments.tune_baselines",
    "experiments.benchmark_data", "experiments.benchmark_stage_pairs", "experiments.reproduce",
    "experiments.semi_supervised", "experiments.loss_weight_ablation", "experiments.train_stage",
    "experiments.train_sequence", "experiments.benchmark_stream")


@pytest.mark.slow
def test_every_binary_that_reads_a_photograph_folder_takes_max_images():
    found = {m: f.get("max_images") for m, f in binary_flags(PHOTO_FOLDER_BINARIES).items()}
    assert found == {m: 0 for m in PHOTO_FOLDER_BINARIES}  # defined everywhere, 0: every image


def test_max_images_refuses_a_negative_number():
    flag_values = flags.FlagValues()
    flags_common.define_max_images(flag_values=flag_values)
    flag_values(["binary", "--max_images=3"])
    assert flag_values.max_images == 3
    with pytest.raises(flags.IllegalFlagValueError, match="max_images"):
        flag_values(["binary", "--max_images=-1"])
    with pytest.raises(ValueError, match="max_images must be an integer >= 0"):
        TrainConfig(model_dir="m", image_dir="p", max_images=-1).validate()
    with pytest.raises(ValueError, match="max_images limits the images of image_dir"):
        TrainConfig(model_dir="m", data_dir="d", max_images=4).validate()


def _run_training_lines(monkeypatch, argv):
    """The lines ``run_training`` logs for ``argv`` (train_stage's flags), training replaced by
    a stand-in that records its config."""
    import types

    from absl import logging

    import stnh_tf.training

    lines, trained = [], []
    fake = types.SimpleNamespace(TrainingDiverged=RuntimeError,
                                 train=lambda cfg, **kw: trained.append(cfg) or
                                 {"final_step": cfg.train_steps})
    monkeypatch.setitem(sys.modules, "stnh_tf.training.loop", fake)
    monkeypatch.setattr(stnh_tf.training, "loop", fake, raising=False)
    monkeypatch.setattr(logging, "info", lambda msg, *a: lines.append(msg % a if a else msg))
    flag_values = flags.FlagValues()
    flags_common.define_training_flags(STAGE, flag_values=flag_values)
    flag_values(["train_stage", "--model_dir=m", "--data_dir=d", *argv])
    cfg = flags_common.config_from_flags(STAGE, flag_values=flag_values)
    flags_common.run_training(cfg, "train_stage", flag_values=flag_values)
    assert [c.train_steps for c in trained] == [cfg.train_steps]
    return lines


def test_training_says_first_that_the_default_is_the_papers_91000_steps(monkeypatch):
    lines = _run_training_lines(monkeypatch, [])
    assert lines[0].startswith("training to step 91,000: the paper's schedule, the default of "
                               "--train_steps: hours to days on a CPU")
    assert lines[0].endswith(f"a smoke run instead: {flags_common.SMOKE_FLAGS} "
                             "(docs/quickstart.md)")
    assert lines[-1] == "finished at step 91000"
    lines = _run_training_lines(monkeypatch, ["--model=homographynet"])
    assert lines[0].startswith("training to step 90,000: DeTone et al.'s schedule")
    lines = _run_training_lines(monkeypatch, flags_common.SMOKE_FLAGS.split())
    assert lines[0] == "training to step 20 (--train_steps)"


def test_the_smoke_flags_are_a_valid_config():
    flag_values = flags.FlagValues()
    flags_common.define_training_flags(STAGE, flag_values=flag_values)
    flag_values(["train_stage", "--model_dir=m", "--data_dir=d",
                 *flags_common.SMOKE_FLAGS.split()])
    flags_common.config_from_flags(STAGE, flag_values=flag_values).validate()


def test_flags_common_doctests():
    import doctest

    result = doctest.testmod(flags_common, optionflags=doctest.ELLIPSIS)
    assert result.attempted >= 4 and result.failed == 0


def test_progress_lines_give_the_time_left_at_the_measured_rate(monkeypatch):
    """Each progress line ends with the time the steps left take at its steps/s."""
    from stnh_tf.training import callbacks

    assert callbacks.time_left(91_000 - 50, 2.0) == f"{(91_000 - 50) / 2.0 / 3600:.1f} h"
    assert callbacks.time_left(450, 2.0) == f"{450 / 2.0 / 60:.1f} min"
    assert callbacks.time_left(18, 2.0) == "9 s"
    assert callbacks.time_left(0, 2.0) == callbacks.time_left(10, 0.0) == ""
    lines = []
    logger = callbacks.ProgressLogger(2, 6, lines.append)
    logger._epoch_start = 0
    ticks = iter([100.0, 101.0, 102.0])  # the clock starts at step 1; 1 s per reading after
    monkeypatch.setattr(callbacks.time, "time", lambda: next(ticks))
    monkeypatch.setattr(callbacks, "_learning_rate", lambda model: 0.01)
    for batch in range(4):  # steps 1..4
        logger.on_train_batch_end(batch, {"loss": 1.0})
    assert lines == ["step 2/6 lr=0.01 loss=1 (1.00 steps/s, 4 s left)",
                     "step 4/6 lr=0.01 loss=1 (1.50 steps/s, 1 s left)"]


def test_progress_logger_prints_the_validation_metrics_at_each_epoch_end(monkeypatch):
    """At an epoch end with validation metrics, one line with the global step and each ``val_``
    metric (the training metrics left out); none without them. (A paper-schedule chunk logged
    no validation line for 3,831 steps when this method had slipped out of the class.)"""
    from stnh_tf.training import callbacks

    lines = []
    logger = callbacks.ProgressLogger(2, 6, lines.append)
    monkeypatch.setattr(callbacks, "_step", lambda model: 500)
    logger.on_epoch_end(0, {"loss": 1.0, "val_loss": 0.5, "val_h_bar_mace": 2.25})
    logger.on_epoch_end(1, {"loss": 1.0})
    assert lines == ["step 500 validation val_h_bar_mace=2.25 val_loss=0.5"]
