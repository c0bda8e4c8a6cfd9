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
import shutil
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
    # a split made before the split's own digest was recorded: judged as then (kept)
    meta_path = os.path.join(d2, "metadata.json")
    meta = json.load(open(meta_path))
    del meta["splits"]["test"]["input_split_sha256"]
    json.dump(meta, open(meta_path, "w"))
    assert stage_k.check_one_source(d2, ["test"], source) == ["test"]


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


def test_a_float_image_with_a_few_values_above_one_stays_on_the_unit_scale():
    """One pixel at 1.01 (a sharpening's overshoot, a linear image's highlight) made the whole
    float image read on the 0..255 scale: black, "flat". A few values above 1 are clipped now;
    an image whose values mostly exceed 1 is still on 0..255."""
    from stnh_tf.data import sources

    unit = np.random.default_rng(0).random((60, 80))
    expected = np.rint(unit * 255).astype(np.uint8)
    over = unit.copy()
    over[0, 0] = 1.01
    got = sources.to_gray_uint8(over)
    assert got[0, 0] == 255 and np.array_equal(got.ravel()[1:], expected.ravel()[1:])
    assert np.array_equal(sources.to_gray_uint8(unit * 255.0), expected)


def test_a_16_bit_alpha_channel_is_on_the_images_full_scale():
    """A 16-bit alpha of 16384 (25%) on full-range colour was scaled by its own bit depth
    (32767: 50%), twice as bright as the same image in 8 bits; scaled like the colour now."""
    from stnh_tf.data import sources

    colour = np.full((4, 4, 3), 65535, np.uint16)
    alpha = np.full((4, 4, 1), 16384, np.uint16)
    got = sources.to_gray_uint8(np.concatenate([colour, alpha], axis=2))
    assert np.all(got == np.rint(255 * 16384 / 65535))  # 64, as RGBA8 with alpha 64 gives
    eight = np.concatenate([np.full((4, 4, 3), 255, np.uint8), np.full((4, 4, 1), 64, np.uint8)],
                           axis=2)
    assert np.array_equal(sources.to_gray_uint8(eight), got)


def test_the_demo_keeps_a_results_json_it_did_not_write(tmp_path):
    """``demo --output_dir=D`` wrote its ``results.json`` over any file of that name (a
    reproduction's own, by a mistyped folder); refused before any work now."""
    from stnh_tf.paper import demo

    out = tmp_path / "repro"
    out.mkdir()
    (out / "results.json").write_text(json.dumps({"budget": "cpu", "table1": {}}))
    with pytest.raises(FileExistsError, match="not an earlier result of demo"):
        demo.run_demo(str(out), samples_per_image=1, examples=1, printer=QUIET)
    assert json.loads((out / "results.json").read_text()) == {"budget": "cpu", "table1": {}}
    assert os.listdir(out) == ["results.json"]


@pytest.mark.slow  # (the demo's whole evaluation, about 20 s)
def test_the_demo_without_examples_draws_no_figure_and_writes_its_results(tmp_path):
    """``demo --examples=0`` (the flag's lower bound) died after the whole evaluation (a figure
    of no columns) and wrote no ``results.json``."""
    from stnh_tf.paper import demo

    result = demo.run_demo(str(tmp_path / "out"), samples_per_image=1, examples=0, printer=QUIET)
    assert result["figure"] is None
    saved = json.loads((tmp_path / "out" / "results.json").read_text())
    assert saved["written_by"] == "demo" and saved["num_pairs"] == result["num_pairs"] > 0


def test_the_overlay_of_images_wider_than_opencv_warps_is_drawn_smaller():
    """``predict`` on images 32,767 px or more on a side ended in a ``cv2.error`` traceback
    (``cv2.warpPerspective`` warps below SHRT_MAX) after the estimate, writing nothing. The
    overlay draws them at a long side of 4096 px; the border quad stays in the images' own
    pixels (OpenCV's ``perspectiveTransform`` of image_b's corners) and the aligned overlap
    blends to gray."""
    import cv2

    from stnh_tf.inference import overlays

    rng = np.random.default_rng(0)
    row = cv2.GaussianBlur(rng.random((1, 33200)).astype(np.float32), (0, 0), 20)
    wide = np.repeat(np.uint8(255 * (row - row.min()) / np.ptp(row)), 64, axis=0)
    image_a, image_b = wide[:, :33000], wide[:, 100:33100]  # b(x) = a(x + 100)
    a_from_b = np.array([[1.0, 0, 100], [0, 1, 0], [0, 0, 1]])
    colour = [cv2.cvtColor(im, cv2.COLOR_GRAY2BGR) for im in (image_a, image_b)]
    panels, quad = overlays.overlay(*colour, a_from_b)
    corners = np.float64([[0, 0], [32999, 0], [32999, 63], [0, 63]])
    np.testing.assert_allclose(quad, cv2.perspectiveTransform(corners[None], a_from_b)[0])
    assert panels.shape[1] <= 2 * (overlays.OVERLAY_MAX_SIDE + 8)
    blend = panels[-2:, overlays.OVERLAY_MAX_SIDE + 8 + 200:-200]  # right panel, bottom rows
    assert np.abs(blend[..., 0].astype(int) - blend[..., 1]).mean() < 3


def test_an_infinite_corner_shift_is_null_in_predicts_json():
    """``max_corner_shift_px`` was written with ``float()``: a corner mapped to infinity gave
    ``Infinity``, which strict JSON readers refuse (the fields beside it write null)."""
    import dataclasses

    from conftest import constant_stage
    from stnh_tf.inference import HomographyEstimator, image_files
    from stnh_tf.inference.options import EstimateOptions

    estimator = HomographyEstimator([constant_stage(np.eye(3), "results_id")])
    a = np.random.default_rng(0).integers(0, 256, (240, 320), np.uint8)
    made = estimator.estimate_images_with_info(a, a, EstimateOptions.network_only())
    estimate = dataclasses.replace(made, max_corner_shift_px=np.array([np.inf]))
    doc = image_files._estimate_json(estimate, (240, 320), np.zeros((4, 2)))
    assert doc["max_corner_shift_px"] is None
    json.dumps(doc, allow_nan=False)


@pytest.mark.skipif(not os.path.isdir(os.path.join(ROOT, ".git")) or not shutil.which("git"),
                    reason="needs this project's git checkout and git")
def test_the_commit_is_recorded_only_from_this_projects_own_checkout(tmp_path):
    """``git_commit`` ran git in the package's parent folder and took whatever repository held
    it: a copy of the package inside another repository (or installed into a virtual
    environment inside a checkout) recorded that repository's commit. ``None`` there now; this
    checkout still records its own (``git rev-parse --short HEAD``)."""
    import shutil

    repo = tmp_path / "other"
    (repo / "vendor").mkdir(parents=True)
    git = lambda *a: subprocess.run(["git", *a], cwd=repo, check=True,  # noqa: E731
                                    capture_output=True, text=True).stdout.strip()
    git("init", "-q")
    (repo / "README").write_text("other\n")
    (repo / ".gitignore").write_text("vendor/\n")
    git("add", "README", ".gitignore")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "other")
    shutil.copytree(os.path.join(ROOT, "stnh_tf"), repo / "vendor" / "stnh_tf",
                    ignore=shutil.ignore_patterns("weights", "__pycache__"))
    code = "from stnh_tf import provenance; print(provenance.git_commit())"
    got = subprocess.run([sys.executable, "-c", code], cwd=repo / "vendor", capture_output=True,
                         text=True, env={**os.environ, "PYTHONPATH": str(repo / "vendor")})
    assert got.stdout.strip() == "None", (got.stdout, got.stderr[-2000:])
    own = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                         text=True).stdout.strip()
    from stnh_tf import provenance

    assert provenance.git_commit().split("+")[0] == own


def test_the_reproductions_latency_is_measured_again_for_another_precision(tmp_path,
                                                                          monkeypatch):
    """``Reproduction.latency`` returned any ``eval/latency.json`` there, whatever precision,
    runs or machine measured it, and recorded no provenance, so ``results.json`` credited the
    numbers to its own run's machine. The cache is reused only for the same runs, warm-up,
    precision and models now, and carries where and under what load it was measured."""
    from stnh_tf.paper import reproduce, table2

    calls = []

    def fake_measure(stage_dirs, runs, warmup, policy):
        calls.append(policy)
        return {"hierarchy": {"1": {"d_e_ms": 5.0}}, "sequence": {}, "policy": policy}

    monkeypatch.setattr(table2, "measure", fake_measure)
    run = reproduce.Reproduction(reproduce.BUDGETS["tiny"], str(tmp_path / "out"),
                                 printer=QUIET)
    (tmp_path / "out" / "eval").mkdir(parents=True, exist_ok=True)
    (tmp_path / "out" / "eval" / "latency.json").write_text(json.dumps(
        {"hierarchy": {"1": {"d_e_ms": 99.0}}, "sequence": {}, "policy": "mixed_bfloat16"}))
    got = run.latency([])
    want = table2.policy(reproduce.BUDGETS["tiny"].mixed_precision)
    assert calls == [want] and got["hierarchy"]["1"]["d_e_ms"] == 5.0
    fields = table2.results_fields(got)
    assert fields["table2_latency_ms"] == {"1": 5.0}
    assert fields["latency_provenance"]["policy"] == want and "loadavg_at_start" in fields[
        "latency_provenance"]
    assert run.latency([])["hierarchy"]["1"]["d_e_ms"] == 5.0 and calls == [want]  # reused


def test_a_hierarchy_of_stages_from_different_runs_is_noted(tmp_path):
    """``evaluate --model_dir=runA,runB`` with runB's stage 2 trained on pairs made by another
    stage-1 model than runA's gave the hierarchy's numbers without a word; a note says so now
    (the training data's recorded ``model_sha256`` against stage 1's file), and none where the
    stage 1 is the one its pairs were made with."""
    import hashlib

    from stnh_tf.data import stage1
    from stnh_tf.evaluation import mace
    from stnh_tf.training import run_dir
    from stnh_tf.training.config import TrainConfig

    data = str(tmp_path / "stage2_data")
    stage1.make_dataset("bundled", data, "train", seed=0, num_shards=1, max_images=1,
                        samples_per_image=1, log=QUIET)
    made_with, other = tmp_path / "made_with.keras", tmp_path / "other.keras"
    made_with.write_bytes(b"model that made the pairs")
    other.write_bytes(b"another stage 1")
    meta_path = os.path.join(data, "metadata.json")
    meta = json.load(open(meta_path))
    meta["splits"]["train"]["model_sha256"] = hashlib.sha256(made_with.read_bytes()).hexdigest()
    json.dump(meta, open(meta_path, "w"))
    run2 = str(tmp_path / "run2")
    run_dir.prepare_model_dir(TrainConfig(model_dir=run2, data_dir=data, stage=2))
    notes = mace.stage_notes([str(other), run2], 1, data)
    assert len(notes) == 1 and "trained on pairs made by another model than its stage 1" in notes[0]
    assert mace.stage_notes([str(made_with), run2], 1, data) == []


def test_a_committed_result_from_before_the_key_is_replaced_by_its_own_binary_only(tmp_path):
    """The results committed before ``written_by`` record the command that wrote them
    (``machine.command``): BENCHMARKS.md's commands that regenerate them are accepted, another
    binary is not."""
    for command, writer in (
            ("python /work/main/experiments/benchmark_small_images.py --json_out=x.json",
             "benchmark_small_images"),
            ("python -m experiments.ablate_estimator --pairs_dirs=S --json_out=x.json",
             "ablate_estimator")):
        path = tmp_path / f"{writer}.json"
        path.write_text(json.dumps({"rows": [], "machine": {"command": command}}))
        summaries.check_json_out(str(path), writer)
        with pytest.raises(FileExistsError, match="not an earlier result of evaluate"):
            summaries.check_json_out(str(path), "evaluate")
    committed = os.path.join(ROOT, "docs", "small_images.json")
    summaries.check_json_out(committed, "benchmark_small_images")


def test_nested_image_folders_are_refused(tmp_path):
    """With ``p`` and ``p/sub`` both given, a photograph of ``sub`` was keyed by its path in
    whichever folder came first: train from ``p,p/sub`` and val from ``p/sub,p`` passed the
    hold-out check (the same folders) and shared photographs. Refused, naming both."""
    from stnh_tf.data import sources

    (tmp_path / "p" / "sub").mkdir(parents=True)
    with pytest.raises(sources.SourceError, match="sub lies inside .*p, also given"):
        sources.split_folders([str(tmp_path / "p"), str(tmp_path / "p" / "sub")])
    assert sources.split_folders([str(tmp_path / "p"), str(tmp_path / "p") + "/"])  # the same


def _jpeg(path, seed=0):
    import cv2

    image = np.random.default_rng(seed).integers(0, 256, (40, 50), np.uint8)
    cv2.imwrite(str(path), image)


def test_one_photograph_under_two_names_is_listed_once(tmp_path):
    """A folder given again through a link to it, and a hard link inside a folder, listed the
    same photograph twice (duplicates were found by the path only, or by ``realpath``, which a
    hard link does not share); each is listed once now, the other name left out and named."""
    from stnh_tf.data import sources

    p = tmp_path / "p"
    p.mkdir()
    for k in range(3):
        _jpeg(p / f"a{k}.jpg", k)
    os.link(p / "a0.jpg", p / "hard.jpg")
    os.symlink(p, tmp_path / "plink")
    one = sources.scan_image_folder(str(p))
    assert [os.path.basename(f) for f in one.files] == ["a0.jpg", "a1.jpg", "a2.jpg"]
    assert [(os.path.basename(f), why.split(" as")[0]) for f, why in one.unreadable] == [
        ("hard.jpg", "the same file (a link)")]
    both = sources.scan_image_folders([str(p), str(tmp_path / "plink")])
    assert len(both.files) == 3  # of 8 names: the other 5 named as the same file
    assert sum(why.startswith(sources.SAME_FILE) for _, why in both.unreadable) == 5


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes here")
def test_a_named_pipe_in_a_photograph_folder_is_left_out_not_read(tmp_path):
    """A FIFO named ``z.jpg`` was listed as a photograph and every reader blocked on it
    (make_dataset, the camera pairs, tune_baselines hung). Left out, named, now."""
    from stnh_tf.data import sources

    _jpeg(tmp_path / "a.jpg")
    os.mkfifo(tmp_path / "z.jpg")
    listing = sources.scan_image_folder(str(tmp_path))
    assert [os.path.basename(f) for f in listing.files] == ["a.jpg"]
    assert listing.unreadable == [(str(tmp_path / "z.jpg"), sources.NOT_A_FILE)]


def test_a_camera_pair_set_made_again_leaves_a_hard_linked_snapshot_whole(tmp_path):
    """The set's PNGs were written in place (``open(target, "wb")``): a snapshot made with
    ``cp -al`` was rewritten through its hard links and no longer matched its own manifest.
    Each PNG is a new file renamed in now."""
    import shutil

    from stnh_tf.data import camera_pair_files

    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(2):
        _jpeg_big = np.random.default_rng(k).integers(0, 256, (240, 320), np.uint8)
        import cv2

        cv2.imwrite(str(photos / f"p{k}.png"), cv2.GaussianBlur(_jpeg_big, (0, 0), 2))
    out, snap = tmp_path / "set", tmp_path / "snapshot"
    camera_pair_files.write_pairs(str(photos), str(out), pairs_per_image=1, seed=0)
    snap.mkdir()
    for name in os.listdir(out):
        os.link(out / name, snap / name)
    camera_pair_files.write_pairs(str(photos), str(out), pairs_per_image=1, seed=1,
                                  overwrite=True)
    camera_pair_files.load_pairs(str(snap))  # its files as its manifest lists them
    camera_pair_files.load_pairs(str(out))
    shutil.rmtree(snap)


def test_benchmark_flags_that_make_no_measure_are_refused():
    """``benchmark_workers --warmup=0`` reported a negative step time (first batch end minus
    last), ``tune_baselines --num_pairs=0`` and ``benchmark_stream --epochs=0`` failed after
    their setup: refused at the flags now."""
    for binary, flag in (("benchmark_workers", "--warmup=0"), ("tune_baselines", "--num_pairs=0"),
                         ("benchmark_stream", "--epochs=0")):
        proc = _run(f"experiments.{binary}", flag)
        assert proc.returncode != 0 and f"flag {flag}: 0 is not a positive integer" in \
            proc.stderr, proc.stderr[-2000:]


def test_stage_pairs_refuse_a_float_context():
    """A float context on [0, 1] (the docstring said "uint8 or float") was rounded straight to
    uint8: every pixel 0 or 1. Refused now, naming the dtype."""
    from stnh_tf import hierarchy

    ctx = np.random.default_rng(0).integers(0, 256, (192, 192), np.uint8)
    assert np.ptp(hierarchy.stage_pair(ctx, np.eye(3), np.eye(3))["patch_a"]) > 200
    with pytest.raises(ValueError, match="context_a must be uint8.*float64"):
        hierarchy.stage_pair(ctx / 255.0, np.eye(3), np.eye(3))


def test_a_stage_file_without_its_weights_is_named(tmp_path):
    """A ``.keras`` zip without its weights gave Keras' "Expected a model.weights.h5 or
    model.weights.npz file." alone: which stage of a hierarchy was broken went unsaid."""
    import zipfile

    from stnh_tf.inference import HomographyEstimator

    broken = tmp_path / "stage1.keras"
    with zipfile.ZipFile(os.path.join(ROOT, "stnh_tf", "weights", "stage1.keras")) as src, \
            zipfile.ZipFile(broken, "w") as dst:
        for item in src.infolist():
            if not item.filename.startswith("model.weights"):
                dst.writestr(item, src.read(item.filename))
    with pytest.raises(ValueError, match=f"cannot load a Keras model from {broken}"):
        HomographyEstimator.load(str(broken))


def test_an_ablation_refuses_sets_of_different_image_sizes():
    """A 640 x 480 set (``make_camera_pairs --scale=2``) and a 320 x 240 one were pooled into
    one cell per group: errors of two frames in one mean and one 3-px success count (an identity
    stub: 25.9 px on the 320 set, 51.7 on the same pairs at 640, 38.8 pooled). Refused before
    any estimate now, naming the sizes."""
    from types import SimpleNamespace

    from stnh_tf.evaluation import ablation

    def pair(size):
        image = np.zeros(size, np.uint8)
        return SimpleNamespace(image_a=image, image_b=image, h_ba=np.eye(3), group="within")

    class NoEstimates:
        def estimate_images_with_info(self, *args):
            raise AssertionError("an estimate before the sizes were checked")

    with pytest.raises(ValueError, match=r"differ in size \(S: 320 x 240, S2: 640 x 480\)"):
        ablation.run([("S", [pair((240, 320))]), ("S2", [pair((480, 640))])], ["default"],
                     NoEstimates())


def test_the_tuning_grid_holds_no_row_that_changes_nothing():
    """``orb/ratio+crosscheck`` set ``cross_check=True``, which ORB_SETTINGS already holds (and
    no ratio): the registered ``orb_ransac`` again, under a name saying otherwise. Every grid row
    changes at least one setting of its baseline now."""
    from stnh_tf.evaluation import baseline_tuning, baselines

    defaults = {"orb_ransac": baselines.ORB_SETTINGS, "orb_default": baselines.ORB_DEFAULT_SETTINGS,
                "sift_ransac": baselines.SIFT_SETTINGS}
    for label, name, changes in baseline_tuning.settings_grid("small")[4:]:
        assert any(defaults[name].get(k) != v for k, v in changes.items()), label


def test_a_non_finite_homography_leaves_the_camera_pair_json_strict(monkeypatch):
    """A method returning a NaN homography made ``mace`` and its pairs' errors infinite, and the
    benchmark's JSON held ``Infinity``, which strict JSON readers refuse. Written as ``"inf"``
    now (as the ablation's JSON always was)."""
    from types import SimpleNamespace

    from stnh_tf.evaluation import baselines, camera_pairs

    image = np.random.default_rng(0).integers(0, 256, (240, 320), np.uint8)
    pairs = [SimpleNamespace(image_a=image, image_b=image, h_ba=np.eye(3), group="within",
                             index=k, kind="camera", offset_px=0.0) for k in range(2)]
    monkeypatch.setattr(baselines.SiftRansac, "estimate_images",
                        lambda self, a, b: (np.full((3, 3), np.nan), False))
    result = camera_pairs.benchmark(pairs, methods=("identity", "sift_ransac"), per_pair=True)
    text = json.dumps(result, allow_nan=False)
    assert result["groups"]["within"]["sift_ransac"]["mace"] == "inf"
    assert json.loads(text)["pairs"][0]["sift_ransac_error"] == "inf"


@pytest.mark.slow  # (a pool of two worker processes, started and killed: about 8 s)
def test_a_killed_pair_worker_stops_the_stream_instead_of_hanging_it(tmp_path):
    """``multiprocessing.Pool`` replaces a worker that dies (killed, out of memory) and drops the
    task it was running: the stream waited for that batch forever, training frozen without a
    word. It stops with an error naming the cause now, and the process then exits (the pool's
    own stop at exit waited on a lock the dead worker held): run in a process of its own."""
    import shutil
    import subprocess
    import sys

    from stnh_tf.data import bundled_photos

    folder = tmp_path / "photos"
    folder.mkdir()
    for k, (_, path) in enumerate(bundled_photos.bundled_image_files()[:4]):
        shutil.copy(path, folder / f"{k:02d}{os.path.splitext(path)[1]}")
    script = (
        "import os, signal, sys, time\n"
        "from stnh_tf.data import pair_datasets\n"
        "if __name__ == '__main__':\n"
        f"    stream = pair_datasets.PairStream({str(folder)!r}, 4, samples_per_image=3, "
        "seed=0, workers=2, prefetch=2)\n"
        "    stream[0]\n"
        "    for worker in list(stream._pool._pool):\n"
        "        os.kill(worker.pid, signal.SIGKILL)\n"
        "    try:\n"
        "        for step in range(1, 30):\n"
        "            stream[step]\n"
        "    except RuntimeError as e:\n"
        "        print('stopped:', e)\n"
        "    stream.close()\n")
    (tmp_path / "killed.py").write_text(script)
    proc = subprocess.run([sys.executable, str(tmp_path / "killed.py")], capture_output=True,
                          text=True, timeout=120, env={**os.environ, "PYTHONPATH": ROOT})
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "stopped: a pair-generator worker process died" in proc.stdout, proc.stdout


def test_a_mixed_stream_is_moved_on_not_rebuilt(monkeypatch):
    """The stream with real pairs mixed in (``--unlabeled_pairs_dir``) had no ``start_step``:
    every fit call after the first (each chunk resumed between checkpoints) closed it and made
    every pair again, the old set still held meanwhile. It moves on with its inner stream now,
    its real pairs those of the new steps."""
    from stnh_tf.data import batches, unlabeled_pairs
    from stnh_tf.training import fit_calls

    class Inner:
        start_step = 10

        def __getitem__(self, index):
            return ("inner", self.start_step + index)

    class Pairs:
        def rows(self, step, count, seed):
            return ("extra", step)

    monkeypatch.setattr(batches, "model_batch", lambda stacked: stacked)
    monkeypatch.setattr(unlabeled_pairs, "concat_batches", lambda a, b: (a, b))
    inner, rebuilt = Inner(), []
    stream = unlabeled_pairs.mixed_stream(inner, Pairs(), 2, 0, 10)
    assert stream[1] == (("inner", 11), ("extra", 11))
    moved = fit_calls.advance_stream(stream, 5, lambda: rebuilt.append(1))
    assert moved is stream and rebuilt == [] and inner.start_step == 15
    assert stream[1] == (("inner", 16), ("extra", 16))


def test_every_documented_command_may_write_its_json_out_again():
    """Each command in the docs that writes ``--json_out`` over a committed result names the
    binary that wrote it (``written_by``, or the command the result records): run again as
    written, it is not refused (two committed evaluations recorded neither)."""
    import glob
    import re

    docs = [os.path.join(ROOT, n) for n in ("README.md", "BENCHMARKS.md")]
    docs += glob.glob(os.path.join(ROOT, "docs", "*.md"))
    checked = 0
    for doc in docs:
        for line in open(doc, encoding="utf-8"):
            binary = re.search(r"python -m experiments\.(\w+)", line)
            out = re.search(r"--json_out=([\w./-]+\.json)\b", line)
            if not binary or not out or not os.path.isfile(os.path.join(ROOT, out.group(1))):
                continue
            summaries.check_json_out(os.path.join(ROOT, out.group(1)), binary.group(1),
                                     make_folder=False)
            checked += 1
    assert checked >= 20
