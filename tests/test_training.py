"""Stage training: the binary, resume after interruption (in-process and kill -9), the NaN guard,
overwrite protection, stage/dataset checks, the schedule, the semi-supervised mask, a two-device
MirroredStrategy, and an overfitting run that proves losses, STN and gradients are wired."""

import dataclasses
import io
import json
import os
import re
import shutil
import signal
import subprocess
import zipfile
import sys
import time

import h5py
import keras
import numpy as np
import pytest
import tensorflow as tf

from conftest import NARROW_FILTERS, narrow_network
from stnh_tf.data import stage1
from stnh_tf.data.bundled_photos import bundled_image_files
from stnh_tf import geometry
from stnh_tf.training import checkpoints, run_dir, stage_estimates
from stnh_tf.training import config as train_config
from stnh_tf.training import precision
from stnh_tf.training import loop as training
from stnh_tf.data import tfrecords as data
from stnh_tf.modeling import runner
from stnh_tf.training import model_kinds

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    """Bundled photographs, 4 images x 3 pairs for train and test (stage-1 data)."""
    d = str(tmp_path_factory.mktemp("tiny_data"))
    log = lambda *a, **k: None
    stage1.make_dataset("bundled", d, "train", seed=0, num_shards=2, max_images=4, log=log)
    stage1.make_dataset("bundled", d, "test", seed=1, num_shards=1, max_images=4, log=log)
    return d


def _cfg(data_dir, model_dir, **kw):
    base = dict(data_dir=data_dir, model_dir=str(model_dir), train_steps=6, warmup_steps=2,
                batch_size=4, checkpoint_every=2, log_every=1, val_samples=0, learning_rate=0.01)
    base.update(kw)
    return train_config.TrainConfig(**base)


def _quiet(*args, **kwargs):
    pass


def _weights(model_dir):
    model = runner.load_model(model_dir)
    return [np.asarray(w) for w in model.get_weights()]


def _run_binary(args, **kw):
    return subprocess.run([sys.executable, "-m", "experiments.train_stage", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=300, **kw)


def test_schedule_is_warmup_then_cosine():
    cfg = train_config.TrainConfig(data_dir="d", model_dir="m")
    sched = training.learning_rate_schedule(cfg)
    lr = lambda s: float(sched(s))
    assert lr(0) == pytest.approx(0.0)
    assert lr(500) == pytest.approx(0.025, rel=1e-4)  # linear warm-up to 0.05 over 1,000 steps
    assert lr(1000) == pytest.approx(0.05, rel=1e-4)
    # Cosine decay over the next 90,000 steps: 0.05 * 0.5 * (1 + cos(pi * t / 90000)).
    for step in (1000 + 22_500, 1000 + 45_000, 1000 + 80_000):
        t = step - 1000
        assert lr(step) == pytest.approx(0.025 * (1 + np.cos(np.pi * t / 90_000)), rel=1e-4)
    assert lr(91_000) == pytest.approx(0.0, abs=1e-7)


@pytest.mark.slow  # (its error paths: test_binary_refuses_a_bad_flag_before_writing, fast)
def test_binary_one_step_smoke(tiny_data, tmp_path):
    model_dir = tmp_path / "run"
    res = _run_binary([f"--data_dir={tiny_data}", f"--model_dir={model_dir}", "--train_steps=1",
                       "--warmup_steps=0", "--batch_size=4", "--checkpoint_every=1",
                       "--val_samples=4"])
    assert res.returncode == 0, res.stderr[-3000:]
    cfg = json.loads((model_dir / "config.json").read_text())
    assert cfg["train_steps"] == 1 and cfg["learning_rate"] == 0.05 and cfg["momentum"] == 0.9
    assert (model_dir / "checkpoint" / "ckpt-00000001.weights.h5").exists()
    assert json.loads((model_dir / "checkpoint" / "state.json").read_text())["step"] == 1
    assert (model_dir / "model.keras").exists()
    assert any(p.name.startswith("events") for p in (model_dir / "logs" / "train").iterdir())
    # A finished run is not overwritten without --overwrite.
    again = _run_binary([f"--data_dir={tiny_data}", f"--model_dir={model_dir}", "--train_steps=1",
                         "--warmup_steps=0", "--batch_size=4", "--checkpoint_every=1"])
    assert again.returncode != 0 and "--overwrite" in again.stderr


@pytest.fixture(scope="module")
def straight_run(tiny_data, tmp_path_factory):
    """The uninterrupted 6-step run (narrow network) that the resume tests must reproduce."""
    model_dir = tmp_path_factory.mktemp("straight")
    with narrow_network():
        ref = training.train(_cfg(tiny_data, model_dir), printer=_quiet)
    assert ref["final_step"] == 6
    return model_dir


@pytest.mark.slow
@pytest.mark.parametrize("where", ["after_checkpoint", "inside_checkpoint"])
def test_resume_after_interruption_matches_uninterrupted_run(tiny_data, straight_run, tmp_path,
                                                             monkeypatch, narrow, where):
    """Interrupted after the step-4 checkpoint, or inside it (its weight file renamed into place,
    its state.json not yet written: the previous checkpoint, step 2, must still be whole)."""

    class Interrupt(keras.callbacks.Callback):
        def on_epoch_end(self, epoch, logs=None):
            if epoch == 1:  # after the checkpoint at step 4
                raise KeyboardInterrupt

    write_json = checkpoints.atomic_write_json

    def killed_before_state_json(path, obj):
        if path.endswith("state.json") and obj["step"] == 4:
            raise KeyboardInterrupt
        write_json(path, obj)

    cfg = _cfg(tiny_data, tmp_path / "interrupted")
    ckpt = tmp_path / "interrupted" / "checkpoint"
    with monkeypatch.context() as m, pytest.raises(KeyboardInterrupt):
        extra = [Interrupt()]
        if where == "inside_checkpoint":
            m.setattr(checkpoints, "atomic_write_json", killed_before_state_json)
            extra = []
        training.train(cfg, printer=_quiet, extra_callbacks=extra)
    state = json.loads((ckpt / "state.json").read_text())
    expected = 4 if where == "after_checkpoint" else 2
    assert state["step"] == expected and not (tmp_path / "interrupted" / "model.keras").exists()
    names = sorted(p.name for p in ckpt.iterdir())
    assert state["weights"] == f"ckpt-{expected:08d}.weights.h5" and state["weights"] in names
    if where == "inside_checkpoint":  # the uncommitted step-4 file is there, and ignored
        assert "ckpt-00000004.weights.h5" in names
    lines = []
    res = training.train(cfg, printer=lines.append)
    assert any("resuming" in l and f"step {expected}" in l for l in lines)
    assert sorted(p.name for p in ckpt.iterdir()) == ["ckpt-00000006.weights.h5", "state.json"]
    assert res["final_step"] == 6
    a, b = _weights(straight_run), _weights(tmp_path / "interrupted")
    assert len(a) == len(b)
    keras.utils.set_random_seed(0)
    init = model_kinds.build_model(cfg).get_weights()
    moved = max(np.abs(u - w).max() for u, w in zip(a, init))
    diff = max(np.abs(u - v).max() for u, v in zip(a, b))
    # Bit-identical on the development machine; the tolerance only admits reduction-order noise.
    # A resume that lost the optimizer's momentum, the schedule position, the dropout RNG state
    # or the data position differs by a sizeable fraction of the distance the weights moved
    # (losing the dropout state alone gave 12%).
    assert moved > 1e-3
    assert diff <= 1e-4 * moved, (diff, moved)


@pytest.mark.slow
def test_init_from_starts_a_stage_from_a_trained_one(tiny_data, tmp_path, narrow):
    """--init_from (a .keras file or a run dir) sets the stage's regression weights before the
    first step: with a learning rate of 1e-12 the trained model keeps the source's weights, which
    differ from a fresh initialisation. A finished run's dir holding the same file passes the
    start's checks (a dir without model.keras does not) and gives the same weights
    (initialize_from, the step train takes, on a fresh build)."""
    keras.utils.set_random_seed(3)
    src = model_kinds.build_model(_cfg(tiny_data, tmp_path / "x"))
    rng = np.random.default_rng(4)
    src.set_weights([w + rng.normal(scale=0.01, size=w.shape).astype(np.float32)
                     for w in src.get_weights()])
    src_file = str(tmp_path / "source.keras")
    src.save(src_file)
    fresh = model_kinds.build_model(_cfg(tiny_data, tmp_path / "x")).get_weights()
    assert max(np.abs(s - f).max() for s, f in zip(src.get_weights(), fresh)) > 5e-3
    cfg = _cfg(tiny_data, tmp_path / "run", init_from=(src_file,), learning_rate=1e-12,
               warmup_steps=0, train_steps=2, dropout=0.0)
    training.train(cfg, printer=_quiet)
    got = _weights(cfg.model_dir)
    assert len(got) == len(fresh)
    for g, s in zip(got, src.get_weights()):
        np.testing.assert_allclose(g, s, atol=1e-6)
    os.makedirs(tmp_path / "src_run")  # the same weights as a finished run's dir
    shutil.copy(src_file, tmp_path / "src_run" / run_dir.FINAL_MODEL)
    training.check_start(dataclasses.replace(cfg, init_from=(str(tmp_path / "src_run"),)))
    os.makedirs(tmp_path / "unfinished_run")
    with pytest.raises(FileNotFoundError, match="no trained model at .*unfinished_run"):
        training.check_start(dataclasses.replace(cfg,
                                                 init_from=(str(tmp_path / "unfinished_run"),)))
    model = model_kinds.build_model(cfg)
    model_kinds.initialize_from(model, (str(tmp_path / "src_run"),))
    for g, s in zip(model.get_weights(), src.get_weights()):
        np.testing.assert_array_equal(g, s)


@pytest.mark.slow  # (8 s: a training run and its provenance; make test-all)
def test_finished_run_records_its_commit_machine_and_backend(tiny_data, tmp_path, narrow):
    """result.json of a finished run holds, beside its final step, the commit, CPU, cores and
    Keras backend of the process that finished it (what a reproduction's model_provenance reads),
    checked against git (a commit of this checkout's history), os.cpu_count and Keras."""
    training.train(_cfg(tiny_data, tmp_path / "run", train_steps=2), printer=_quiet)
    record = json.loads((tmp_path / "run" / "result.json").read_text())
    assert record["final_step"] == 2 and record["wall_s_this_run"] > 0
    commit = record["machine"]["git_commit"].split("+")[0]  # (HEAD when the suite started)
    assert subprocess.run(["git", "merge-base", "--is-ancestor", commit, "HEAD"],
                          cwd=ROOT).returncode == 0, commit
    assert record["machine"]["cpu_count"] == os.cpu_count()
    assert record["machine"]["keras_backend"] == keras.backend.backend()


def test_init_from_rejects_a_stage_of_another_build(tiny_data, tmp_path, narrow):
    other = model_kinds.build_model(_cfg(tiny_data, tmp_path / "x", input_norm="patch"))
    other.save(tmp_path / "patch_norm.keras")
    cfg = _cfg(tiny_data, tmp_path / "run", init_from=(str(tmp_path / "patch_norm.keras"),))
    with pytest.raises(ValueError, match="same batch_norm and input_norm"):
        training.train(cfg, printer=_quiet)
    for bad in (dict(init_from=("a", "b")), dict(init_from=("a",), model="homographynet")):
        with pytest.raises(ValueError, match="init_from of a single stage takes one stn run"):
            _cfg(tiny_data, tmp_path / "run2", **bad).validate()


@pytest.mark.slow  # (11 s: two training runs; make test-all)
def test_steps_per_execution_makes_the_same_updates(tiny_data, straight_run, tmp_path):
    """Two steps per compiled call: the same six updates as the straight run (one step a call),
    checkpoints at the same steps, and the resume check lets the two settings continue one run."""
    cfg = _cfg(tiny_data, tmp_path / "spe2", steps_per_execution=2, log_every=2)
    with narrow_network():
        out = training.train(cfg, printer=_quiet)
    assert out["final_step"] == 6
    names = sorted(p.name for p in (tmp_path / "spe2" / "checkpoint").iterdir())
    assert "ckpt-00000006.weights.h5" in names
    for got, ref in zip(_weights(cfg.model_dir), _weights(straight_run)):
        np.testing.assert_array_equal(got, ref)
    resumed = dataclasses.replace(cfg, model_dir=str(tmp_path / "resumed"))
    run_dir.prepare_model_dir(resumed)
    run_dir.prepare_model_dir(dataclasses.replace(resumed, steps_per_execution=1))


def test_steps_per_execution_must_divide_checkpoints_and_reports(tiny_data, tmp_path):
    for kw, name in (({"checkpoint_every": 3}, "checkpoint_every"),
                     ({"log_every": 3, "checkpoint_every": 4}, "log_every")):
        with pytest.raises(ValueError, match=f"steps_per_execution \\(2\\) must divide {name}"):
            _cfg(tiny_data, tmp_path / "run", steps_per_execution=2, **kw).validate()
    with pytest.raises(ValueError, match="steps_per_execution"):
        _cfg(tiny_data, tmp_path / "run", steps_per_execution=0).validate()


def test_resume_refuses_different_configuration(tiny_data, tmp_path):
    cfg = _cfg(tiny_data, tmp_path / "run", train_steps=2)
    run_dir.prepare_model_dir(cfg)
    with pytest.raises(ValueError, match="different configuration"):
        run_dir.prepare_model_dir(_cfg(tiny_data, tmp_path / "run", train_steps=4))


def test_resume_may_move_its_folders_but_not_switch_the_kind_of_source(tmp_path):
    """TFRecords and pairs generated from images come in different orders: a run started on one
    is not resumed on the other, while a moved folder of the same kind is fine."""
    base = dict(model_dir=str(tmp_path / "run"), train_steps=2, warmup_steps=1, checkpoint_every=1)
    run_dir.prepare_model_dir(train_config.TrainConfig(data_dir="records", **base))
    run_dir.prepare_model_dir(train_config.TrainConfig(data_dir="moved/records", **base))
    with pytest.raises(ValueError, match="'source': \\('data_dir', 'image_dir'\\)"):
        run_dir.prepare_model_dir(train_config.TrainConfig(image_dir="images", **base))


@pytest.mark.slow
def test_kill_9_then_same_command_finishes(tiny_data, tmp_path):
    model_dir = tmp_path / "killed"
    args = [f"--data_dir={tiny_data}", f"--model_dir={model_dir}", "--train_steps=40",
            "--warmup_steps=2", "--batch_size=2", "--checkpoint_every=2", "--val_samples=0",
            "--learning_rate=0.001"]
    proc = subprocess.Popen([sys.executable, "-m", "experiments.train_stage", *args], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    state = model_dir / "checkpoint" / "state.json"
    deadline = time.time() + 240
    while time.time() < deadline and not (state.exists()
                                          and json.loads(state.read_text())["step"] >= 4):
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed_at = json.loads(state.read_text())["step"]
    assert 4 <= killed_at < 40 and not (model_dir / "model.keras").exists()
    # state.json names a weight file of its step that is there (a kill inside the next checkpoint
    # may leave that one's renamed weight file beside it, uncommitted; temporary files aside).
    committed = json.loads(state.read_text())["weights"]
    assert committed == f"ckpt-{killed_at:08d}.weights.h5"
    left = {p.name for p in state.parent.iterdir() if not p.name.startswith("tmp-")}
    assert {committed, "state.json"} <= left and len(left) <= 3, left
    res = _run_binary(args)  # the very same command
    assert res.returncode == 0, res.stderr[-3000:]
    resumed_at = int(res.stderr.split(f"resuming {model_dir} from step ")[1].split()[0])
    assert resumed_at >= killed_at  # it may have written one more checkpoint before dying
    assert json.loads((model_dir / "result.json").read_text())["final_step"] == 40


@pytest.mark.slow  # the binary's start and a few steps of the full network (~20 s each)
@pytest.mark.parametrize("source", ["data_dir", "image_dir_workers"])
def test_ctrl_c_saves_the_step_and_exits_with_one_line(tiny_data, tmp_path, source):
    """Issue 78, item 5: Ctrl-C (SIGINT to the binary's process group, as a terminal sends it)
    printed a KeyboardInterrupt traceback and saved nothing (the run, before its first
    checkpoint, was even removed), while SIGTERM saved the step. Now SIGINT stops as SIGTERM
    does: after the current step, that step's checkpoint saved between the periodic ones, no final
    model, and one line naming the stop as the binary's last, with no traceback. With pairs
    generated in worker processes (``--image_dir --workers=1``) the workers, which got the
    Ctrl-C too, printed tracebacks and the binary waited a minute for them; now they ignore it;
    and TensorFlow's error on finalizing the stream's iterator at exit no longer follows the
    last line (loop.train collects it first)."""
    model_dir, err_path = tmp_path / "run", tmp_path / "stderr.txt"
    if source == "data_dir":
        data = [f"--data_dir={tiny_data}"]
    else:
        images = tmp_path / "images"
        images.mkdir()
        for _, path in bundled_image_files()[:4]:
            shutil.copy(path, images)
        data = [f"--image_dir={images}", "--workers=1"]
    args = [*data, f"--model_dir={model_dir}", "--train_steps=400", "--warmup_steps=2",
            "--batch_size=2", "--checkpoint_every=200", "--log_every=1", "--val_samples=0",
            "--learning_rate=0.001"]
    with open(err_path, "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "experiments.train_stage", *args],
                                cwd=ROOT, stdout=subprocess.DEVNULL, stderr=err,
                                start_new_session=True)
    try:
        deadline = time.time() + 240
        while time.time() < deadline and not re.search(r"step [2-9]\d*/400", err_path.read_text()):
            assert proc.poll() is None, err_path.read_text()[-3000:]
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGINT)
        proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = err_path.read_text()
    assert "Traceback" not in text and "KeyboardInterrupt" not in text, text[-3000:]
    last = text.strip().splitlines()[-1]
    stopped = re.fullmatch(r"train_stage: stopped by SIGINT at step (\d+) of 400, not finished: "
                           r"the same command resumes it", last)
    assert stopped and proc.returncode == 1, (proc.returncode, text[-3000:])
    step = int(stopped.group(1))
    assert 2 <= step < 200  # between the periodic checkpoints
    state = json.loads((model_dir / "checkpoint" / "state.json").read_text())
    assert state == {**state, "step": step, "weights": f"ckpt-{step:08d}.weights.h5"}
    assert (model_dir / "checkpoint" / state["weights"]).is_file()
    assert not (model_dir / "model.keras").exists()


def test_overwrite_deletes_finished_or_other_runs_and_resumes_an_unfinished_one(tmp_path):
    def make_run(name, finished, **kw):
        cfg = _cfg("d", tmp_path / name, **kw)
        run_dir.prepare_model_dir(cfg)
        (tmp_path / name / "checkpoint").mkdir()
        (tmp_path / name / "checkpoint" / "state.json").write_text("{}")
        if finished:
            (tmp_path / name / "model.keras").write_text("x")
        return cfg

    same = make_run("unfinished", False)
    run_dir.prepare_model_dir(same, overwrite=True)  # re-running an interrupted --overwrite command
    assert (tmp_path / "unfinished" / "checkpoint" / "state.json").exists()
    other = dataclasses.replace(make_run("other", False), learning_rate=0.5)
    with pytest.raises(ValueError, match="learning_rate"):
        run_dir.prepare_model_dir(other)
    run_dir.prepare_model_dir(other, overwrite=True)
    assert not (tmp_path / "other" / "checkpoint").exists()
    assert json.loads((tmp_path / "other" / "config.json").read_text())["learning_rate"] == 0.5
    done = make_run("finished", True)
    with pytest.raises(FileExistsError, match="--overwrite"):
        run_dir.prepare_model_dir(done)
    run_dir.prepare_model_dir(done, overwrite=True)  # (set aside until the new run ends well)
    assert sorted(p.name for p in (tmp_path / "finished").iterdir()) == [".previous_run",
                                                                          "config.json"]
    run_dir.discard_previous_run(str(tmp_path / "finished"))
    assert sorted(p.name for p in (tmp_path / "finished").iterdir()) == ["config.json"]


def test_homographynet_refuses_loss_weights_it_would_ignore():
    assert model_kinds.loss_spec(_cfg("d", "m", model="homographynet"))[1] == {"offsets": 1.0}
    with pytest.raises(ValueError, match="l2_weight/l1_weight/l2_reduction do not apply"):
        model_kinds.loss_spec(_cfg("d", "m", model="homographynet", l2_weight=10.0))


@pytest.mark.slow  # (4 s: a training run; make test-all)
def test_non_finite_loss_stops_with_step_and_checkpoint(tiny_data, tmp_path, narrow):
    cfg = _cfg(tiny_data, tmp_path / "nan", learning_rate=1e12, warmup_steps=0, train_steps=20,
               checkpoint_every=2)
    with pytest.raises(training.TrainingDiverged) as err:
        training.train(cfg, printer=_quiet)
    msg = str(err.value)
    found = re.search(r"non-finite (loss|weights) at step (\d+);", msg)
    assert found and "last good checkpoint" in msg, msg
    assert 1 <= int(found.group(2)) <= 20
    assert not (tmp_path / "nan" / "model.keras").exists()


def _all_finite(weights) -> bool:
    return all(np.isfinite(np.asarray(w, np.float64)).all() for w in weights)


@pytest.mark.slow  # (two short training runs)
def test_non_finite_weights_are_never_checkpointed_nor_finished(tiny_data, tmp_path, narrow):
    """An update can overflow the weights while the loss it came from was finite: the guard
    looked at the loss alone, so the checkpoint of that step (the one TrainingDiverged called
    the last good one, and a chunk commits) held NaN weights, and a run whose last update did
    it finished with a model.keras of NaN weights (a reviewer's runs, lr 1e12). Weights are
    checked at each epoch end now, before the checkpoint: the run stops, its last checkpoint
    finite, no model written."""
    for name, steps in (("every", 20), ("last", 2)):
        cfg = _cfg(tiny_data, tmp_path / name, learning_rate=1e12, warmup_steps=0,
                   train_steps=steps, checkpoint_every=1)
        with pytest.raises(training.TrainingDiverged, match="non-finite (loss|weights)"):
            training.train(cfg, printer=_quiet)
        assert not (tmp_path / name / "model.keras").exists()
        path = checkpoints.checkpoint_weights_path(str(tmp_path / name / "checkpoint"))
        arrays = []
        if path is not None:  # (every float array the checkpoint holds, optimizer's included)
            with h5py.File(path) as f:
                f.visititems(lambda _, item: arrays.append(item[()]) if isinstance(
                    item, h5py.Dataset) and item.dtype.kind == "f" else None)
            assert arrays and _all_finite(arrays)


def test_stage_mismatch_and_missing_data_are_clear_errors(tiny_data, tmp_path, narrow):
    with pytest.raises(ValueError, match="stage-1 data but stage 2"):
        training.train(_cfg(tiny_data, tmp_path / "s2", stage=2), printer=_quiet)
    with pytest.raises((FileNotFoundError, ValueError), match="no_such_dir"):
        training.train(_cfg(str(tmp_path / "no_such_dir"), tmp_path / "x"), printer=_quiet)


def test_semi_supervised_mask_keeps_only_l1(tiny_data, narrow):
    """A sample whose ground-truth H is missing (h_mask = 0) contributes only the L1 term."""
    keras.utils.set_random_seed(0)
    cfg = _cfg(tiny_data, "unused", l2_weight=1.0, l1_weight=1.0)
    model = training.compile_model(model_kinds.build_model(cfg), cfg)
    x, y, w = next(iter(data.load_split(tiny_data, "train", 4, shuffle=False)))
    out = model.predict(x, verbose=0)
    l2 = np.mean((out["h_bar"] - y["h_bar"].numpy()) ** 2, axis=-1)
    l1 = np.mean(np.abs(out["patch_a_warp"] - y["patch_a_warp"].numpy()), axis=(1, 2, 3))
    assert np.all(l2 > 0) and np.all(l1 > 0)
    mask = np.array([1.0, 0.0, 1.0, 0.0], np.float32)
    w = {"h_bar": mask, "patch_a_warp": np.ones(4, np.float32)}
    res = model.evaluate(x, y, sample_weight=w, batch_size=4, verbose=0, return_dict=True)
    assert res["h_bar_loss"] == pytest.approx(np.sum(mask * l2) / 4, rel=1e-4)
    assert res["patch_a_warp_loss"] == pytest.approx(np.mean(l1), rel=1e-4)
    assert res["loss"] == pytest.approx(np.sum(mask * l2) / 4 + np.mean(l1), rel=1e-4)
    # With every mask at zero the L2 term vanishes entirely; the L1 term is unchanged.
    zero = model.evaluate(x, y, sample_weight={"h_bar": np.zeros(4, np.float32),
                                               "patch_a_warp": np.ones(4, np.float32)},
                          batch_size=4, verbose=0, return_dict=True)
    assert zero["h_bar_loss"] == pytest.approx(0.0, abs=1e-9)
    assert zero["loss"] == pytest.approx(np.mean(l1), rel=1e-4)
    # The gradient of an unlabelled batch reaches the network through the STN alone.
    with tf.GradientTape() as tape:
        pred = model(x, training=False)
        loss = tf.reduce_mean(tf.abs(pred["patch_a_warp"] - y["patch_a_warp"]))
    grads = tape.gradient(loss, model.get_layer("regression").trainable_variables)
    assert (all(g is not None for g in grads)
            and any(float(tf.reduce_max(tf.abs(g))) > 0 for g in grads))


MIRRORED_SCRIPT = r"""
import json, sys
import numpy as np
import tensorflow as tf
cpu = tf.config.list_physical_devices("CPU")[0]
tf.config.set_logical_device_configuration(cpu, [tf.config.LogicalDeviceConfiguration()] * 2)
from stnh_tf.training import config as train_config
from stnh_tf.training import loop as training
from stnh_tf.data import tfrecords as data
from stnh_tf.modeling import models, runner
data_dir, work, filters, mask = sys.argv[1], sys.argv[2], json.loads(sys.argv[3]), sys.argv[4]
models.CONV_FILTERS = tuple(filters)  # conftest's narrow network

def stream(masked):
    def fn(cfg, split, start_step):
        ds = data.load_split(cfg.data_dir, split, cfg.batch_size, shuffle=False,
                             skip_batches=start_step)
        if not masked:
            return ds
        weights = tf.constant(json.loads(mask), tf.float32)
        return ds.map(lambda x, y, w: (x, y, {**w, "h_bar": weights}))
    return fn

out = {}
for name, strategy, masked in (("mirrored", "mirrored", True), ("single", "default", True),
                               ("unmasked", "default", False)):
    cfg = train_config.TrainConfig(data_dir=data_dir, model_dir=f"{work}/{name}", train_steps=4,
                                   warmup_steps=1, batch_size=4, checkpoint_every=2,
                                   val_samples=0, learning_rate=1e-3, dropout=0.0,
                                   l2_weight=10.0, strategy=strategy)
    replicas = training._strategy(cfg).num_replicas_in_sync
    res = training.train(cfg, printer=lambda *a: None, stream_fn=stream(masked))
    out[name] = {"replicas": replicas, "final_step": res["final_step"],
                 "history": res["history"]}
    np.savez(f"{work}/{name}.npz", *runner.load_model(cfg.model_dir).get_weights())
print(json.dumps(out))
"""


@pytest.mark.slow
def test_mirrored_strategy_on_two_logical_cpus_equals_one_device(tiny_data, tmp_path):
    """Two logical CPUs under MirroredStrategy train the same weights, and log the same losses,
    as one device with the same global batch of 4 (2 per replica), with h_mask 1 on one
    replica's half of every batch and 0 on the other's: the masked L2 term is reduced over the
    global batch across replicas. The mask matters: training without it ends far away.

    Measured (narrow network, these 4 steps): the two runs' weights differ by 3e-6 of the
    distance they moved (1.8e-6 with the paper's widths at lr 0.01), float32 reduction order
    across replicas, hence the bound 1e-4; without the mask they end 4x that distance apart. A
    reduction over each replica's own batch doubles the masked term's weight, a change of the
    same kind as dropping the mask.

    The batches are read unshuffled: tf.data's distribution of the seeded shuffled stream gives
    another (reproducible) order than one device reads. The logged MACE metric is not compared:
    under MirroredStrategy, Keras reports half the single device's when one replica's samples
    all have mask 0 (measured: 11.83 against 23.66 px at step 1; the losses agree)."""
    work = tmp_path / "m"
    work.mkdir()
    res = subprocess.run([sys.executable, "-c", MIRRORED_SCRIPT, tiny_data, str(work),
                          json.dumps(NARROW_FILTERS), json.dumps([1.0, 1.0, 0.0, 0.0])],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert {k: (v["replicas"], v["final_step"]) for k, v in out.items()} == {
        "mirrored": (2, 4), "single": (1, 4), "unmasked": (1, 4)}
    for key in ("loss", "h_bar_loss", "patch_a_warp_loss"):
        np.testing.assert_allclose(out["mirrored"]["history"][key],
                                   out["single"]["history"][key], rtol=1e-4, err_msg=key)
    runs = {}
    for name in out:
        with np.load(work / f"{name}.npz") as z:
            runs[name] = [z[f"arr_{i}"] for i in range(len(z.files))]
    with narrow_network():
        keras.utils.set_random_seed(0)
        init = model_kinds.build_model(_cfg(tiny_data, "unused", dropout=0.0)).get_weights()

    def distance(u, v):
        assert len(u) == len(v)
        return max(np.abs(a - b).max() for a, b in zip(u, v))

    moved = distance(runs["single"], init)
    assert moved > 1e-3
    assert distance(runs["mirrored"], runs["single"]) <= 1e-4 * moved
    assert distance(runs["unmasked"], runs["single"]) > 0.5 * moved


@pytest.mark.slow
def test_overfits_eight_pairs(tmp_path_factory):
    """The model and losses of :mod:`stnh_tf.training.loop` drive the MACE of 8 fixed pairs far
    below the identity's, and the photometric error down with it: losses, STN and gradients are
    wired through every layer (8 different targets cannot be met by the output bias alone). Adam
    with full batches, because SGD at this scale needs thousands of steps (no claim about
    generalization; the schedule itself is tested above). Measured with init seeds 0/1/2 on a
    Zen 3 CPU (fit in 10-epoch calls): MACE / identity 0.39 / 0.40 / 0.47 and L1 / initial L1
    0.36 / 0.41 / 0.52 after 100 epochs, ~95 s; the descent is not monotone (0.67 -> 0.89 -> 0.51
    between epochs 60 and 80 for seed 1), hence end-point thresholds with a margin."""
    d = str(tmp_path_factory.mktemp("eight"))
    stage1.make_dataset("bundled", d, "train", seed=5, samples_per_image=2, num_shards=1,
                        max_images=4, log=lambda *a, **k: None)
    arrays = data.load_arrays(d, "train")
    assert len(arrays["h_ba"]) == 8
    keras.utils.set_random_seed(0)
    cfg = _cfg(d, "unused", dropout=0.0)
    model = model_kinds.build_model(cfg)
    losses, weights, _ = model_kinds.loss_spec(cfg)
    model.compile(optimizer=keras.optimizers.Adam(3e-4), loss=losses, loss_weights=weights)
    x = {"patch_a": arrays["patch_a"], "patch_b": arrays["patch_b"]}
    y = {"h_bar": arrays["h_bar"], "patch_a_warp": arrays["patch_a_t"]}

    def mace_and_l1():
        out = model.predict(x, verbose=0)
        h = geometry.denormalize_homography(
            geometry.vector_to_matrix(out["h_bar"].astype(np.float64)))
        return (float(geometry.mean_corner_error(h, arrays["h_ba"])),
                float(np.abs(out["patch_a_warp"] - arrays["patch_a_t"]).mean()))

    mace0, l1_0 = mace_and_l1()
    identity = float(geometry.mean_corner_error(np.broadcast_to(np.eye(3), arrays["h_ba"].shape),
                                                arrays["h_ba"]))
    assert mace0 == pytest.approx(identity, rel=1e-3)  # identity-initialised output layer
    model.fit(x, y, batch_size=8, epochs=100, verbose=0)
    mace, l1 = mace_and_l1()
    assert identity > 15.0
    assert mace < 0.7 * identity, (mace, identity)
    assert l1 < 0.85 * l1_0, (l1, l1_0)


CPUINFO = {  # abridged /proc/cpuinfo of five CPUs (the Milan with its two logical CPUs), one
    # without flags
    "epyc_milan": "processor\t: 0\nvendor_id\t: AuthenticAMD\n"
                  "flags\t\t: fpu sse2 avx avx2 fma f16c\n\n"
                  "processor\t: 1\nvendor_id\t: AuthenticAMD\n"
                  "flags\t\t: fpu sse2 avx avx2 fma f16c\n",
    "sapphire_rapids": "processor\t: 0\nflags\t\t: avx2 avx512f avx512_bf16 amx_bf16 amx_tile\n",
    "xeon_no_amx": "processor\t: 0\nvendor_id\t: GenuineIntel\n"
                   "flags\t\t: avx2 avx512f avx512_bf16 avx512_fp16\n",
    "epyc_zen4": "processor\t: 0\nvendor_id\t: AuthenticAMD\n"
                 "flags\t\t: avx2 avx512f avx512_bf16\n",
    "neoverse_v1": "processor\t: 0\nFeatures\t: fp asimd sve bf16 i8mm\nCPU implementer\t: 0x41\n",
    "no_flags": "processor\t: 0\nmodel name\t: something\n",
}


@pytest.mark.parametrize("name, expected", [("epyc_milan", False), ("sapphire_rapids", True),
                                            ("xeon_no_amx", True), ("epyc_zen4", True),
                                            ("neoverse_v1", True), ("no_flags", None)])
def test_cpu_has_native_bfloat16_reads_cpu_flags(tmp_path, name, expected):
    path = tmp_path / name
    path.write_text(CPUINFO[name])
    assert precision.cpu_has_native_bfloat16(str(path)) is expected
    assert precision.cpu_has_native_bfloat16(str(tmp_path / "missing")) is None


def test_cpu_vendor_reads_vendor_id(tmp_path):
    expected = {"epyc_milan": "AuthenticAMD", "epyc_zen4": "AuthenticAMD",
                "xeon_no_amx": "GenuineIntel", "neoverse_v1": None, "no_flags": None}
    for name, vendor in expected.items():
        (tmp_path / name).write_text(CPUINFO[name])
        assert precision.cpu_vendor(str(tmp_path / name)) == vendor, name
    assert precision.cpu_vendor(str(tmp_path / "missing")) is None


def test_mixed_precision_warning_for_emulated_bfloat16_and_no_amx(tmp_path, monkeypatch):
    for name, text in CPUINFO.items():
        (tmp_path / name).write_text(text)
    mixed = train_config.TrainConfig(data_dir="d", model_dir="m", mixed_precision=True)
    fp32 = train_config.TrainConfig(data_dir="d", model_dir="m", mixed_precision=False)
    monkeypatch.setattr(precision, "accelerator_present", lambda: False)
    warning = precision.mixed_precision_warning(mixed, str(tmp_path / "epyc_milan"))
    assert "no bfloat16 instructions" in warning and "--nomixed_precision" in warning
    assert precision.mixed_precision_warning(fp32, str(tmp_path / "epyc_milan")) is None
    warning = precision.mixed_precision_warning(mixed, str(tmp_path / "xeon_no_amx"))
    assert "no AMX" in warning and "benchmark_training" in warning
    assert precision.mixed_precision_warning(fp32, str(tmp_path / "xeon_no_amx")) is None
    for name in ("sapphire_rapids", "neoverse_v1", "no_flags", "epyc_zen4"):
        assert precision.mixed_precision_warning(mixed, str(tmp_path / name)) is None
    monkeypatch.setattr(precision, "accelerator_present", lambda: True)
    assert precision.mixed_precision_warning(mixed, str(tmp_path / "epyc_milan")) is None


def test_accelerator_present_agrees_with_tensorflow():
    assert precision.accelerator_present() == bool(tf.config.list_physical_devices("GPU"))


# ------------------------------------------------------------------------------------------------
# Nothing lost, nothing crashes: --overwrite, failed starts, flags, paths read from files
# ------------------------------------------------------------------------------------------------
def test_overwrite_never_deletes_a_folder_that_is_not_a_run(tmp_path):
    """A folder with someone's own config.json, notes and sources is not a training run: it is
    refused with or without --overwrite, and survives whole."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "config.json").write_text(json.dumps({"name": "my project", "lr": 3}))
    (mine / "notes.txt").write_text("notes")
    (mine / "main.py").write_text("print('mine')")
    before = sorted(p.name for p in mine.iterdir())
    for overwrite in (False, True):
        with pytest.raises(ValueError, match=r"config.json.* is not the configuration of a "
                                             r"stnh-tf training run"):
            run_dir.prepare_model_dir(_cfg("d", mine), overwrite=overwrite)
        assert sorted(p.name for p in mine.iterdir()) == before
    (mine / "config.json").unlink()
    (mine / "model.keras").write_text("someone's model")  # no config.json at all
    with pytest.raises(FileExistsError, match="holds no training run"):
        run_dir.prepare_model_dir(_cfg("d", mine), overwrite=True)
    assert (mine / "model.keras").read_text() == "someone's model"
    # A config.json that is a list, or not JSON: an error naming the file, never a traceback.
    for text in ("[1, 2]", "{broken"):
        (mine / "config.json").write_text(text)
        with pytest.raises(ValueError, match=re.escape(str(mine / "config.json"))):
            run_dir.prepare_model_dir(_cfg("d", mine), overwrite=True)
        assert (mine / "notes.txt").exists()
    # A real finished run: --overwrite replaces what the run wrote, and only that (set aside
    # until the new run ends well, then deleted).
    run = tmp_path / "run"
    run_dir.prepare_model_dir(_cfg("d", run))
    assert json.loads((run / "config.json").read_text())["format"] == "stnh_tf.train_config"
    (run / "model.keras").write_text("x")
    (run / "logs").mkdir()
    (run / "my_notes.txt").write_text("kept")
    run_dir.prepare_model_dir(_cfg("d", run, learning_rate=0.5), overwrite=True)
    assert sorted(p.name for p in (run / run_dir.PREVIOUS_RUN).iterdir()) == [
        "config.json", "logs", "model.keras"]
    run_dir.discard_previous_run(str(run))
    assert sorted(p.name for p in run.iterdir()) == ["config.json", "my_notes.txt"]


def test_run_config_without_the_format_marker_is_still_a_run(tmp_path):
    """config.json files written before the marker existed (runs in progress) stay resumable."""
    cfg = _cfg("d", tmp_path)
    (tmp_path / "config.json").write_text(json.dumps(cfg.to_json()))
    assert run_dir.prepare_model_dir(cfg) is False  # resumed, not a new run
    assert json.loads((tmp_path / "config.json").read_text())["format_version"] == 1


def test_failed_overwrite_keeps_the_finished_run(tiny_data, tmp_path, narrow):
    """--overwrite with a flag the data cannot serve (a batch larger than the dataset) fails
    before anything is deleted."""
    run = tmp_path / "run"
    run_dir.prepare_model_dir(_cfg(tiny_data, run))
    (run / "model.keras").write_text("finished model")
    (run / "result.json").write_text("{}")
    with pytest.raises(ValueError, match="fewer than one batch of 64"):
        training.train(_cfg(tiny_data, run, batch_size=64), overwrite=True, printer=_quiet)
    assert (run / "model.keras").read_text() == "finished model"
    assert sorted(p.name for p in run.iterdir()) == ["config.json", "model.keras", "result.json"]


def test_failed_start_leaves_the_folder_as_it_was(tiny_data, tmp_path, narrow):
    """An error after config.json was written (here: the data stream fails) removes what the
    start wrote, so the corrected command is not refused as 'a different configuration'."""
    def broken_stream(cfg, split, start_step):
        raise RuntimeError("stream failed")

    for model_dir, existed in ((tmp_path / "new", False), (tmp_path / "empty", True)):
        if existed:
            model_dir.mkdir()
        with pytest.raises(RuntimeError, match="stream failed"):
            training.train(_cfg(tiny_data, model_dir), printer=_quiet, stream_fn=broken_stream)
        assert model_dir.exists() == existed and not (existed and list(model_dir.iterdir()))
        assert run_dir.prepare_model_dir(_cfg(tiny_data, model_dir, learning_rate=0.02)) is True


@pytest.mark.slow  # (two training calls: the make test time)
def test_an_overwrite_failing_before_its_first_checkpoint_puts_the_finished_run_back(
        tiny_data, tmp_path, narrow):
    """--overwrite deleted the finished run before the new one had anything: a retrain that
    failed in its first step (here the stream; an out-of-memory, an I/O error) left an empty
    folder. The finished run is set aside and put back; a retrain that ends well deletes it."""
    run = tmp_path / "run"
    run_dir.prepare_model_dir(_cfg(tiny_data, run))
    (run / "model.keras").write_text("finished model")
    (run / "result.json").write_text('{"final_step": 7}')
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}

    def broken_stream(cfg, split, start_step):
        raise MemoryError("the retrain's first step")

    new = _cfg(tiny_data, run, learning_rate=0.02, train_steps=2, checkpoint_every=2)
    with pytest.raises(MemoryError):
        training.train(new, overwrite=True, printer=_quiet, stream_fn=broken_stream)
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before
    assert sorted(p.name for p in run.iterdir()) == ["config.json", "model.keras", "result.json"]
    result = training.train(new, overwrite=True, printer=_quiet)
    assert result["final_step"] == 2 and not (run / run_dir.PREVIOUS_RUN).exists()
    assert (run / "model.keras").read_bytes() != before["model.keras"]


@pytest.mark.slow  # (two training calls: the make test time)
def test_an_overwrite_stopped_before_its_end_keeps_the_run_it_replaces(tiny_data, tmp_path,
                                                                         narrow):
    """An --overwrite run stopped early on purpose (its time limit, a first Ctrl-C or SIGTERM:
    the loop stops after the step and returns) counted as ended well, and the finished run it
    replaces was deleted. It stays set aside until the new run finishes (the stop's message
    says so); the resumed run that finishes deletes it."""
    run = tmp_path / "run"
    run_dir.prepare_model_dir(_cfg(tiny_data, run))
    (run / "model.keras").write_text("finished model")
    new = _cfg(tiny_data, run, learning_rate=0.02, train_steps=4, checkpoint_every=1)
    said = []
    result = training.train(new, overwrite=True, printer=said.append, time_limit_s=1e-6)
    assert result["final_step"] < 4 and result["stopped_by"]
    assert (run / run_dir.PREVIOUS_RUN / "model.keras").read_text() == "finished model"
    assert any(run_dir.PREVIOUS_RUN in line and "until this one finishes" in line
               for line in said), said
    result = training.train(new, printer=_quiet)  # resumed to its end
    assert result["final_step"] == 4 and not (run / run_dir.PREVIOUS_RUN).exists()


def test_a_finished_replacement_is_the_run_a_later_overwrite_sets_aside(tiny_data, tmp_path):
    """A replacement that finished its model but did not discard the run it replaced (its
    result.json write failed, or a kill) was deleted by the next --overwrite, which kept the
    older run aside and put it back when it failed early: the folder silently went back two
    runs. The newest finished run is kept aside now."""
    run = tmp_path / "run"
    run_dir.prepare_model_dir(_cfg(tiny_data, run))
    (run / "model.keras").write_text("R1")
    run_dir.prepare_model_dir(_cfg(tiny_data, run, learning_rate=0.02), overwrite=True)
    assert (run / run_dir.PREVIOUS_RUN / "model.keras").read_text() == "R1"
    (run / "model.keras").write_text("R2")  # finished; R1 still aside
    run_dir.set_aside(str(run))  # the next --overwrite
    assert (run / run_dir.PREVIOUS_RUN / "model.keras").read_text() == "R2"
    run_dir.undo_new_run(str(run), made_dir=False)  # that run failing before a checkpoint
    assert (run / "model.keras").read_text() == "R2"
    assert not (run / run_dir.PREVIOUS_RUN).exists()


def test_an_overwrite_failing_between_the_folder_and_the_model_puts_the_run_back(
        tiny_data, tmp_path, monkeypatch):
    """A failure after the folder was prepared but before the training loop's guard (setting the
    seed or the precision policy; an interrupt) kept the folder locked and the finished run set
    aside: the next command was refused while nothing ran. Both are undone now."""
    run = tmp_path / "run"
    run_dir.prepare_model_dir(_cfg(tiny_data, run))
    (run / "model.keras").write_text("finished model")
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}

    def interrupted(seed):
        raise KeyboardInterrupt("between the folder and the model")

    monkeypatch.setattr(keras.utils, "set_random_seed", interrupted)
    new = _cfg(tiny_data, run, learning_rate=0.02, train_steps=2, checkpoint_every=2)
    with pytest.raises(KeyboardInterrupt):
        training.train(new, overwrite=True, printer=_quiet)
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before
    assert sorted(p.name for p in run.iterdir()) == ["config.json", "model.keras"]
    run_dir.RunLock(str(run)).release()  # not held: taken and given back at once


def test_a_run_set_aside_with_nothing_in_its_place_is_put_back(tiny_data, tmp_path):
    """A kill between --overwrite's set-aside and the new config.json left only .previous_run:
    every later command was refused ("holds no training run"). The run is put back first."""
    run = tmp_path / "run"
    run_dir.prepare_model_dir(_cfg(tiny_data, run))
    (run / "model.keras").write_text("finished model")
    run_dir.set_aside(str(run))  # (then killed)
    assert sorted(p.name for p in run.iterdir()) == [run_dir.PREVIOUS_RUN]
    with pytest.raises(FileExistsError, match="holds a finished model"):
        run_dir.prepare_model_dir(_cfg(tiny_data, run))
    assert (run / "model.keras").read_text() == "finished model"


def test_corrupted_shard_during_training_names_the_file(tiny_data, tmp_path, narrow):
    data_dir = tmp_path / "data"
    shutil.copytree(tiny_data, data_dir)
    shard = data_dir / "train-00001-of-00002.tfrecord"
    blob = bytearray(shard.read_bytes())
    blob[len(blob) // 2] ^= 0xFF  # same size, bad CRC: only reading the records finds it
    shard.write_bytes(bytes(blob))
    with pytest.raises(data.ShardError, match="train-00001-of-00002.tfrecord"):
        training.train(_cfg(str(data_dir), tmp_path / "run", train_steps=2, checkpoint_every=2),
                       printer=_quiet)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("field, value", [
    ("checkpoint_every", -5), ("checkpoint_every", 0), ("shuffle_buffer", 0), ("val_samples", -3),
    ("batch_size", 0), ("log_every", 0), ("samples_per_image", 0), ("workers", -1), ("seed", -1),
    ("val_seed", -2), ("dropout", 1.0), ("dropout", -0.1), ("momentum", 1.5),
    ("l2_weight", float("nan")), ("l1_weight", -1.0), ("checkpoint_every", 2.0)])
def test_bad_flag_values_are_clear_errors(field, value):
    cfg = _cfg("d", "m", **{field: value})
    with pytest.raises(ValueError, match=rf"^{field} must be .*received {re.escape(repr(value))}"):
        cfg.validate()


def test_both_loss_weights_zero_is_refused():
    """l2_weight = l1_weight = 0 would train nothing and mark the run finished; one of them alone
    at 0 is a valid ablation."""
    with pytest.raises(ValueError, match="l2_weight and l1_weight are both 0"):
        _cfg("d", "m", l2_weight=0.0, l1_weight=0.0).validate()
    for weights in ({"l2_weight": 0.0}, {"l1_weight": 0.0}):
        _cfg("d", "m", **weights).validate()


def test_binary_refuses_a_bad_flag_before_writing(tiny_data, tmp_path):
    """--checkpoint_every=-5 used to exit 0 with an untrained model.keras."""
    res = _run_binary([f"--data_dir={tiny_data}", f"--model_dir={tmp_path / 'run'}",
                       "--train_steps=10", "--checkpoint_every=-5", "--warmup_steps=0"])
    assert res.returncode != 0 and "Traceback" not in res.stderr
    assert "train_stage: checkpoint_every must be an integer >= 1; received -5." in res.stderr
    assert not (tmp_path / "run").exists()


def test_checkpoint_state_cannot_name_weights_outside_its_folder(tmp_path):
    ckpt = tmp_path / "run" / "checkpoint"
    ckpt.mkdir(parents=True)
    (tmp_path / "elsewhere.weights.h5").write_text("not this run's")
    for name in ("../../elsewhere.weights.h5", str(tmp_path / "elsewhere.weights.h5")):
        (ckpt / "state.json").write_text(json.dumps({"step": 2, "weights": name}))
        with pytest.raises(ValueError, match="is not a path inside"):
            checkpoints.checkpoint_weights_path(str(ckpt))
    (ckpt / "state.json").write_text("{not json")
    with pytest.raises(ValueError, match="state.json"):
        checkpoints.checkpoint_weights_path(str(ckpt))


def _ticking_time_limit():
    """A TimeLimit on a fake clock on which each training step ends 1,000 s after it began."""
    from stnh_tf.training import callbacks

    class Ticking(callbacks.TimeLimit):
        def __init__(self, *args, **kwargs):
            self.offset = 0.0
            super().__init__(*args, clock=lambda: time.monotonic() + self.offset, **kwargs)

        def on_train_batch_end(self, batch, logs=None):
            self.offset += 1000.0
            super().on_train_batch_end(batch, logs)

    return Ticking


@pytest.mark.slow  # (make test-all)
def test_chunks_stop_at_the_time_limit_and_continue_on_another_machine(tiny_data, straight_run,
                                                                       tmp_path, narrow,
                                                                       monkeypatch):
    """Three chunks of the 6-step run, each stopped by the time limit after one checkpoint (steps
    of 1,000 s on a fake clock, a limit of 2,500 s: two steps), each on a fresh run folder
    (another machine) resuming from the checkpoint committed in the repository folder: the
    finished model (without optimizer state) equals the uninterrupted run's, the committed
    checkpoint is gone, and the ledger has one row per chunk."""
    from stnh_tf.training import chunks, ledger

    monkeypatch.setattr(training, "TimeLimit", _ticking_time_limit())
    repo = tmp_path / "repo"
    rows = []
    for k in range(3):
        cfg = _cfg(tiny_data, tmp_path / f"machine{k}")
        rows.append(chunks.run_chunk(cfg, str(repo), 2500.0, f"machine {k}", printer=_quiet))
        resume = repo / "resume" / "stage1"
        if k < 2:
            assert json.loads((resume / "state.json").read_text())["step"] == 2 * (k + 1)
            assert not (tmp_path / f"machine{k}" / "model.keras").exists()
            assert sorted(p.name for p in resume.iterdir()) == [
                "ckpt-%08d.weights.h5" % (2 * (k + 1)), "config.json", "state.json"]
    assert [(r["from_step"], r["to_step"], r["done"]) for r in rows] == [
        (0, 2, False), (2, 4, False), (4, 6, True)]
    assert not (repo / "resume" / "stage1").exists()
    assert json.loads((repo / "ledger.json").read_text()) == rows
    from stnh_tf.provenance import machine_info  # each row: the commit, machine and versions
    assert all(r["machine"]["keras"] == keras.__version__
               and r["machine"]["git_commit"] == machine_info()["git_commit"] for r in rows)
    record = json.loads((repo / "stage1.json").read_text())
    assert record["chunks"] == rows and record["final_step"] == 6
    assert record["config"] == dataclasses.replace(cfg, model_dir=record["config"]["model_dir"]
                                                   ).to_json()
    assert record["wall_s"] == pytest.approx(sum(r["wall_s"] for r in rows), abs=0.2)
    assert record["machines"] == ["machine 0 (tensorflow)", "machine 1 (tensorflow)",
                                  "machine 2 (tensorflow)"]
    from stnh_tf.inference import shipped_weights  # the card of a chunked stage: its record
    card = shipped_weights.ship([str(repo / "stage1.keras")], str(tmp_path / "shipped"))
    entry = card["stages"][0]
    assert (entry["config"], entry["chunks"], entry["final_step"]) == (record["config"], rows, 6)
    def optimizer_saved(path):
        with zipfile.ZipFile(path) as z, h5py.File(io.BytesIO(z.read("model.weights.h5"))) as f:
            return "optimizer" in f

    assert optimizer_saved(tmp_path / "machine2" / "model.keras")
    assert not optimizer_saved(repo / "stage1.keras")
    finished = keras.saving.load_model(str(repo / "stage1.keras"), compile=False)
    a = _weights(straight_run)
    b = [np.asarray(w) for w in finished.get_weights()]
    assert max(np.abs(u - v).max() for u, v in zip(a, b)) <= 1e-4 * max(np.abs(u).max() for u in a)
    doc = tmp_path / "gpu.md"
    doc.write_text(f"# ledger\n{ledger.LEDGER_START}\nold\n{ledger.LEDGER_END}\nafter\n")
    assert ledger.write_ledger_table(str(repo), str(doc))
    lines = doc.read_text().splitlines()
    assert lines[4] == "| 1 | 0 -> 2 | machine 0 | tensorflow | %.2f | 0 | %s |" % (
        rows[0]["steps_per_s"], rows[0]["date"]) and lines[-1] == "after"
    assert not ledger.write_ledger_table(str(repo), str(doc))  # unchanged the second time


@pytest.mark.slow  # (make test-all)
def test_a_part_other_than_a_stage_is_chunked_under_its_own_name(tiny_data, tmp_path, narrow,
                                                                  monkeypatch):
    """paper_schedule --part: the 2-stage sequence model trained in two chunks (the first
    stopped by the time limit after one checkpoint, on a fake clock; the second on a fresh run
    folder, another machine) is committed under its own name (resume/sequence2/, then
    sequence2.keras and sequence2.json), its ledger rows carry the part and the ledger table
    shows it; a finished part is refused by name, and a hierarchical stage beside it is not."""
    from stnh_tf.training import chunks, ledger

    monkeypatch.setattr(training, "TimeLimit", _ticking_time_limit())
    repo = tmp_path / "repo"
    cfg = lambda k: _cfg(tiny_data, tmp_path / f"machine{k}", model="sequence",  # noqa: E731
                         num_stages=2, train_steps=4, learning_rate=1e-3)
    first = chunks.run_chunk(cfg(0), str(repo), 2500.0, "machine 0", printer=_quiet,
                             part="sequence2")
    resume = repo / "resume" / "sequence2"
    assert (first["part"], first["to_step"], first["done"]) == ("sequence2", 2, False)
    assert json.loads((resume / "state.json").read_text())["step"] == 2
    assert not (repo / "resume" / "stage1").exists()
    monkeypatch.undo()  # the real clock: the second chunk trains to the end
    second = chunks.run_chunk(cfg(1), str(repo), 0, "machine 1", printer=_quiet,
                              part="sequence2")
    assert (second["from_step"], second["to_step"], second["done"]) == (2, 4, True)
    assert not resume.exists() and not (repo / "stage1.keras").exists()
    record = json.loads((repo / "sequence2.json").read_text())
    assert record["part"] == "sequence2" and record["chunks"] == [first, second]
    assert record["config"]["model"] == "sequence" and record["final_step"] == 4
    model = keras.saving.load_model(str(repo / "sequence2.keras"), compile=False)
    assert {"h_bar_1", "h_bar_2"} <= set(model.output_names)
    table = ledger.ledger_table(json.loads((repo / "ledger.json").read_text()))
    assert table.splitlines()[2].startswith("| sequence2 | 0 -> 2 | machine 0 |")
    with pytest.raises(FileExistsError, match="part sequence2 is finished"):
        chunks.run_chunk(cfg(2), str(repo), 0, "machine 2", printer=_quiet, part="sequence2")
    assert not (tmp_path / "machine2").exists()
    assert chunks.finished_model(str(repo), 1) == str(repo / "stage1.keras")
    for bad in ("", "Stage1", "../up", "a/b", None):
        with pytest.raises(ValueError, match="a part is a stage number or a name"):
            chunks.part_name(bad)


def test_a_chunk_goes_on_with_the_next_stage_in_the_time_it_leaves(monkeypatch):
    """run_stages: where a chunk finishes its stage, the next stage's chunk gets the time left
    (on a fake clock); it stops at an unfinished stage, at the last stage, and where less than
    min_next_s is left; with no limit every stage trains to its end."""
    from stnh_tf.training import chunks

    clock, calls, plan = [0.0], [], {}

    def chunk(stage, root, left, device, printer, commit, step_back=False):
        calls.append((stage, left))  # a chunk: its time and whether done
        spent, done = plan[stage]
        clock[0] += spent
        return {"stage": stage, "done": done}

    monkeypatch.setattr(chunks, "run_chunk", chunk)

    def run(limit, stages, first=1, last=3):
        clock[0], lines = 0.0, []
        calls.clear()
        plan.clear()
        plan.update(stages)
        rows = chunks.run_stages(lambda k: k, first, last, "repo", limit, "machine",
                                 printer=lines.append, clock=lambda: clock[0])
        assert [r["stage"] for r in rows] == [stage for stage, _ in calls]
        return list(calls), lines

    done3 = {1: (400.0, True), 2: (300.0, True), 3: (200.0, True)}
    assert run(1000.0, done3)[0] == [(1, 1000.0), (2, 600.0), (3, 300.0)]
    calls, lines = run(800.0, done3)
    assert calls == [(1, 800.0), (2, 400.0)]  # 100 s left: under 120, stage 3 not started
    assert lines[-1] == "stage 3 not started: 100 s left, under 120 s"
    assert run(1000.0, {1: (400.0, False)})[0] == [(1, 1000.0)]  # stage 1 not finished
    assert run(0.0, done3)[0] == [(1, 0.0), (2, 0.0), (3, 0.0)]  # no limit: each to its end
    assert run(1000.0, done3, first=2, last=2)[0] == [(2, 1000.0)]
    with pytest.raises(ValueError, match="first stage"):
        run(1000.0, done3, first=3, last=2)


def _h5_checkpoint(folder, step):
    """A checkpoint of ``step`` in ``folder``: state.json and the weights file it names, an HDF5
    file of a weight of its own and the optimizer's step count, as Keras saves them."""
    folder.mkdir(parents=True)
    with h5py.File(folder / f"ckpt-{step:08d}.weights.h5", "w") as f:
        f["layers/dense/vars/0"] = np.full((4,), step, np.float32)
        f["optimizer/vars/0"] = np.int64(step)
    (folder / "state.json").write_text(json.dumps({"step": step,
                                                   "weights": f"ckpt-{step:08d}.weights.h5"}))


def test_sync_in_keeps_a_newer_local_checkpoint(tmp_path):
    from stnh_tf.training import chunks

    _h5_checkpoint(tmp_path / "resume", 4)
    (tmp_path / "resume" / "config.json").write_text("{}")
    _h5_checkpoint(tmp_path / "run" / "checkpoint", 6)
    assert chunks.sync_in(str(tmp_path / "resume"), str(tmp_path / "run")) is None
    assert chunks.sync_in(str(tmp_path / "resume"), str(tmp_path / "new")) == 4
    name = "ckpt-00000004.weights.h5"
    assert (tmp_path / "new" / "checkpoint" / name).read_bytes() == \
        (tmp_path / "resume" / name).read_bytes()
    assert (tmp_path / "new" / "config.json").read_text() == "{}"


def test_saved_stage_estimates_travel_with_the_committed_checkpoint(tmp_path):
    """sync_out puts the run folder's saved estimates into the resume folder; sync_in puts them
    into a run folder that lacks them (a chunk on another machine) and keeps a folder's own."""
    from stnh_tf.training import chunks

    run = tmp_path / "run"
    _h5_checkpoint(run / "checkpoint", 4)
    (run / "config.json").write_text("{}")
    h = np.random.default_rng(0).normal(size=(5, 3, 3))
    stage_estimates.save_estimates(str(run), "train", "key-1", h, {"outside_context": 2})
    resume = tmp_path / "repo" / "resume" / "stage2"
    assert chunks.sync_out(str(run), str(resume)) == 4
    assert sorted(os.listdir(resume)) == ["ckpt-00000004.weights.h5", "config.json",
                                          "stage_estimates_train.npz", "state.json"]
    other = tmp_path / "other"
    assert chunks.sync_in(str(resume), str(other)) == 4
    got, rejected = stage_estimates.load_estimates(str(other), "train", "key-1")
    np.testing.assert_array_equal(got, h.astype(np.float32))
    assert rejected == {"outside_context": 2}
    stage_estimates.save_estimates(str(other), "train", "key-2", h[:1], {})
    chunks.sync_in(str(resume), str(other))
    assert stage_estimates.load_estimates(str(other), "train", "key-2")[0].shape == (1, 3, 3)


def test_saved_stage_estimates_are_read_only_under_their_key(tmp_path):
    from stnh_tf.training import run_dir

    assert stage_estimates.load_estimates(str(tmp_path), "val", "k") is None  # none saved
    h = np.random.default_rng(1).normal(size=(3, 3, 3))
    path = stage_estimates.save_estimates(str(tmp_path), "val", "k", h, {"singular": 1})
    assert os.path.basename(path) == run_dir.ESTIMATES_FILES["val"]
    assert stage_estimates.load_estimates(str(tmp_path), "train", "k") is None  # another split
    assert stage_estimates.load_estimates(str(tmp_path), "val", "other") is None  # other pairs or stages
    got, rejected = stage_estimates.load_estimates(str(tmp_path), "val", "k")
    assert got.dtype == np.float64 and rejected == {"singular": 1}
    np.testing.assert_array_equal(got, h.astype(np.float32).astype(np.float64))
    with open(path, "r+b") as f:  # a torn file reads as none saved
        f.truncate(40)
    assert stage_estimates.load_estimates(str(tmp_path), "val", "k") is None


def _scalars(folder):
    """{tag: {step: value}} of the TensorBoard event files in ``folder``."""
    out = {}
    for path in sorted(folder.glob("events.out.tfevents.*")):
        for event in tf.compat.v1.train.summary_iterator(str(path)):
            for v in event.summary.value:
                out.setdefault(v.tag, {})[event.step] = float(tf.make_ndarray(v.tensor))
    return out


@pytest.mark.parametrize("log_every, checkpoint_every, train_steps, logged", [
    pytest.param(1, 2, 6, [1, 2, 3, 4, 5, 6], marks=pytest.mark.slow),  # (make test's time)
    pytest.param(50, 3, 6, [1, 2, 3, 4, 5, 6],  # a run shorter than log_every: >= ten reports
                 marks=pytest.mark.slow),
    pytest.param(4, 3, 12, [2, 4, 6, 8, 10, 12],  # checkpoint_every not a multiple of log_every
                 marks=pytest.mark.slow),
])
def test_tensorboard_scalars_are_against_the_global_step(tiny_data, tmp_path, narrow, log_every,
                                                          checkpoint_every, train_steps, logged):
    """The loss terms and the learning rate at every reported step, the validation MACE at every
    checkpoint, read back from the event files; the learning rate equals the schedule's (Keras'
    CosineDecay) that step's update was made with (at the step before: update s - 1, 0-based)."""
    cfg = _cfg(tiny_data, tmp_path / "run", log_every=log_every,
               checkpoint_every=checkpoint_every, train_steps=train_steps, val_samples=4,
               val_split="test")  # (tiny_data has no val split: the default would not validate)
    lines = []
    training.train(cfg, printer=lines.append)
    train = _scalars(tmp_path / "run" / "logs" / "train")
    for tag in ("loss", "h_bar_loss", "patch_a_warp_loss", "learning_rate"):
        assert sorted(train[tag]) == logged, (tag, train[tag])
    schedule = training.learning_rate_schedule(cfg)
    for step, lr in train["learning_rate"].items():
        assert lr == pytest.approx(float(schedule(step - 1)), rel=1e-5)
    validation = _scalars(tmp_path / "run" / "logs" / "validation")
    assert sorted(validation["h_bar_mace"]) == list(range(checkpoint_every, train_steps + 1,
                                                          checkpoint_every))
    reported = [int(m.group(1)) for m in map(re.compile(r"step (\d+)/").match, lines) if m]
    assert reported == logged


@pytest.mark.slow  # (8 s; make test-all)
def test_fit_timing_counts_the_steps_of_each_call(monkeypatch, narrow):
    """``benchmark_stream``'s timing: with k steps per compiled call, each callback gap is k
    steps (a fake clock that ticks 1 s per reading gives exactly k steps/s)."""
    from stnh_tf.data import batches, bundled_photos, pair_datasets
    from stnh_tf.evaluation import benchmarks

    images = bundled_photos.bundled_image_files()[:2]
    pb = batches.PairBatches(images, 4, samples_per_image=4, seed=0)
    arrays = batches.materialize(pb, 0)
    ticks = iter(range(10**6))
    monkeypatch.setattr(benchmarks.time, "perf_counter", lambda: float(next(ticks)))
    rates = {}
    for suffix, k, callbacks in benchmarks.fit_variants((1, 2), ("none", "training")):
        rates[suffix] = benchmarks.time_fit(
            "array", pb, ["bundled"], batch_size=4, steps_per_epoch=4, epochs=2,
            mixed_precision=False, steps_per_execution=k, training_callbacks=callbacks,
            stream=pair_datasets.ArrayStream(arrays, pb))["steps_per_s"]
    assert rates == {"": 1.0, "/spe1+callbacks": 1.0, "/spe2": 2.0, "/spe2+callbacks": 2.0}
    with pytest.raises(ValueError, match="must divide steps_per_epoch"):
        benchmarks.time_fit("array", pb, ["bundled"], batch_size=4, steps_per_epoch=3,
                            steps_per_execution=2, stream=pair_datasets.ArrayStream(arrays, pb))


@pytest.mark.slow  # (three short training runs)
def test_a_run_resumes_with_its_init_from_file_gone(tiny_data, tmp_path, narrow):
    """A run started with ``init_from`` was refused on every resume once that file was gone (a
    temporary copy, another machine), although a resume never reads it: the only way on was
    ``--overwrite``, from step 0. It resumes now, and its config.json keeps the file's recorded
    digest; another file at that path is still another configuration."""
    training.train(_cfg(tiny_data, tmp_path / "src", train_steps=2), printer=_quiet)
    init = tmp_path / "init.keras"
    shutil.copy(tmp_path / "src" / "model.keras", init)
    cfg = _cfg(tiny_data, tmp_path / "run", init_from=(str(init),))
    assert training.train(cfg, printer=_quiet, time_limit_s=0.001)["final_step"] < 6
    recorded = json.loads((tmp_path / "run" / "config.json").read_text())["model_sha256"]
    os.remove(init)
    assert training.train(cfg, printer=_quiet)["final_step"] == 6
    assert json.loads((tmp_path / "run" / "config.json").read_text())[
        "model_sha256"] == recorded


@pytest.mark.slow  # (a short training run)
def test_a_finished_model_whose_record_was_lost_is_finished_by_the_same_command(
        tiny_data, tmp_path, narrow, monkeypatch):
    """``model.keras`` is written, then ``result.json``: a full disk (or a kill) between left a
    folder every later call refused as finished, and ``--overwrite`` trained it again from step
    0. With its checkpoint at the last step the same command now writes the record (and the
    model again, from that checkpoint: the same weights), training nothing."""
    cfg = _cfg(tiny_data, tmp_path / "run")
    real = training.atomic_write_json

    def full_disk(path, *args, **kwargs):
        if os.path.basename(path) == "result.json":
            raise OSError(28, "No space left on device", path)
        return real(path, *args, **kwargs)

    monkeypatch.setattr(training, "atomic_write_json", full_disk)
    with pytest.raises(OSError, match="No space"):
        training.train(cfg, printer=_quiet)
    monkeypatch.setattr(training, "atomic_write_json", real)
    before = _weights(tmp_path / "run")
    assert not (tmp_path / "run" / "result.json").exists()
    result = training.train(cfg, printer=_quiet)
    assert result["final_step"] == 6 and (tmp_path / "run" / "result.json").is_file()
    for a, b in zip(before, _weights(tmp_path / "run")):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(FileExistsError, match="finished model"):  # finished now: refused
        training.train(cfg, printer=_quiet)


@pytest.mark.slow  # (two short training runs)
def test_a_failed_overwrite_says_where_the_run_it_replaced_is(tiny_data, tmp_path, narrow):
    """``--overwrite`` keeps the replaced run in ``.previous_run`` until the new one finishes;
    a new run that failed after its first checkpoint (diverged: "train anew with a new
    --model_dir, or --overwrite") left a folder that looked like an unfinished run with no
    model. Every error after the first checkpoint now says where the replaced run is."""
    training.train(_cfg(tiny_data, tmp_path / "run"), printer=_quiet)

    class Fails(keras.callbacks.Callback):  # an error after the first checkpoint (step 2)
        def on_train_batch_end(self, batch, logs=None):
            if int(self.model.optimizer.iterations.numpy()) >= 3:
                raise RuntimeError("failed at step 3")

    lines = []
    cfg = _cfg(tiny_data, tmp_path / "run", train_steps=8)
    with pytest.raises(RuntimeError, match="failed at step 3"):
        training.train(cfg, overwrite=True, printer=lines.append, extra_callbacks=[Fails()])
    assert (tmp_path / "run" / "checkpoint" / "state.json").is_file()
    aside = tmp_path / "run" / run_dir.PREVIOUS_RUN
    assert (aside / "model.keras").is_file()
    assert any(str(aside) in line and "to have it back" in line for line in lines), lines


@pytest.mark.slow  # (a short training run)
def test_the_logged_learning_rate_is_the_one_its_step_was_made_with(tiny_data, tmp_path,
                                                                     narrow):
    """The progress line (and TensorBoard's ``learning_rate``) of step s gave the schedule at
    s, the rate of the next update: DeTone et al.'s step schedule showed its drops one step
    early (a reviewer's run: "step 2: lr=0.001" for an update made at 0.01). Step s's update is
    made at the schedule's value at s - 1 (Keras evaluates it at ``iterations`` before the
    update)."""
    cfg = _cfg(tiny_data, tmp_path / "run", lr_schedule="step", warmup_steps=0)
    lines = []
    training.train(cfg, printer=lines.append)
    schedule = training.learning_rate_schedule(cfg)
    logged = {int(m.group(1)): float(m.group(2)) for m in (
        re.match(r"step (\d+)/6 lr=(\S+)", line) for line in lines) if m}
    assert sorted(logged) == [1, 2, 3, 4, 5, 6]
    made_with = {s: float(keras.ops.convert_to_numpy(schedule(s - 1))) for s in logged}
    assert len(set(made_with.values())) == 3  # (the two drops fall inside the run)
    for s, lr in logged.items():
        assert lr == pytest.approx(made_with[s], rel=1e-4), (s, lr, made_with)


def test_a_checkpoint_save_cut_short_leaves_no_temporary_file(tmp_path):
    """A checkpoint whose weights file could not be written whole (a full disk) left its
    ``tmp-<pid>.weights.h5``, which the clean-up of older files skips: every later failure on
    that disk left another. It is removed, the error goes on, the committed checkpoint stays."""
    model = keras.Sequential([keras.Input((2,)), keras.layers.Dense(1)])
    model.compile(optimizer="sgd", loss="mse")
    model.optimizer.build(model.trainable_variables)
    saver = checkpoints.AtomicCheckpoint(str(tmp_path))
    saver.set_model(model)
    saver.on_epoch_end(0)
    before = sorted(os.listdir(tmp_path))
    real = model.save_weights

    def full_disk(path, *args, **kwargs):
        real(path, *args, **kwargs)
        with open(path, "r+b") as f:  # half of it written, then the disk is full
            f.truncate(os.path.getsize(path) // 2)
        raise OSError(28, "No space left on device")

    model.save_weights = full_disk
    with pytest.raises(OSError, match="No space"):
        saver.on_epoch_end(1)
    assert sorted(os.listdir(tmp_path)) == before
