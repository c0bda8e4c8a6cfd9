"""Faults of a hostile review of the evaluation and figure binaries (2026-12-07). Data loss:
``--json_out`` replaced any JSON that carried no project ``format`` (a run's ``state.json``,
the reproduction's ``results.json``, another tool's result); ``plot_learning_curves
--json_out`` had no check (it wrote over README.md); ``plot_hbar_histogram`` wrote its
statistics over any JSON of the figure's name; a figure cut short by a full disk or a kill left a
truncated PNG in place of the old one. Silently wrong: a stage-k split was kept as "made from the
same data" after the stage-1 split it came from was made again (only the input's train split
was recorded)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from stnh_tf.evaluation import summaries

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
QUIET = lambda *a, **k: None  # noqa: E731


def test_json_out_replaces_only_an_earlier_result_of_the_same_binary(tmp_path):
    """A run's ``state.json``, another binary's result or a result without the key are refused
    before the work; the binary's own earlier result and a blank file stay writable, and what
    it writes names it."""
    state = tmp_path / "run" / "state.json"
    state.parent.mkdir()
    state.write_text(json.dumps({"epoch": 36, "logs": {"loss": 0.17}}))
    before = state.read_bytes()
    with pytest.raises(FileExistsError, match="not an earlier result of evaluate"):
        summaries.check_json_out(str(state), "evaluate")
    assert state.read_bytes() == before
    out = tmp_path / "result.json"
    summaries.write_json_out({"mace": 1.5}, str(out), "benchmark_camera_pairs")
    assert json.loads(out.read_text()) == {"mace": 1.5, "written_by": "benchmark_camera_pairs"}
    with pytest.raises(FileExistsError, match="not an earlier result of evaluate"):
        summaries.check_json_out(str(out), "evaluate")
    summaries.check_json_out(str(out), "benchmark_camera_pairs")  # its own: a re-run replaces it
    lines = []
    summaries.emit({"mace": 2.0}, "table", str(out), lines.append, writer="benchmark_camera_pairs")
    assert json.loads(out.read_text())["mace"] == 2.0 and lines == ["table", f"JSON: {out}"]
    (tmp_path / "blank.json").write_text("\n")
    summaries.check_json_out(str(tmp_path / "blank.json"), "evaluate")


def test_a_define_json_out_binary_refuses_a_file_it_did_not_write(tmp_path):
    """The ``--json_out`` of the benchmark binaries (``flags_common.define_json_out``) is
    checked when the flags are read: another file is refused before any work."""
    from absl import flags

    from experiments import flags_common

    fv = flags.FlagValues()
    flags_common.define_json_out(fv)
    doc = tmp_path / "README.md"
    doc.write_text("# notes\n")
    with pytest.raises(flags.IllegalFlagValueError, match="is not JSON"):
        fv(["benchmark_latency", f"--json_out={doc}"])
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"rows": []}))
    with pytest.raises(flags.IllegalFlagValueError, match="not an earlier result"):
        fv(["benchmark_latency", f"--json_out={other}"])
    assert doc.read_text() == "# notes\n" and json.loads(other.read_text()) == {"rows": []}


def _run(*args, cwd=ROOT):
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=300)


@pytest.mark.slow  # (two binaries, about 5 s each)
def test_the_figure_binaries_keep_a_json_they_did_not_write(tmp_path):
    """``plot_learning_curves --json_out=README.md`` replaced the document with the curve;
    ``plot_hbar_histogram --output=D/x.png`` replaced ``D/x.json`` whatever it held. Both are
    refused now, the files as they were."""
    log = tmp_path / "chunk.log"
    log.write_text("I1207 12:00:00.000000 1 loop.py:1] step 100/200 loss 0.5 lr 0.01\n")
    doc = tmp_path / "README.md"
    doc.write_text("# notes\n")
    proc = _run("experiments.plot_learning_curves", f"--logs={log}",
                f"--output={tmp_path / 'c.png'}", f"--json_out={doc}")
    assert proc.returncode != 0 and "is not JSON" in proc.stderr, proc.stderr[-2000:]
    assert doc.read_text() == "# notes\n"
    stats = tmp_path / "figs" / "fig.json"
    stats.parent.mkdir()
    stats.write_text(json.dumps({"kept": True}))
    proc = _run("experiments.plot_hbar_histogram", f"--data_dir={tmp_path / 'data'}",
                f"--output={tmp_path / 'figs' / 'fig.png'}")
    assert proc.returncode != 0 and "not an earlier result" in proc.stderr, proc.stderr[-2000:]
    assert json.loads(stats.read_text()) == {"kept": True}


def test_a_figure_cut_short_leaves_the_old_one_whole(tmp_path, monkeypatch):
    """``savefig`` wrote into the figure's path: a full disk (``OSError``) midway left a
    truncated PNG in place of the committed one. The figure is rendered to memory and written
    by an atomic rename now."""
    import matplotlib.figure

    from stnh_tf.paper import figures

    path = tmp_path / "fig1.png"
    path.write_bytes(b"old figure")

    def failing_savefig(self, target, *args, **kwargs):
        if hasattr(target, "write"):
            target.write(b"\x89PNG partial")
        else:
            with open(target, "wb") as f:
                f.write(b"\x89PNG partial")
        raise OSError(27, "File too large")

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", failing_savefig)
    h_bar = np.random.default_rng(0).normal(size=(20, 8))
    with pytest.raises(OSError, match="File too large"):
        figures.hbar_histogram(h_bar, str(path), bins=5)
    assert path.read_bytes() == b"old figure"
    assert os.listdir(tmp_path) == ["fig1.png"]


def test_a_stage_k_split_is_not_kept_once_its_input_split_is_made_again(tmp_path):
    """``made_from`` recorded the input's train split for every split: after the stage-1 test
    split was made again (another seed), the stage-2 test split made from the old one was
    "complete, made from the same data and model: kept". Each split records its own input
    split now, and is kept only where that split is the same."""
    from stnh_tf.data import stage1, stage_k

    d1, d2 = str(tmp_path / "s1"), str(tmp_path / "s2")
    stage1.make_dataset("bundled", d1, "train", seed=0, num_shards=1, max_images=2,
                        samples_per_image=1, log=QUIET)
    stage1.make_dataset("bundled", d1, "test", seed=1, num_shards=1, max_images=2,
                        samples_per_image=1, log=QUIET)
    model = os.path.join(ROOT, "stnh_tf", "weights", "stage1.keras")
    stage_k.make_stage_dataset(2, d1, d2, "test", model_dir=model, log=QUIET)
    source = stage_k.made_from(d1, model)
    assert stage_k.check_one_source(d2, ["test"], source) == ["test"]  # the same: kept
    stage_k.check_made(d2, "test", d1, model)
    stage1.make_dataset("bundled", d1, "test", seed=5, num_shards=1, max_images=2,
                        samples_per_image=1, log=QUIET, overwrite=True)
    assert stage_k.check_one_source(d2, ["test"], source) == []  # made again
    with pytest.raises(ValueError, match="from another 'test' split of"):
        stage_k.check_made(d2, "test", d1, model)


def test_a_restore_cut_short_leaves_no_truncated_model_that_counts_as_finished(tmp_path,
                                                                             monkeypatch):
    """``SemiSupervised.restore`` copied the repository's ``<name>.keras`` straight into the
    run's ``model.keras``: a kill or a full disk midway left a truncated file that counts as a
    finished model (never trained again, failing at load). Copied through a temporary file and
    renamed now: cut short, nothing is there and the next restore copies it."""
    import shutil

    from stnh_tf.paper import reproduce, semi_supervised
    from stnh_tf.training import run_dir

    run = reproduce.Reproduction(reproduce.BUDGETS["tiny"], str(tmp_path / "out"),
                                 printer=QUIET)
    experiment = semi_supervised.SemiSupervised(run)
    monkeypatch.setattr(semi_supervised.SemiSupervised, "check_repo", lambda self, repo: None)
    name = experiment.model_names()[0]
    repo = tmp_path / "repo"
    repo.mkdir()
    (repo / f"{name}.keras").write_bytes(b"PK" + bytes(4096))
    (repo / f"{name}.json").write_text(json.dumps({"format": "stnh_tf.train_config"}))
    real_copy2 = shutil.copy2

    def cut_short(src, dst, **kwargs):
        if str(src).endswith(".keras"):
            with open(dst, "wb") as f:
                f.write(b"PK" + bytes(100))
            raise OSError(28, "No space left on device")
        return real_copy2(src, dst, **kwargs)

    monkeypatch.setattr(shutil, "copy2", cut_short)
    with pytest.raises(OSError, match="No space left"):
        experiment.restore(str(repo))
    final = os.path.join(run.model_dir(name), run_dir.FINAL_MODEL)
    assert not os.path.exists(final)
    assert os.listdir(run.model_dir(name)) == [run_dir.CONFIG_FILE]
    monkeypatch.setattr(shutil, "copy2", real_copy2)
    assert experiment.restore(str(repo))[name] == "finished"
    assert open(final, "rb").read() == b"PK" + bytes(4096)


def test_the_evaluation_cache_checks_the_models_where_the_pairs_are_unknown(tmp_path):
    """``pairs is None or A and B and C`` read as ``pairs is None or (A and B and C)``: where the
    test split could not be read (no pairs digest) any cached evaluation was taken, another
    model's or a 2-model one for 1 model."""
    from stnh_tf.paper import eval_cache

    path = tmp_path / "eval.json"
    path.write_text(json.dumps({"model": {"mace": 3.0},
                                eval_cache.CACHE_KEY: {"models": ["sha-old"], "pairs": None}}))
    assert eval_cache.cached(str(path), {"models": ["sha-new"], "pairs": None}, []) is None
    assert eval_cache.cached(str(path), {"models": ["sha-old", "x"], "pairs": None}, []) is None
    assert eval_cache.cached(str(path), {"models": ["sha-old"], "pairs": None},
                             [])["model"]["mace"] == 3.0


def test_an_unknown_baseline_is_refused_before_any_pair_is_read(tmp_path):
    """``evaluate --baselines=sift`` (a typo) failed only after the data were read and every
    model had run; refused first now, naming the choices."""
    from stnh_tf.evaluation import mace

    with pytest.raises(ValueError, match=r"unknown baseline\(s\) \['sift'\]; choose from"):
        mace.evaluate((), str(tmp_path / "no_such_data"), "test", ["identity", "sift"])
