"""A hostile round on the paper schedule's chunks (issue 77 item 2, continued): what a chunk
writes is never lost and a chunk never starts from the wrong state, whatever stops it. Each test
failed on the code before its fix. Training is :func:`test_faults._fake_train` (a checkpoint 2
steps on from the one there, as ``loop.train`` leaves one); references are the files' bytes and
the ledger's JSON."""

from __future__ import annotations

import errno
import json
import os

import pytest

from stnh_tf.training import checkpoints, chunks, file_parts
from stnh_tf.training import ledger as ledger_lib
from stnh_tf.training import loop as training
from test_faults import QUIET, _config_json, _fake_checkpoint, _fake_train, _files, _train_cfg


def _row(from_step, to_step, part="sequence2", **extra):
    return {"stage": 1, "part": part, "from_step": from_step, "to_step": to_step,
            "done": False, "device": "cpu", "backend": "tensorflow", "steps_per_s": 0.3,
            "wall_s": 100.0 * (to_step - from_step), "date": "2026-12-06", **extra}


def _committed(root, cfg, step, part="sequence2"):
    """``root/resume/<part>`` holding a checkpoint of ``step`` of ``cfg``'s run, as sync_out
    leaves it."""
    resume = root / "resume" / part
    _fake_checkpoint(resume, step)
    (resume / "config.json").write_text(_config_json(cfg))
    return resume


def _commit_over(tmp_path, committed, own):
    """``(run, resume, cfg)``: a run folder at step ``own`` and stage 1's committed checkpoint
    at step ``committed``, of one run."""
    run, resume = tmp_path / "run", tmp_path / "repo" / "resume" / "stage1"
    cfg = _train_cfg("d", run, train_steps=100)
    _committed(tmp_path / "repo", cfg, committed, part="stage1")
    _fake_checkpoint(run / "checkpoint", own)
    (run / "config.json").write_text(_config_json(cfg))
    return run, resume, cfg


def test_a_chunk_does_not_start_below_the_step_the_ledger_recorded(tmp_path, monkeypatch):
    """The ledger's last row of a part ends at step 4, but its committed checkpoint is gone (a
    deletion committed, a checkout gone wrong) and the run folder is fresh: the chunk trained
    from step 0, committed that, and its row forked the ledger. Refused in one line naming both
    steps and the way back, before anything is trained or written; with ``step_back`` it trains
    on from step 0 (the rows past it then superseded: :func:`ledger.chain`). A run folder ahead
    of the ledger (a chunk that ended without its row) goes on from it, said in one line."""
    root, calls = tmp_path / "repo", []
    root.mkdir()
    (root / "ledger.json").write_text(json.dumps([_row(0, 2), _row(2, 4)]))
    monkeypatch.setattr(training, "train", _fake_train(calls))
    cfg = _train_cfg("d", tmp_path / "run", train_steps=100)
    before = _files(root)
    with pytest.raises(ValueError) as refused:
        chunks.run_chunk(cfg, str(root), 0, "here", printer=QUIET, part="sequence2")
    message = str(refused.value)
    assert "ends at step 4" in message and "of step 0" in message and "\n" not in message
    assert "--step_back" in message and str(root / "resume" / "sequence2") in message
    assert calls == [] and _files(root) == before
    row = chunks.run_chunk(cfg, str(root), 0, "here", printer=QUIET, part="sequence2",
                           step_back=True)
    assert (row["from_step"], row["to_step"]) == (0, 2)
    rows = ledger_lib.read_ledger(str(root))
    assert [(r["from_step"], r["to_step"]) for r in ledger_lib.chain(rows, "sequence2")] == [
        (0, 2)]
    # a run folder ahead of the ledger: its checkpoint of step 8, the ledger's last row at 2
    _fake_checkpoint(tmp_path / "run" / "checkpoint", 8)
    lines = []
    row = chunks.run_chunk(cfg, str(root), 0, "here", printer=lines.append, part="sequence2")
    assert (row["from_step"], row["to_step"]) == (8, 10)
    assert any("of step 8 is past the ledger's last row (2" in line for line in lines), lines


def test_committed_weights_in_parts_without_their_state_are_refused(tmp_path):
    """A committed checkpoint kept in parts whose state.json is lost was taken for no
    checkpoint (its step read from whole files' names only): the chunk trained from step 0.
    Refused in one line naming the folder, the run folder kept byte for byte."""
    import h5py
    import numpy as np

    run, resume = tmp_path / "run", tmp_path / "repo" / "resume" / "sequence2"
    cfg = _train_cfg("d", run, train_steps=100)
    (run / "checkpoint").mkdir(parents=True)
    (run / "config.json").write_text(_config_json(cfg))
    name = "ckpt-00000006.weights.h5"
    with h5py.File(run / "checkpoint" / name, "w") as f:  # 1.2 MB, in parts of 0.5 MB
        f["layers/dense/vars/0"] = np.random.default_rng(0).random((300_000,), np.float32)
        f["optimizer/vars/0"] = np.int64(6)
    (run / "checkpoint" / "state.json").write_text(json.dumps({"step": 6, "weights": name}))
    resume.mkdir(parents=True)
    file_parts.write_parts(str(run / "checkpoint" / name), str(resume / name), 500_000)
    (resume / "config.json").write_text(_config_json(cfg))
    fresh = tmp_path / "fresh"
    with pytest.raises(ValueError) as refused:
        chunks.sync_in(str(resume), str(fresh), cfg)  # before: None, and training from 0
    message = str(refused.value)
    assert str(resume) in message and "state.json" in message and "\n" not in message
    assert not fresh.exists()
    # parts without their manifest either: a first commit cut short (the manifest and
    # state.json come last), nothing committed, not a checkpoint; the next commit replaces them
    (resume / f"{name}.parts.json").unlink()
    assert chunks.sync_in(str(resume), str(fresh), cfg) is None
    assert chunks.sync_out(str(run), str(resume)) == 6
    assert chunks.sync_in(str(resume), str(tmp_path / "fresh2"), cfg) == 6


def test_a_committed_checkpoint_without_its_config_is_refused(tmp_path):
    """A committed checkpoint without its config.json was taken as of this run, unchecked: into
    a run folder with a checkpoint, copied over it; into a fresh one, the copy failed half-way.
    Refused in one line naming the folder and the file, nothing copied."""
    run, resume = tmp_path / "run", tmp_path / "repo" / "resume" / "stage1"
    cfg = _train_cfg("d", run, train_steps=100)
    _fake_checkpoint(run / "checkpoint", 2)
    (run / "config.json").write_text(_config_json(cfg))
    _fake_checkpoint(resume, 4)
    for folder in (run, tmp_path / "fresh"):
        before = _files(folder) if folder.exists() else None
        with pytest.raises(ValueError) as refused:
            chunks.sync_in(str(resume), str(folder), cfg)  # before: 4, copied unchecked
        message = str(refused.value)
        assert str(resume) in message and "config.json" in message and "\n" not in message
        assert (_files(folder) if folder.exists() else None) == before


def test_an_error_in_training_commits_what_the_chunk_trained(tmp_path, monkeypatch):
    """An error inside training (a full disk, a crashed pair worker, memory) after the chunk had
    saved checkpoints lost the chunk: nothing committed, no row, the steps only in the run
    folder outside the repository. The checkpoint it reached is committed and a row with the
    error added; the error still goes on (the chunk failed)."""
    root, calls = tmp_path / "repo", []
    train = _fake_train(calls)
    cfg = _train_cfg("d", tmp_path / "run", train_steps=100)
    _committed(root, cfg, 4)
    (root / "ledger.json").write_text(json.dumps([_row(0, 4)]))

    def failing(cfg, **kw):  # trains 2 steps (their checkpoint saved), then the disk is full
        train(cfg, **kw)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(training, "train", failing)
    with pytest.raises(OSError, match="No space left"):
        chunks.run_chunk(cfg, str(root), 0, "here", printer=QUIET, part="sequence2")
    state = json.loads((root / "resume" / "sequence2" / "state.json").read_text())
    assert state["step"] == 6  # before: 4
    rows = ledger_lib.read_ledger(str(root))
    assert (rows[-1]["from_step"], rows[-1]["to_step"]) == (4, 6)  # before: no row
    assert "No space left" in rows[-1]["error"] and not rows[-1]["done"]
    # the next chunk goes on from there
    monkeypatch.setattr(training, "train", train)
    fresh = _train_cfg("d", tmp_path / "run2", train_steps=100)
    row = chunks.run_chunk(fresh, str(root), 0, "here", printer=QUIET, part="sequence2")
    assert (row["from_step"], row["to_step"]) == (6, 8)


def test_a_commit_cut_short_leaves_the_committed_checkpoint_whole(tmp_path, monkeypatch):
    """sync_out renamed the committed folder away, then the new one into its place: a kill in
    between left no resume/<part> (the new checkpoint in a .tmp- folder nothing reads), and a
    stale .old-<pid> folder broke a later commit. It now updates the folder in place, state.json
    last: cut short at any write, the folder still holds the old step complete (sync_in reads
    it back bit for bit), and the next sync_out completes, leaving no stray file."""
    run, resume, cfg = _commit_over(tmp_path, committed=2, own=4)
    old = _files(resume)
    write_json, replace = checkpoints.atomic_write_json, os.replace

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    def replace_but_weights(src, dst):  # killed as the new weights are renamed into place
        if ".weights.h5" in os.path.basename(dst):
            raise KeyboardInterrupt
        return replace(src, dst)

    for where in ("state", "weights"):
        if where == "state":  # killed as the new state.json is written
            monkeypatch.setattr(checkpoints, "atomic_write_json", interrupted)
        else:
            monkeypatch.setattr(checkpoints.os, "replace", replace_but_weights)
        with pytest.raises(KeyboardInterrupt):
            chunks.sync_out(str(run), str(resume))
        monkeypatch.setattr(checkpoints, "atomic_write_json", write_json)
        monkeypatch.setattr(checkpoints.os, "replace", replace)
        state = json.loads((resume / "state.json").read_text())
        assert state["step"] == 2, where  # before: resume/stage1 gone
        back = tmp_path / f"back_{where}"
        assert chunks.sync_in(str(resume), str(back), cfg) == 2
        assert (back / "checkpoint" / state["weights"]).read_bytes() == old[state["weights"]]
    assert chunks.sync_out(str(run), str(resume)) == 4
    assert sorted(_files(resume)) == ["ckpt-00000004.weights.h5", "config.json", "state.json"]
    assert not list((tmp_path / "repo" / "resume").glob("stage1.*"))


def test_a_commit_never_replaces_a_newer_committed_checkpoint(tmp_path):
    """Another chunk (on a GPU machine, its resume/ copied back) committed step 10 while this
    one trained from 2 to 4: sync_out replaced step 10 by step 4, the ledger's row to 10 left
    without its checkpoint. Refused in one line naming both steps; nothing replaced."""
    run, resume, cfg = _commit_over(tmp_path, committed=10, own=4)
    before = _files(resume)
    with pytest.raises(ValueError) as refused:
        chunks.sync_out(str(run), str(resume))
    message = str(refused.value)
    assert "step 10" in message and " 4 " in message and "\n" not in message, message
    assert _files(resume) == before


def test_a_commit_never_replaces_other_weights_of_the_same_step(tmp_path):
    """Two machines trained the same steps from one commit (2 -> 4 each): the second sync_out
    deleted the committed weights of step 4 before writing its own (a kill in between left
    state.json naming a missing file) and forked the run silently. Refused in one line naming
    the step; nothing replaced. The same weights of the same step commit as before (nothing
    rewritten)."""
    run, resume, cfg = _commit_over(tmp_path, committed=4, own=4)
    weights = run / "checkpoint" / "ckpt-00000004.weights.h5"
    import h5py

    with h5py.File(weights, "r+") as f:  # another machine's step 4
        f["layers/dense/vars/0"][...] = -1.0
    before = _files(resume)
    with pytest.raises(ValueError) as refused:
        chunks.sync_out(str(run), str(resume))
    message = str(refused.value)
    assert "other weights of step 4" in message and "\n" not in message, message
    assert _files(resume) == before
    (resume / "ckpt-00000004.weights.h5").write_bytes(weights.read_bytes())
    assert chunks.sync_out(str(run), str(resume)) == 4
    assert (resume / "ckpt-00000004.weights.h5").read_bytes() == weights.read_bytes()
    assert json.loads((resume / "state.json").read_text())["step"] == 4


def test_the_record_of_a_part_leaves_out_the_chunks_trained_again(tmp_path):
    """A part's record (stage<k>.json / <part>.json, what its model card lists) summed every row
    of the part, also a chunk whose checkpoint was never committed and whose steps were
    trained again (the sequence model's 0 -> 1,399). It lists the rows its model is made of
    (:func:`ledger.chain`: back from the last, each the latest row ending where the later one
    began, a gap where a chunk ended without its row) and the others apart, unsummed."""
    root = tmp_path / "repo"
    root.mkdir()
    rows = [_row(0, 1399), _row(0, 2322), _row(0, 500, part="stage3"), _row(2322, 4763),
            _row(5000, 6000, done=True)]
    (root / "ledger.json").write_text(json.dumps(rows))
    record = chunks.stage_record(str(root), "sequence2", {"samples_per_image": 3})
    assert [(r["from_step"], r["to_step"]) for r in record["chunks"]] == [
        (0, 2322), (2322, 4763), (5000, 6000)]
    assert [(r["from_step"], r["to_step"]) for r in record["superseded_chunks"]] == [(0, 1399)]
    assert record["wall_s"] == 100.0 * (2322 + 2441 + 1000) and record["final_step"] == 6000
    assert json.loads((root / "sequence2.json").read_text()) == record


def test_a_part_stopped_while_finishing_is_finished_by_the_next_call(tmp_path, monkeypatch):
    """A chunk that trained to the end and was stopped before it finished the part (the model
    saved in the run folder, stage<k>.keras not yet written: a kill while writing it) could not
    be finished: the re-run refused the run folder's finished model ("pass --overwrite",
    which paper_schedule does not have, and train_stage's would delete the run). The next call
    finishes it without training: the model kept, its row and record written, resume/ removed."""
    root, calls = tmp_path / "repo", []
    cfg = _train_cfg("d", tmp_path / "run", train_steps=6)
    _committed(root, cfg, 4)
    (root / "ledger.json").write_text(json.dumps([_row(0, 4)]))
    _fake_checkpoint(tmp_path / "run" / "checkpoint", 6)
    (tmp_path / "run" / "config.json").write_text(_config_json(cfg))
    (tmp_path / "run" / "model.keras").write_bytes(b"the finished model")
    monkeypatch.setattr(training, "train", _fake_train(calls))
    monkeypatch.setattr(chunks, "strip_optimizer",
                        lambda src, dst: open(dst, "wb").write(open(src, "rb").read()))
    row = chunks.run_chunk(cfg, str(root), 0, "here", printer=QUIET, part="sequence2")
    assert calls == [] and row["done"] and row["to_step"] == 6
    assert (root / "sequence2.keras").read_bytes() == b"the finished model"
    assert json.loads((root / "sequence2.json").read_text())["final_step"] == 6
    assert not (root / "resume" / "sequence2").exists()


def test_a_sigterm_during_the_commit_acts_once_it_is_written(tmp_path, monkeypatch):
    """A SIGTERM (what `timeout` sends at a GPU command's limit) or Ctrl-C after training ended,
    while the chunk committed its checkpoint and row, cut them short: the signal's default
    handler ended the process with the steps uncommitted. It now waits for the commit: the
    handler in place runs once the row is in the ledger (here a test handler that reads the
    ledger; before, it ran with the row missing)."""
    import signal

    root, calls = tmp_path / "repo", []
    monkeypatch.setattr(training, "train", _fake_train(calls))
    sync_out, seen = chunks.sync_out, []

    def killed_while_committing(model_dir, resume):
        os.kill(os.getpid(), signal.SIGTERM)
        return sync_out(model_dir, resume)

    monkeypatch.setattr(chunks, "sync_out", killed_while_committing)
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: seen.append(
        len(ledger_lib.read_ledger(str(root)))))
    try:
        row = chunks.run_chunk(_train_cfg("d", tmp_path / "run", train_steps=100), str(root), 0,
                               "here", printer=QUIET)
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert seen == [1] and row["to_step"] == 2  # the handler ran once, after the row
    assert json.loads((root / "resume" / "stage1" / "state.json").read_text())["step"] == 2


def test_a_chunk_on_other_photographs_is_refused(tmp_path, monkeypatch):
    """The photograph folders are not part of a run's identity (a checkout or a machine may keep
    them anywhere), so a chunk on a machine whose copy differed (a partial copy, a file added)
    trained on from the same step with another pair stream, silently, and the part's record
    counted only the last machine's photographs. Each chunk's row now records the photographs
    (count and sha256 of their ids and sizes, relative to the folders given: the same at any
    path), and a chunk whose training photographs differ from the part's last row's is refused
    in one line, before training; the same photographs at another path train on."""
    import shutil

    import cv2
    import numpy as np

    photos, val = tmp_path / "photos", tmp_path / "val"
    for folder, n in ((photos, 3), (val, 2)):
        folder.mkdir()
        for i in range(n):
            cv2.imwrite(str(folder / f"{i}.png"), np.full((24, 32), 40 * i, np.uint8))
    root, calls = tmp_path / "repo", []
    monkeypatch.setattr(training, "train", _fake_train(calls))

    def cfg(train=photos, run="run"):
        return _train_cfg("", tmp_path / run, train_steps=100, image_dir=str(train),
                          val_image_dir=str(val))

    first = chunks.run_chunk(cfg(), str(root), 0, "here", printer=QUIET)
    assert first["photographs"]["train"]["count"] == 3
    assert first["photographs"]["val"]["count"] == 2
    cv2.imwrite(str(photos / "3.png"), np.zeros((24, 32), np.uint8))  # a photograph added
    before = _files(root)
    with pytest.raises(ValueError) as refused:
        chunks.run_chunk(cfg(), str(root), 0, "here", printer=QUIET)  # before: trained on
    message = str(refused.value)
    assert str(photos) in message and "\n" not in message and "'count': 4" in message, message
    assert len(calls) == 1 and _files(root) == before
    (photos / "3.png").unlink()
    moved = tmp_path / "elsewhere" / "photos"
    shutil.copytree(photos, moved)
    row = chunks.run_chunk(cfg(moved, "run2"), str(root), 0, "here", printer=QUIET)
    assert (row["from_step"], row["to_step"]) == (2, 4)
    assert row["photographs"] == first["photographs"]


def test_other_validation_photographs_train_on_and_are_said(tmp_path, monkeypatch):
    """Validation only monitors a chunk (its pairs are apart from the training stream), yet a
    chunk whose validation folder differed from the part's last row's (a photograph added) was
    refused like one on other training photographs. It now trains on from the ledger's step,
    says so in one line naming the folder, and its row records the new validation set; other
    training photographs are still refused."""
    import cv2
    import numpy as np

    photos, val = tmp_path / "photos", tmp_path / "val"
    for folder, n in ((photos, 3), (val, 2)):
        folder.mkdir()
        for i in range(n):
            cv2.imwrite(str(folder / f"{i}.png"), np.full((24, 32), 40 * i, np.uint8))
    root, calls, said = tmp_path / "repo", [], []
    monkeypatch.setattr(training, "train", _fake_train(calls))
    cfg = _train_cfg("", tmp_path / "run", train_steps=100, image_dir=str(photos),
                     val_image_dir=str(val))
    first = chunks.run_chunk(cfg, str(root), 0, "here", printer=QUIET)
    cv2.imwrite(str(val / "2.png"), np.zeros((24, 32), np.uint8))  # a validation photograph added
    row = chunks.run_chunk(cfg, str(root), 0, "here", printer=said.append)  # before: refused
    assert (row["from_step"], row["to_step"]) == (2, 4) and len(calls) == 2
    assert row["photographs"]["train"] == first["photographs"]["train"]
    assert (first["photographs"]["val"]["count"], row["photographs"]["val"]["count"]) == (2, 3)
    lines = [line for line in said if "validation photographs" in line]
    assert len(lines) == 1 and str(val) in lines[0] and "\n" not in lines[0], said
    cv2.imwrite(str(photos / "3.png"), np.zeros((24, 32), np.uint8))  # a training one added
    with pytest.raises(ValueError, match="nothing was trained"):
        chunks.run_chunk(cfg, str(root), 0, "here", printer=QUIET)
    assert len(calls) == 2


def test_a_finished_part_moved_away_trains_anew(tmp_path, monkeypatch):
    """The refusal of a finished part says "move it away to train it anew"; done so, the chunk
    was then refused for starting below the ledger's last step (the finished run's), although
    the part is to be trained anew. A part whose last row finished it starts from step 0
    (:func:`ledger.recorded_step` is None), and its new rows make its chain."""
    root, calls = tmp_path / "repo", []
    root.mkdir()
    (root / "ledger.json").write_text(json.dumps([_row(0, 4), _row(4, 8, done=True)]))
    monkeypatch.setattr(training, "train", _fake_train(calls))
    assert ledger_lib.recorded_step(ledger_lib.read_ledger(str(root)), "sequence2") is None
    row = chunks.run_chunk(_train_cfg("d", tmp_path / "run", train_steps=100), str(root), 0,
                           "here", printer=QUIET, part="sequence2")
    assert (row["from_step"], row["to_step"]) == (0, 2)
    rows = ledger_lib.read_ledger(str(root))
    assert [(r["from_step"], r["to_step"]) for r in ledger_lib.chain(rows, "sequence2")] == [
        (0, 2)]


def test_step_back_reaches_the_first_stage_only(monkeypatch):
    """run_stages passed --step_back to every stage it went on to, silencing a later stage's
    refusal too. Only the first stage's chunk gets it."""
    seen = []

    def chunk(stage, root, left, device, printer, commit, step_back=False):
        seen.append((stage, step_back))
        return {"stage": stage, "done": True}

    monkeypatch.setattr(chunks, "run_chunk", chunk)
    chunks.run_stages(lambda k: k, 1, 3, "repo", 0.0, "machine", printer=QUIET,
                      step_back=True)
    assert seen == [(1, True), (2, False), (3, False)]


def test_a_ledger_broken_while_the_chunk_trained_keeps_its_row(tmp_path, monkeypatch):
    """The ledger is checked before a chunk trains, but a merge or an edit can break it while
    the chunk trains (hours): the row was lost, and for a chunk that finished its part so were
    the part's record and the removal of resume/ (the next call refused it as finished). The
    row is kept in ledger.pending.json (the error names it); once the ledger reads again the
    next call adds it, and for a finished part writes the record with it."""
    root, calls = tmp_path / "repo", []
    train = _fake_train(calls)
    good = json.dumps([_row(0, 2)])

    def breaking(cfg, **kw):  # the ledger edited into invalid JSON while this trains
        result = train(cfg, **kw)
        (root / "ledger.json").write_text("<<<<<<< HEAD\n")
        if cfg.train_steps <= result["final_step"]:  # trained to the end
            (tmp_path / "run" / "model.keras").write_bytes(b"the finished model")
        return result

    monkeypatch.setattr(training, "train", breaking)
    monkeypatch.setattr(chunks, "strip_optimizer",
                        lambda src, dst: open(dst, "wb").write(open(src, "rb").read()))
    cfg = _train_cfg("d", tmp_path / "run", train_steps=8)
    _committed(root, cfg, 2)
    (root / "ledger.json").write_text(good)
    with pytest.raises(ValueError) as refused:
        chunks.run_chunk(cfg, str(root), 0, "here", printer=QUIET, part="sequence2")
    assert str(root / "ledger.pending.json") in str(refused.value)
    assert json.loads((root / "resume" / "sequence2" / "state.json").read_text())["step"] == 4
    (root / "ledger.json").write_text(good)  # mended
    monkeypatch.setattr(training, "train", train)
    row = chunks.run_chunk(cfg, str(root), 0, "here", printer=QUIET, part="sequence2")
    rows = ledger_lib.read_ledger(str(root))
    assert [(r["from_step"], r["to_step"]) for r in rows] == [(0, 2), (2, 4), (4, 6)]
    assert row == rows[-1] and not (root / "ledger.pending.json").exists()
    # the chunk that finishes the part, the ledger broken meanwhile
    monkeypatch.setattr(training, "train", breaking)
    with pytest.raises(ValueError, match="ledger.pending.json"):
        chunks.run_chunk(cfg, str(root), 0, "here", printer=QUIET, part="sequence2")
    assert (root / "sequence2.keras").exists() and not (root / "sequence2.json").exists()
    (root / "ledger.json").write_text(json.dumps(rows))  # mended
    with pytest.raises(FileExistsError, match="part sequence2 is finished"):
        chunks.run_chunk(cfg, str(root), 0, "here", printer=QUIET, part="sequence2")
    record = json.loads((root / "sequence2.json").read_text())
    assert record["final_step"] == 8 and record["chunks"][-1]["done"]
    assert not (root / "resume" / "sequence2").exists()


def _last_chunk_of_a_part(tmp_path):
    """``(root, cfg, train)``: part sequence2 committed at step 6 of 8 (its ledger row 0 -> 6)
    and a stand-in for ``loop.train`` that trains it to its end (the run folder's model)."""
    root, calls = tmp_path / "repo", []
    cfg = _train_cfg("d", tmp_path / "run", train_steps=8)
    _committed(root, cfg, 6)
    (root / "ledger.json").write_text(json.dumps([_row(0, 6)]))
    train = _fake_train(calls)

    def to_the_end(cfg, **kw):
        result = train(cfg, **kw)
        (tmp_path / "run" / "model.keras").write_bytes(b"the finished model")
        return result

    return root, cfg, to_the_end


def test_a_full_disk_at_the_finishing_row_keeps_the_row_and_the_record_whole(tmp_path,
                                                                            monkeypatch):
    """The chunk that finishes a part wrote the finished model, then its row: a full disk (or a
    kill) between lost the row, and the next call wrote the part's record from the rows before
    it (final_step 6 of 8, its wall time short) and removed resume/. The row is now kept
    (ledger.pending.json) before the model is written, so the next call adds it and writes the
    whole record."""
    root, cfg, to_the_end = _last_chunk_of_a_part(tmp_path)
    monkeypatch.setattr(training, "train", to_the_end)
    monkeypatch.setattr(chunks, "strip_optimizer",
                        lambda src, dst: open(dst, "wb").write(open(src, "rb").read()))
    real = ledger_lib.atomic_write_json

    def full_disk(path, doc):
        if os.path.basename(path) == ledger_lib.LEDGER_FILE:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(path, doc)

    monkeypatch.setattr(ledger_lib, "atomic_write_json", full_disk)
    with pytest.raises(OSError, match="No space left"):
        chunks.run_chunk(cfg, str(root), 0, "here", printer=QUIET, part="sequence2")
    assert (root / "sequence2.keras").exists() and not (root / "sequence2.json").exists()
    monkeypatch.setattr(ledger_lib, "atomic_write_json", real)
    with pytest.raises(FileExistsError, match="part sequence2 is finished"):
        chunks.run_chunk(cfg, str(root), 0, "here", printer=QUIET, part="sequence2")
    record = json.loads((root / "sequence2.json").read_text())
    assert record["final_step"] == 8 and record["chunks"][-1]["done"]
    assert [(r["from_step"], r["to_step"]) for r in record["chunks"]] == [(0, 6), (6, 8)]
    assert not (root / "resume" / "sequence2").exists()


def test_a_finished_part_without_its_finishing_row_keeps_resume(tmp_path):
    """A finished model whose finishing row is nowhere (a ledger mended from an older commit,
    the pending rows lost) got a record from the rows there were (final_step 4) and its
    committed checkpoint removed. The record is not written now, resume/ is kept, and the
    message says why."""
    root, said = tmp_path / "repo", []
    cfg = _train_cfg("d", tmp_path / "run", train_steps=8)
    _committed(root, cfg, 4)
    (root / "ledger.json").write_text(json.dumps([_row(0, 4)]))
    (root / "sequence2.keras").write_bytes(b"a finished model")
    with pytest.raises(FileExistsError, match="part sequence2 is finished"):
        chunks.run_chunk(cfg, str(root), 0, "here", printer=said.append, part="sequence2")
    assert not (root / "sequence2.json").exists()
    assert (root / "resume" / "sequence2" / "state.json").exists()
    assert any("no row that finished it" in line and "step 4" in line for line in said), said


def test_a_finished_model_cut_short_leaves_no_temporary_file(tmp_path, monkeypatch):
    """strip_optimizer's save cut short (a full disk) left ``stage<k>.keras.tmp-<pid>.keras``
    in the committed folder; it is removed now, and nothing is at the finished model's path."""
    from stnh_tf.modeling import runner

    class Cut:
        def save(self, path):
            open(path, "wb").write(b"PK\x03\x04 cut")
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(runner, "load_model", lambda src: Cut())
    with pytest.raises(OSError, match="No space left"):
        chunks.strip_optimizer(str(tmp_path / "final.keras"), str(tmp_path / "stage3.keras"))
    assert os.listdir(tmp_path) == []


def test_the_ledger_table_keeps_the_rest_of_the_document_as_it_was(tmp_path):
    """write_ledger_table read docs/gpu.md in the locale's encoding with newlines translated
    and wrote it back as UTF-8 with ``\\n``: a document with CRLF line endings (or, under a
    non-UTF-8 locale, a non-ASCII character) came back changed outside the block, and a
    document holding the markers twice had its text between the two blocks dropped. The rest
    of the document stays byte for byte now, and two blocks are refused."""
    root = tmp_path / "root"
    root.mkdir()
    (root / ledger_lib.LEDGER_FILE).write_text(json.dumps([_row(0, 4)]))
    doc = tmp_path / "gpu.md"
    head = "# runbook \u2014 \u00b5s\r\nprose\r\n".encode()
    doc.write_bytes(head + f"{ledger_lib.LEDGER_START}\nold\n{ledger_lib.LEDGER_END}".encode()
                    + b"\r\nmore\r\n")
    assert ledger_lib.write_ledger_table(str(root), str(doc))
    data = doc.read_bytes()
    assert data.startswith(head + ledger_lib.LEDGER_START.encode())
    assert data.endswith(ledger_lib.LEDGER_END.encode() + b"\r\nmore\r\n")
    twice = data + b"between\r\n" + f"{ledger_lib.LEDGER_START}\n{ledger_lib.LEDGER_END}".encode()
    doc.write_bytes(twice)
    with pytest.raises(ValueError, match="one .* block"):
        ledger_lib.write_ledger_table(str(root), str(doc))
    assert doc.read_bytes() == twice


def test_a_failed_finished_model_write_leaves_no_finishing_row(tmp_path, monkeypatch):
    """The finishing row is kept before the finished model is written; where that write fails
    (or the chunk is killed in it), the row stayed pending and the next call added it, then
    finished the part with a second finishing row (the ledger said "done" twice, once for a
    part without a model). It is dropped, the steps trained committed with a row of their
    own (the error), and the next call finishes the part with one finishing row."""
    root, cfg, to_the_end = _last_chunk_of_a_part(tmp_path)
    def full_disk(src, dst):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(training, "train", to_the_end)
    monkeypatch.setattr(chunks, "strip_optimizer", full_disk)
    with pytest.raises(OSError, match="No space left"):
        chunks.run_chunk(cfg, str(root), 0, "here", printer=QUIET, part="sequence2")
    assert not (root / "sequence2.keras").exists()
    assert not [r for r in json.loads((root / "ledger.pending.json").read_text())
                if r.get("done")]
    monkeypatch.setattr(chunks, "strip_optimizer",
                        lambda src, dst: open(dst, "wb").write(open(src, "rb").read()))
    row = chunks.run_chunk(cfg, str(root), 0, "here", printer=QUIET, part="sequence2")
    rows = ledger_lib.read_ledger(str(root))
    assert row["done"] and [(r["from_step"], r["to_step"], r["done"]) for r in rows] == [
        (0, 6, False), (6, 8, False), (8, 8, True)]
    assert "No space left" in rows[1]["error"]
    assert json.loads((root / "sequence2.json").read_text())["final_step"] == 8


def test_a_part_to_train_anew_beside_its_finished_run_folder_is_refused(tmp_path, monkeypatch):
    """Moving the finished model and record away "to train it anew" left the run folder's
    ``model.keras`` at ``train_steps``: the chunk took the "finished run, no training" shortcut
    and wrote the old model back as the new one, with a 4 -> 4 row. Refused now, naming the run
    folder to move away; nothing trained or written."""
    root, calls = tmp_path / "repo", []
    root.mkdir()
    (root / "ledger.json").write_text(json.dumps([_row(0, 4, done=True)]))
    cfg = _train_cfg("d", tmp_path / "run", train_steps=4)
    _fake_checkpoint(tmp_path / "run" / "checkpoint", 4)
    (tmp_path / "run" / "config.json").write_text(_config_json(cfg))
    (tmp_path / "run" / "model.keras").write_bytes(b"the finished run")
    monkeypatch.setattr(training, "train", _fake_train(calls))
    before = _files(root)
    with pytest.raises(ValueError, match=f"the run folder {tmp_path / 'run'} holds the finished"):
        chunks.run_chunk(cfg, str(root), 0, "here", printer=QUIET, part="sequence2")
    assert calls == [] and _files(root) == before


def test_an_error_with_nothing_new_to_commit_says_so(tmp_path, monkeypatch):
    """A chunk failing before it trained printed "its checkpoint of step N is committed ... with
    its ledger row" although nothing was committed (it compared with the step it started from,
    not the committed one), and a user believing it could delete the run folder. Said as it is
    now; where the run folder is ahead of the committed checkpoint, that one is committed."""
    run, resume, cfg = _commit_over(tmp_path, committed=2, own=2)
    lines = []
    chunks._commit_stopped(str(run), str(resume), str(tmp_path / "repo"), 2, lines.append,
                           lambda step: _row(2, step))
    assert lines == [f"training stopped by an error; nothing new to commit ({resume} holds step "
                     "2, the run folder step 2)"]
    _fake_checkpoint(run / "checkpoint", 8)  # trained by an earlier chunk, not committed
    lines.clear()
    chunks._commit_stopped(str(run), str(resume), str(tmp_path / "repo"), 8, lines.append,
                           lambda step: _row(8, step))
    assert json.loads((resume / "state.json").read_text())["step"] == 8
    assert "without a row" in lines[0] and not (tmp_path / "repo" / "ledger.json").exists()


def test_a_commit_that_fails_keeps_the_chunks_row(tmp_path, monkeypatch):
    """A full disk in ``sync_out`` lost the chunk's row (neither in the ledger nor kept
    pending): the next chunk went on from the run folder and the part's record left those
    steps out. The row is kept in ``ledger.pending.json``, marked not committed."""
    root, calls = tmp_path / "repo", []
    cfg = _train_cfg("d", tmp_path / "run", train_steps=100)
    _committed(root, cfg, 4)
    (root / "ledger.json").write_text(json.dumps([_row(0, 4)]))
    monkeypatch.setattr(training, "train", _fake_train(calls))

    def full(model_dir, resume):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(chunks, "sync_out", full)
    with pytest.raises(OSError, match="No space left"):
        chunks.run_chunk(cfg, str(root), 0, "here", printer=QUIET, part="sequence2")
    pending = json.loads((root / "ledger.pending.json").read_text())
    assert [(r["from_step"], r["to_step"], r["committed"]) for r in pending] == [(4, 6, False)]


@pytest.mark.slow  # (the binary in a subprocess, about 9 s)
def test_a_ledger_table_that_cannot_be_written_never_hides_the_chunks_error(tmp_path):
    """``paper_schedule`` rewrote docs/gpu.md's ledger table in a ``finally``: where that raised
    (a merge-conflicted gpu.md), its error replaced the chunk's own ("pair worker crashed", or
    that the row was kept in ledger.pending.json). The chunk's error is the one said now, the
    table's logged beside it."""
    import subprocess
    import sys

    script = (
        "import sys\n"
        "from absl import app\n"
        "from experiments import paper_schedule as ps\n"
        "from stnh_tf.training import chunks, ledger\n"
        "def crashed(*a, **k):\n"
        "    raise ValueError('pair worker crashed')\n"
        "def conflicted(*a, **k):\n"
        "    raise ValueError('gpu.md must hold one ledger block')\n"
        "chunks.run_chunk = crashed\n"
        "ledger.write_ledger_table = conflicted\n"
        f"ps.ROOT = {str(tmp_path)!r}\n"
        "sys.argv = ['paper_schedule', '--part=sequence2', "
        f"'--runs_dir={tmp_path / 'runs'}', '--time_limit_s=60']\n"
        "app.run(ps.main)\n")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.run([sys.executable, "-c", script], cwd=root, capture_output=True,
                          text=True, timeout=300, env={**os.environ, "PYTHONPATH": root})
    assert proc.returncode != 0 and "paper_schedule: pair worker crashed" in proc.stderr, \
        proc.stderr[-3000:]
    assert "ledger table not rewritten: gpu.md must hold one ledger block" in proc.stderr


def test_a_returned_chunk_merged_back_never_replaces_a_newer_committed_checkpoint(tmp_path):
    """The runbook said to untar what a GPU call sent back over the repository: where a CPU
    chunk had committed step 17,546 meanwhile, the sent (older) checkpoint of 17,544 came back
    over it and its ledger row went, and the next chunk resumed from 17,544 without a word.
    ``merge_back`` keeps the newer checkpoint and both machines' rows; a returned checkpoint of a
    later step replaces an older one here, a finished part comes in and its resume/ goes."""
    from stnh_tf.training.merge_back import merge_back

    cfg = _train_cfg("d", tmp_path / "run", train_steps=100)
    root, back = tmp_path / "repo", tmp_path / "back"
    sent = [_row(0, 4)]
    _committed(root, cfg, 6)  # the CPU chunk's, committed after the call was sent
    (root / "ledger.json").write_text(json.dumps([*sent, _row(4, 6, device="cpu")]))
    _committed(back / "paper_schedule", cfg, 5)  # the GPU chunk's, from step 4
    _committed(back / "paper_schedule", cfg, 3, part="stage3")
    (back / "paper_schedule" / "ledger.json").write_text(json.dumps(
        [*sent, _row(4, 5, device="gpu"), _row(0, 3, part="stage3", done=True)]))
    (back / "paper_schedule" / "stage3.keras").write_bytes(b"finished stage 3")
    _committed(root, cfg, 2, part="stage3")
    lines = []
    out = merge_back(str(root), str(back), printer=lines.append)
    assert out["kept"] == {"sequence2": 6} and out["rows"] == 2
    assert json.loads((root / "resume" / "sequence2" / "state.json").read_text())["step"] == 6
    rows = ledger_lib.read_ledger(str(root))
    # the GPU chunk's row, its weights not taken, before the CPU chunk's that goes on from the
    # same step: appended, it was the part's last row, and the next chunk's start and the part's
    # record (its chain of chunks) followed it (a review's find)
    assert [(r["from_step"], r["to_step"], r["device"]) for r in rows] == [
        (0, 4, "cpu"), (4, 5, "gpu"), (4, 6, "cpu"), (0, 3, "cpu")]
    assert ledger_lib.recorded_step(rows, "sequence2") == 6
    assert [(r["from_step"], r["to_step"]) for r in ledger_lib.chain(rows, "sequence2")] == [
        (0, 4), (4, 6)]
    assert (root / "stage3.keras").read_bytes() == b"finished stage 3"
    assert out["checkpoints"] == {"stage3": 3}  # (the part's resume/ came back too)
    assert any("kept the committed checkpoint of step 6" in line for line in lines)
    # merged again (an interrupted merge, say): nothing twice, the pending rows included
    (back / "paper_schedule" / "ledger.pending.json").write_text(json.dumps([_row(5, 7)]))
    merge_back(str(root), str(back), printer=QUIET)
    merge_back(str(root), str(back), printer=QUIET)
    assert len(ledger_lib.read_ledger(str(root))) == 4
    assert len(json.loads((root / "ledger.pending.json").read_text())) == 1
    (back / "paper_schedule" / "stage3.keras").write_bytes(b"another stage 3")
    with pytest.raises(ValueError, match="differs from .*stage3.keras"):
        merge_back(str(root), str(back), printer=QUIET)


@pytest.mark.parametrize("bad", [{"to_step": None}, {"from_step": "4"}, {"wall_s": "long"},
                                 {"stage": True}])
def test_a_ledger_row_without_its_numbers_is_refused_when_read(tmp_path, bad):
    """A row whose step or time is null or a string (a hand edit, a merge) passed the ledger's
    check (only the fields' presence) and failed later with a bare TypeError, in the step
    comparisons or the table's formatting. Refused when read now, naming the row and field; a
    pending file that is not a list of rows too."""
    (tmp_path / "ledger.json").write_text(json.dumps([_row(0, 2), {**_row(2, 4), **bad}]))
    with pytest.raises(ValueError, match=f"its row 1 holds no number in \\['{next(iter(bad))}'"):
        ledger_lib.read_ledger(str(tmp_path))
    (tmp_path / "ledger.json").write_text(json.dumps([_row(0, 2)]))
    (tmp_path / "ledger.pending.json").write_text(json.dumps({"rows": []}))
    with pytest.raises(ValueError, match="ledger.pending.json is not a list of ledger rows"):
        ledger_lib.add_pending_rows(str(tmp_path))


def test_an_error_rows_steps_per_s_is_over_training_time(tmp_path, monkeypatch):
    """An error row's steps/s was over the chunk's whole wall time, the pairs' making included
    (minutes of a chunk's start), where the other rows' are over training time alone: two rows
    of the same speed disagreed. Training's own start (the first ``fit`` call's) counts now."""
    root, calls = tmp_path / "repo", []
    train = _fake_train(calls)
    cfg = _train_cfg("d", tmp_path / "run", train_steps=100)
    _committed(root, cfg, 4)
    (root / "ledger.json").write_text(json.dumps([_row(0, 4)]))
    now = [1000.0]
    monkeypatch.setattr(chunks.time, "time", lambda: now[0])

    def failing(cfg, extra_callbacks=(), **kw):  # 100 s of pairs, 10 s of training, an error
        now[0] += 100.0
        for callback in extra_callbacks:
            callback.on_train_begin()
        train(cfg, **kw)
        now[0] += 10.0
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(training, "train", failing)
    with pytest.raises(OSError, match="No space left"):
        chunks.run_chunk(cfg, str(root), 0, "here", printer=QUIET, part="sequence2")
    rows = ledger_lib.read_ledger(str(root))
    assert (rows[-1]["from_step"], rows[-1]["to_step"]) == (4, 6)
    assert rows[-1]["steps_per_s"] == pytest.approx(2 / 10.0)  # before: 2 / 110
