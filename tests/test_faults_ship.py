"""A hostile review of ``experiments.ship_weights`` (issue 79's fourth round): each test fails
on the code before it.

Data loss: ``ship`` replaced the shipped files one by one, so a wrong second ``--model_dir``, a
mistyped ``--eval_json`` or a failed check left new weights under the old card; a save cut short
truncated a shipped ``.keras`` (Keras opens the target for writing first); a model worse on the
bundled check replaced a better one without a word; without ``--weights_dir`` the package's folder
was not checked apart from ``--model_dir`` (swapping two shipped stages lost one). Silently
wrong: ``replace_stage`` without ``--eval_json`` kept the old stage's evaluation as the card's.
Crashes: ordinary errors of the binary ended in tracebacks.

The bundled check itself (minutes) is replaced by a stand-in here: these tests are about which
files end where; ``tests/test_ship_weights.py`` tests the check."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import narrow_network, to_bar
from stnh_tf.inference import shipped_weights

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _constant_model(path, h_pix):
    from stnh_tf.modeling import models

    with narrow_network():
        model = models.build_stn_homography()
    fc2 = model.get_layer("regression").get_layer("fc2")
    kernel, _ = fc2.get_weights()
    fc2.set_weights([np.zeros_like(kernel), to_bar(h_pix).ravel()[:8].astype("float32")])
    model.save(path)
    return path


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("runs")
    shift = np.array([[1.0, 0, 3.0], [0, 1.0, -2.0], [0, 0, 1.0]])
    return {"a": _constant_model(str(d / "a.keras"), np.eye(3)),
            "b": _constant_model(str(d / "b.keras"), shift)}


@pytest.fixture()
def check(monkeypatch):
    """The bundled check's stand-in: the MACE ``scores`` gives each stage file's bytes."""
    scores = {}

    def stand_in(paths):
        digest = hashlib.sha256(b"".join(open(p, "rb").read() for p in paths)).hexdigest()
        return {"estimate_mace_1_stages": scores.get("next", 1.0), "files": digest}

    monkeypatch.setattr(shipped_weights, "bundled_check", stand_in)
    return scores


def _state(folder):
    return {n: hashlib.sha256(open(os.path.join(folder, n), "rb").read()).hexdigest()
            for n in sorted(os.listdir(folder))}


@pytest.fixture()
def shipped(tmp_path, runs, check):
    w = tmp_path / "weights"
    check["next"] = 2.0
    shipped_weights.ship([runs["a"], runs["a"]], str(w),
                         eval_json=_eval(tmp_path, 0.79))
    return str(w), _state(w)


def _eval(tmp_path, mace):
    path = tmp_path / f"eval_{mace}.json"
    path.write_text(json.dumps({"model": {"mace": mace}}))
    return str(path)


def test_a_failed_ship_replaces_nothing(shipped, runs, tmp_path):
    w, before = shipped
    with pytest.raises(FileNotFoundError):
        shipped_weights.ship([runs["b"], str(tmp_path / "typo")], w)
    assert _state(w) == before
    with pytest.raises(FileNotFoundError):
        shipped_weights.ship([runs["b"], runs["b"]], w, eval_json=str(tmp_path / "typo.json"))
    assert _state(w) == before


def test_a_save_cut_short_leaves_the_shipped_file(shipped, runs, monkeypatch):
    import keras

    w, before = shipped

    def full_disk(self, path, *a, **k):
        with open(path, "wb") as f:
            f.write(b"PK\x03\x04 cut")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(keras.Model, "save", full_disk)
    with pytest.raises(OSError, match="No space left"):
        shipped_weights.replace_stage(2, runs["b"], w)
    assert _state(w) == before  # (was: stage2.keras of 11 bytes)


def _card_write_fails(monkeypatch):
    """The card's write fails (a full disk) from now on; returns the real writer."""
    real = shipped_weights.atomic_write_json

    def failing(path, doc):
        if path.endswith("model_card.json"):
            raise OSError(28, "No space left on device")
        return real(path, doc)

    monkeypatch.setattr(shipped_weights, "atomic_write_json", failing)
    return real


def test_a_failed_card_write_puts_the_old_files_back(shipped, runs, monkeypatch):
    w, before = shipped
    _card_write_fails(monkeypatch)
    with pytest.raises(OSError):
        shipped_weights.ship([runs["b"]], w)
    assert _state(w) == before


def test_worse_weights_are_refused_unless_allowed(shipped, runs, check):
    w, before = shipped
    check["next"] = 3.1  # the card says 2.0
    with pytest.raises(ValueError, match=r"worse than the card .* 2.000 -> 3.100 px.*allow_worse"):
        shipped_weights.replace_stage(1, runs["b"], w)
    assert _state(w) == before
    check["next"] = 2.04  # within the tolerance: the same model on another CPU
    card = shipped_weights.replace_stage(1, runs["b"], w)
    assert card["bundled_check_change"] == {"estimate_mace_1_stages": [2.0, 2.04]}
    check["next"] = 3.1
    card = shipped_weights.replace_stage(1, runs["a"], w, allow_worse=True)
    assert card["bundled_check_change"] == {"estimate_mace_1_stages": [2.04, 3.1]}
    assert json.load(open(os.path.join(w, "model_card.json"))) == card
    assert not [n for n in os.listdir(w) if n.startswith(".")]  # no staging folder left


def test_a_replaced_stage_marks_the_old_evaluation_stale(shipped, runs, tmp_path):
    w, _ = shipped
    card = shipped_weights.replace_stage(2, runs["b"], w)
    assert card["evaluation"] == {"model": {"mace": 0.79}}  # kept, but said to be stale
    assert "stage 2 (stage2.keras) was replaced" in card["evaluation_stale"]
    card = shipped_weights.replace_stage(2, runs["b"], w, eval_json=_eval(tmp_path, 0.5))
    assert card["evaluation"] == {"model": {"mace": 0.5}} and "evaluation_stale" not in card


def _binary(*args, default_dir=None):
    """experiments.ship_weights in a subprocess; ``default_dir`` stands in for the package's
    weights folder (so that no test can write into the checkout's)."""
    code = ("import sys; from absl import app; from stnh_tf.inference import model_files\n"
            f"model_files.default_weights_dir = lambda: {default_dir!r}\n"
            "import experiments.ship_weights as m; sys.argv = ['ship_weights', *sys.argv[1:]]\n"
            "app.run(m.main)")
    return subprocess.run([sys.executable, "-c", code, *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)


@pytest.mark.slow  # (four subprocesses: the make test time)
def test_the_binary_checks_the_default_folder_and_says_errors_in_one_line(shipped, tmp_path):
    w, before = shipped
    proc = _binary(f"--model_dir={w}/stage2.keras,{w}/stage1.keras", default_dir=w)
    assert proc.returncode != 0 and "holds --model_dir" in proc.stderr, proc.stderr[-2000:]
    assert _state(w) == before
    for args, message in (
            (["--replace_stage=5", f"--model_dir={w}/stage1.keras",
              f"--weights_dir={tmp_path / 'other'}"], "model_card.json"),
            ([f"--model_dir={tmp_path / 'no_such_run'}", f"--weights_dir={tmp_path / 'x'}"],
             "no trained model at"),
            (["--refresh_check", f"--weights_dir={tmp_path / 'empty'}"], "model_card.json")):
        proc = _binary(*args, default_dir=w)
        assert proc.returncode != 0 and message in proc.stderr, (args, proc.stderr[-2000:])
        assert "Traceback" not in proc.stderr, args
    assert _state(w) == before


_KILLED_IN_THE_SWAP = """
import os, signal, sys
from stnh_tf.inference import shipped_weights
shipped_weights.bundled_check = lambda paths: {"estimate_mace_1_stages": 1.0}
real = shipped_weights.atomic_write_json
def killed(path, doc):  # the new models and manifest are in place, the card not yet
    if path.endswith("model_card.json"):
        os.kill(os.getpid(), signal.SIGKILL)
    return real(path, doc)
shipped_weights.atomic_write_json = killed
shipped_weights.ship([sys.argv[1]] * 3, sys.argv[2])  # (three stages over two)
"""


@pytest.mark.slow  # (a subprocess loading TensorFlow: the make test time)
def test_a_ship_killed_in_its_swap_is_put_back_by_the_next(shipped, runs, check):
    """A ship killed (SIGKILL) between placing the new models and writing the card left new
    weights under the old card, and the next ship deleted its staging folder with the old files
    set aside in it. The next ship (or ``replace_stage``) puts them back first, and removes a
    stage file that had no old version (three stages shipped over two)."""
    w, before = shipped
    proc = subprocess.run([sys.executable, "-c", _KILLED_IN_THE_SWAP, runs["b"], w],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == -9, proc.stderr[-2000:]
    # new stage files under the old card, and the staging folder with the old ones
    assert [n for n in os.listdir(w) if n.startswith(shipped_weights.STAGING_PREFIX)]
    stage1 = hashlib.sha256(open(os.path.join(w, "stage1.keras"), "rb").read()).hexdigest()
    assert stage1 != before["stage1.keras"]
    assert os.path.exists(os.path.join(w, "stage3.keras"))
    assert sorted(shipped_weights.put_back(w)) == ["default.json", "model_card.json",
                                                   "stage1.keras", "stage2.keras", "stage3.keras"]
    assert _state(w) == before


def test_put_back_moves_only_what_the_plan_names(shipped, monkeypatch):
    """A ship killed while copying the old card into its staging folder left a half-written
    temporary file there, which put_back moved into the weights folder; one killed after its
    swap (no ``.previous`` left) must not be undone. Neither touches the weights now."""
    w, before = shipped
    early = os.path.join(w, f"{shipped_weights.STAGING_PREFIX}1", shipped_weights.PREVIOUS)
    os.makedirs(early)
    open(os.path.join(early, "model_card.json.tmp-1"), "w").write("{half")
    done = os.path.join(w, f"{shipped_weights.STAGING_PREFIX}2")
    os.makedirs(os.path.join(done, ".shipped"))
    with open(os.path.join(done, shipped_weights.PLAN), "w") as f:
        json.dump({"swap": ["stage1.keras"], "new": ["stage1.keras"], "kept": []}, f)
    assert shipped_weights.put_back(w) == []
    assert _state(w) == before


def test_a_failed_put_back_keeps_the_old_files_for_the_next_ship(shipped, runs, monkeypatch):
    """Where putting the old files back fails too (after a failed card write), the staging folder
    was removed with them; it is kept now, the error names it, and a later ship from another
    process puts them back."""
    w, before = shipped
    real_json, real_bytes = shipped_weights.atomic_write_json, shipped_weights.atomic_write_bytes

    def failing_json(path, doc):
        if path.endswith("model_card.json"):
            raise OSError(28, "No space left on device")
        return real_json(path, doc)

    def failing_bytes(path, data):
        if os.path.dirname(path) == w:  # the card's old bytes back: fails too
            raise OSError(5, "Input/output error")
        return real_bytes(path, data)

    monkeypatch.setattr(shipped_weights, "atomic_write_json", failing_json)
    monkeypatch.setattr(shipped_weights, "atomic_write_bytes", failing_bytes)
    with pytest.raises(RuntimeError, match="so did putting the old files back"):
        shipped_weights.ship([runs["b"], runs["b"]], w)
    assert "model_card.json" in shipped_weights.put_back(w)
    assert _state(w) == before


def test_two_ships_at_once_the_second_is_refused(shipped, runs, check, monkeypatch):
    """Two ``ship_weights`` into one folder at once each read the old card and swapped files in
    turn: the second's card could describe files the first had placed (or put them back as its
    own old ones). The folder is locked now: while one ship holds it, another ship,
    ``--replace_stage``, ``--refresh_check`` and ``--refresh_evaluation`` are refused, nothing
    replaced, and the first finishes whole."""
    import threading

    from stnh_tf.evaluation import card_evaluation

    w, before = shipped
    entered, release = threading.Event(), threading.Event()
    stand_in = shipped_weights.bundled_check

    def slow_check(paths):  # the first ship, paused inside its check
        entered.set()
        assert release.wait(60)
        return stand_in(paths)

    monkeypatch.setattr(shipped_weights, "bundled_check", slow_check)
    first = {}
    thread = threading.Thread(target=lambda: first.update(
        card=shipped_weights.ship([runs["b"], runs["b"]], w)))
    thread.start()
    try:
        assert entered.wait(60)
        for second in (lambda: shipped_weights.ship([runs["a"]] * 3, w),
                       lambda: shipped_weights.replace_stage(1, runs["a"], w),
                       lambda: shipped_weights.refresh_check(w),
                       lambda: card_evaluation.refresh_card(w, "unused")):
            with pytest.raises(FileExistsError, match="another ship_weights is writing"):
                second()
    finally:
        release.set()
        thread.join(60)
    card = json.load(open(os.path.join(w, "model_card.json")))
    assert card == first["card"]
    assert [s["source"] for s in card["stages"]] == [os.path.abspath(runs["b"])] * 2
    assert sorted(_state(w)) == sorted(before)  # two stages, no staging folder left
    assert _state(w)["stage1.keras"] != before["stage1.keras"]


def _killed_after_its_card(w, before_dir, new_card: bytes):
    """The staging folder a ship killed just after writing its card leaves (``new_card``: the
    card it was writing), the old files of ``before_dir`` set aside in it."""
    import shutil

    staging = os.path.join(w, f"{shipped_weights.STAGING_PREFIX}1")
    aside = os.path.join(staging, shipped_weights.PREVIOUS)
    os.makedirs(aside)
    for name in ("stage1.keras", "stage2.keras", "default.json", "model_card.json"):
        shutil.copy(os.path.join(before_dir, name), os.path.join(aside, name))
    with open(os.path.join(staging, shipped_weights.PLAN), "w") as f:
        json.dump({"swap": ["stage1.keras", "stage2.keras"], "new": [],
                   "kept": ["default.json", "model_card.json"]}, f)
    with open(os.path.join(staging, shipped_weights.NEW_CARD), "wb") as f:
        f.write(new_card)


def test_a_ship_killed_after_writing_its_card_is_kept(shipped, runs, tmp_path, monkeypatch):
    """A ship killed after its card was written (the swap done, its staging folder not yet
    marked) was undone by the next ship: the new weights silently went back to the old. It is
    kept now; killed before the card was written it is still put back (the control)."""
    import shutil

    w, before = shipped
    before_dir = str(tmp_path / "before")
    shutil.copytree(w, before_dir)
    shipped_weights.ship([runs["b"], runs["b"]], w)
    after = _state(w)
    assert after != before
    card = open(os.path.join(w, "model_card.json"), "rb").read()
    _killed_after_its_card(w, before_dir, card)
    assert shipped_weights.put_back(w) == []
    assert _state(w) == after
    _killed_after_its_card(w, before_dir, card.replace(b"stage", b"other"))  # not yet written
    assert sorted(shipped_weights.put_back(w)) == ["default.json", "model_card.json",
                                                   "stage1.keras", "stage2.keras"]
    assert _state(w) == before
    # killed while undoing a failed swap, its card in place but a new model moved back into the
    # staging folder already: not done, put back
    shipped_weights.ship([runs["b"], runs["b"]], w)
    card = open(os.path.join(w, "model_card.json"), "rb").read()
    _killed_after_its_card(w, before_dir, card)
    staging = os.path.join(w, f"{shipped_weights.STAGING_PREFIX}1")
    os.replace(os.path.join(w, "stage1.keras"), os.path.join(staging, "stage1.keras"))
    assert "stage1.keras" in shipped_weights.put_back(w)
    assert _state(w) == before


def test_the_card_a_ship_writes_marks_its_swap_done(shipped, runs, monkeypatch):
    """The ship's own record of the card it writes: a ship stopped right after writing its card
    (the rename that marks the swap done, and the staging folder's removal, not reached) is kept
    by the next put_back, its files as the ship left them."""
    import shutil

    w, before = shipped
    real_replace = os.replace
    with monkeypatch.context() as m:  # (the process ends here, as if killed)
        m.setattr(os, "replace", lambda src, dst: None if str(dst).endswith(".shipped")
                  else real_replace(src, dst))
        m.setattr(shutil, "rmtree", lambda *args, **kwargs: None)
        shipped_weights.ship([runs["b"], runs["b"]], w)
    staging = [n for n in os.listdir(w) if n.startswith(shipped_weights.STAGING_PREFIX)]
    assert len(staging) == 1
    after = _state_files(w)
    assert after != before
    assert shipped_weights.put_back(w) == []
    assert _state(w) == after


def _state_files(folder):
    return {n: hashlib.sha256(open(os.path.join(folder, n), "rb").read()).hexdigest()
            for n in sorted(os.listdir(folder)) if os.path.isfile(os.path.join(folder, n))}


def test_a_killed_ships_folder_is_put_back_whatever_process_has_its_id_now(shipped, runs,
                                                                           tmp_path):
    """A ship killed in its swap left its staging folder named by its process id, and the next
    writer put it back only where no process had that id: with the id reused (across container
    runs; pid 1 here, always running) a later ship went on over the half-swapped folder, the
    folder stayed, and a writer after the id was free reverted the later ship to the weights
    before both. Every writer holds the folder's lock, so a staging folder found under it is a
    dead writer's: the next ship puts it back first, then ships whole."""
    import shutil

    w, before = shipped
    before_dir = str(tmp_path / "before")
    shutil.copytree(w, before_dir)
    shipped_weights.ship([runs["b"], runs["b"]], w)
    card = open(os.path.join(w, "model_card.json"), "rb").read()
    _killed_after_its_card(w, before_dir, card.replace(b"stage", b"other"))  # (pid 1's name)
    card = shipped_weights.ship([runs["b"]] * 3, w)
    assert not [n for n in os.listdir(w) if n.startswith(shipped_weights.STAGING_PREFIX)]
    assert [s["source"] for s in card["stages"]] == [os.path.abspath(runs["b"])] * 3
    after = _state(w)
    shipped_weights.refresh_check(w)  # a later writer finds nothing to put back
    assert {n: h for n, h in _state(w).items() if n.endswith(".keras")} == {
        n: h for n, h in after.items() if n.endswith(".keras")}


def test_fewer_stages_shipped_over_more_leave_no_later_stage_file(shipped, runs, monkeypatch):
    """Two stages shipped over three left the old ``stage3.keras`` beside the new manifest, and
    ``HomographyEstimator.load(folder)`` (README's way to load a weights folder) ran it as a
    third stage under a two-stage card. It goes with the old files now, and comes back where
    the ship fails."""
    from stnh_tf.inference.estimator import HomographyEstimator

    w, _ = shipped
    shipped_weights.ship([runs["a"]] * 3, w)
    three = _state(w)
    real = _card_write_fails(monkeypatch)
    with pytest.raises(OSError, match="No space"):
        shipped_weights.ship([runs["b"], runs["b"]], w)
    assert _state(w) == three  # stage3.keras back with the rest
    monkeypatch.setattr(shipped_weights, "atomic_write_json", real)
    shipped_weights.ship([runs["b"], runs["b"]], w)
    assert sorted(n for n in os.listdir(w) if n.endswith(".keras")) == ["stage1.keras",
                                                                       "stage2.keras"]
    assert HomographyEstimator.load(w).num_stages == 2


def test_a_weights_folder_loads_the_hierarchy_its_manifest_names(shipped):
    """A weights folder holding ``default.json`` and, beside it, a stage file the manifest does
    not name (a copy, a leftover): ``load(folder)`` took every numbered stage file; it loads
    the manifest's hierarchy, as ``load()`` does the package's."""
    import shutil

    from stnh_tf.inference import model_files

    w, _ = shipped
    shutil.copy(os.path.join(w, "stage1.keras"), os.path.join(w, "stage3.keras"))
    assert model_files.resolve_model_paths(w) == model_files.read_manifest(
        os.path.join(w, "default.json"))
    assert len(model_files.resolve_model_paths(w)) == 2
