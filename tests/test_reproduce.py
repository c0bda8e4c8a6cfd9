"""The reproduce driver end to end at a tiny budget (a few steps per model, bundled photographs;
marked slow, about 2 minutes), and its budget checks of reused models (fast)."""

import dataclasses
import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from stnh_tf.paper import reproduce
from stnh_tf.training import presets, run_dir
from stnh_tf.data import tfrecords as data

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PNG = b"\x89PNG\r\n\x1a\n"


def _mace(h, h_true):
    """MACE (px) of ``h`` ([3, 3] or [N, 3, 3]) against ``h_true`` [N, 3, 3], written out here."""
    corners = np.array([[0, 0, 1], [128, 0, 1], [128, 128, 1], [0, 128, 1]], np.float64).T
    p, q = h @ corners, h_true @ corners
    return float(np.linalg.norm(p[:, :2] / p[:, 2:] - q[:, :2] / q[:, 2:], axis=1).mean())


def _model_mace(model_dir, samples):
    """MACE of a single-stage model's raw H_bar on ``samples``, denormalized with the paper's M
    written out independently (conftest)."""
    import keras

    from conftest import norm_matrix

    model = keras.models.load_model(os.path.join(model_dir, "model.keras"), compile=False)
    h8 = model.predict({"patch_a": samples["patch_a"], "patch_b": samples["patch_b"]},
                       verbose=0)["h_bar"].astype(np.float64)
    h_bar = np.concatenate([h8, np.ones((len(h8), 1))], axis=1).reshape(-1, 3, 3)
    m = norm_matrix()
    return _mace(np.linalg.inv(m) @ h_bar @ m, samples["h_ba"])


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("reproduce"))
    logs = []
    run = reproduce.Reproduction(reproduce.BUDGETS["tiny"], out, source="bundled",
                                 printer=logs.append)
    result = run.run()
    return out, result, logs


@pytest.mark.slow
def test_every_table_and_figure_is_written(tiny_run):
    out, result, logs = tiny_run
    # Progress (issue 78): each model's line at its last step, with its loss, steps/s and time
    # left, and the training's; after the last model, nothing is left.
    steps = [x for x in logs if re.match(r"\[train\] \S+ step 2/2 loss=\S+ \(\d+\.\d\d steps/s, "
                                         r"0 s left; training: ", x)]
    assert [x.split(" ")[1] for x in steps] == [m[0] for m in reproduce.planned_models(
        reproduce.BUDGETS["tiny"], reproduce.ABLATION_WEIGHTS)]
    assert steps[-1].endswith("; training: 0 s left)")
    tables = open(os.path.join(out, "tables.md")).read()
    for heading in ("Fig. 4", "Table 1", "Table 2"):
        assert heading in tables
    # Every method of Fig. 4 and every ablation row has a number, with the paper's beside it.
    fig4 = result["fig4_mace"]
    assert set(fig4) == {"Identity", "ORB + RANSAC", "SIFT + RANSAC", "HomographyNet",
                         "STN-Homography 1 stage", "STN-Homography 2 stages",
                         "STN-Homography 3 stages", "Sequence 2 stages"}
    assert all(np.isfinite(v) and v >= 0 for v in fig4.values())
    # (a row whose stage predictions were rejected is marked and explained: the tiny models')
    marked = " (rejected: see below)" if result["fig4_rejected"].get(
        "STN-Homography 3 stages") else ""
    assert re.search(r"\| STN-Homography 3 stages" + re.escape(marked)
                     + r" \| \d+\.\d\d \| [^|]* \| 1\.57 \|", tables)  # (the paper's schedule)
    assert ("Rejected predictions" in tables) == bool(result["fig4_rejected"])
    assert "**Smoke test**" in tables and "**Smoke test**" in open(
        os.path.join(out, "table1.md")).read()
    assert set(result["table1_mace"]) == {"1,1", "1,10", "1,0.1", "10,1", "0.1,1"}
    # The rows the paper's claim compares have the budget's seeds (tiny: 2), the others one.
    assert re.search(r"\| 10 \| 1 \| \d+\.\d\d \| 2 seeds: \d+\.\d\d, \d+\.\d\d \| [^|]* "
                     r"\| 4\.85 \|", tables)
    assert re.search(r"\| 1 \| 10 \| \d+\.\d\d \| 1 seed \| [^|]* \| 21\.86 \|", tables)
    assert {k: len(v) for k, v in result["table1_mace_per_seed"].items()} == {
        "1,1": 2, "1,10": 1, "1,0.1": 1, "10,1": 2, "0.1,1": 1}
    assert set(result["table2_latency_ms"]) == {"1", "2", "3"}
    assert all(v > 0 for v in result["table2_latency_ms"].values())
    for name in ("fig1_hbar_histogram.png", "fig4_mace_bars.png", "fig5_prediction_examples.png"):
        with open(os.path.join(out, "figures", name), "rb") as f:
            assert f.read(8) == PNG
    # header, rule, the identity and 5 rows
    assert open(os.path.join(out, "table1.md")).read().count("\n| ") == 8
    # Where each model was trained (issue 78): all here, by this process, none reused.
    prov = result["model_provenance"]
    assert set(prov) == {"stage1", "stage2", "stage3", "homographynet", "sequence2",
                         *(reproduce.ablation_name(*w, seed) for w in reproduce.ABLATION_WEIGHTS
                           for seed in reproduce.table1_seeds(reproduce.BUDGETS["tiny"], *w)
                           if (*w, seed) != (1.0, 1.0, 0))}
    assert result["assembled"] is False and not any(e["reused"] for e in prov.values())
    for e in prov.values():
        assert e["steps"] == json.load(open(os.path.join(e["run"], "config.json")))["train_steps"]
        assert (e["commit"], e["backend"], e["machine"]["cores"]) == (
            result["machine"]["git_commit"], result["machine"]["keras_backend"], os.cpu_count())
    table1 = json.load(open(os.path.join(out, "table1.json")))
    assert table1["assembled"] is False and set(table1["model_provenance"]) == {
        n for n in prov if n.startswith("ablation_") or n == "stage1"}
    assert "Every model was trained by this reproduction" in tables


@pytest.mark.slow
def test_numbers_come_from_the_models_on_the_test_pairs(tiny_run):
    """Identity and the (1, 1) ablation row (= stage 1 alone) recomputed here from the stored test
    pairs: the model's raw H_bar, denormalized with the paper's M written out independently."""
    out, result, _ = tiny_run
    samples = data.load_arrays(os.path.join(out, "data", "stage1"), "test")
    assert result["fig4_mace"]["Identity"] == pytest.approx(_mace(np.eye(3)[None], samples["h_ba"]),
                                                            rel=1e-9)
    stage1 = result["models"]["stages"][0]
    assert result["models"]["ablation"]["1,1"] == stage1
    # Seed 0 of the (1, 1) row is stage 1; seed 1 is its own model, trained with seed 1.
    seed1 = result["models"]["ablation_seeds"]["1,1"][1]
    assert result["models"]["ablation_seeds"]["1,1"][0] == stage1 and seed1 != stage1
    assert json.load(open(os.path.join(seed1, run_dir.CONFIG_FILE)))["seed"] == 1
    per_seed = [_model_mace(stage1, samples), _model_mace(seed1, samples)]
    assert result["table1_mace_per_seed"]["1,1"] == pytest.approx(per_seed, rel=1e-4)
    assert result["table1_mace"]["1,1"] == pytest.approx(np.mean(per_seed), rel=1e-4)


@pytest.mark.slow
def test_rerun_skips_finished_work_and_ablation_binary_reuses_rows(tiny_run):
    """A second run trains nothing and reports what the models give (recomputed here from the
    stored test pairs, not from the first run's results); so does the ablation binary."""
    out, first, _ = tiny_run
    samples = data.load_arrays(os.path.join(out, "data", "stage1"), "test")
    logs = []
    again = reproduce.Reproduction(reproduce.BUDGETS["tiny"], out, source="bundled",
                                   printer=logs.append).run()
    assert not any(line.startswith(("[train]", "[data]")) for line in logs), logs
    assert not [k for k in again["timings_this_run_s"] if k.startswith("train_")]
    assert set(again["fig4_mace"]) == set(first["fig4_mace"])
    assert again["fig4_mace"]["Identity"] == pytest.approx(_mace(np.eye(3)[None], samples["h_ba"]),
                                                           rel=1e-9)
    for row, dirs in again["models"]["ablation_seeds"].items():
        assert dirs == first["models"]["ablation_seeds"][row]  # the same models, not retrained
        assert again["table1_mace_per_seed"][row] == pytest.approx(
            [_model_mace(d, samples) for d in dirs], rel=1e-4), row
    res = subprocess.run([sys.executable, "-m", "experiments.loss_weight_ablation", "--budget=tiny",
                          "--source=bundled", f"--output_dir={out}", "--weights=10:1,1:1"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert ("l2=10 l1=1: MACE" in res.stdout and "(seeds: " in res.stdout
            and "[train]" not in res.stdout)
    table = json.load(open(os.path.join(out, "table1.json")))
    assert table["10,1"]["model_dirs"] == first["models"]["ablation_seeds"]["10,1"]
    assert len(table["10,1"]["model_dirs"]) == 2  # the tiny budget's 2 seeds
    assert table["10,1"]["mace"] == pytest.approx(
        np.mean([_model_mace(d, samples) for d in table["10,1"]["model_dirs"]]), rel=1e-4)
    for row, dirs in first["models"]["ablation_seeds"].items():  # the rows left out: kept
        assert table[row]["model_dirs"] == dirs, row


def test_reuse_refuses_a_model_of_another_budget(tmp_path):
    """A reused stage-1 run (its config.json as training writes it, and a finished model.keras)
    is taken as it is at its own budget and refused at another one, before any training."""
    tiny = reproduce.BUDGETS["tiny"]
    data_dir = str(tmp_path / "data")
    stage1 = str(tmp_path / "stage1")
    run = reproduce.Reproduction(tiny, str(tmp_path / "same"), source="bundled",
                                 printer=lambda *a: None,
                                 reuse={"stage1": stage1, "data_stage1": data_dir})
    run_dir.prepare_model_dir(run.config("stage1", data_dir=run.stage1_data(), stage=1))
    with open(os.path.join(stage1, run_dir.FINAL_MODEL), "w") as f:
        f.write("a finished model")
    assert json.load(open(os.path.join(stage1, run_dir.CONFIG_FILE)))["train_steps"] == 2
    assert run.hierarchy(1) == [stage1]  # same budget: reused, not trained
    assert "train_stage1" not in run.timings
    other = dataclasses.replace(tiny, train_steps=4)
    run = reproduce.Reproduction(other, str(tmp_path / "other"), source="bundled",
                                 printer=lambda *a: None,
                                 reuse={"stage1": stage1, "data_stage1": data_dir})
    with pytest.raises(ValueError, match=r"different budget \{'train_steps': \(2, 4\)\}"):
        run.hierarchy(1)
    with pytest.raises(ValueError, match="unknown reuse"):
        reproduce.Reproduction(other, str(tmp_path), reuse={"stage9": stage1})


def test_paper_budget_uses_the_papers_image_counts():
    """Section 3 of the paper: 118,000 COCO 2014 trainval and 10,000 test images, 3 pairs each."""
    b = reproduce.BUDGETS["paper"]
    assert (b.max_images * b.samples_per_image, b.test_max_images * b.test_samples_per_image) == (
        354_000, 30_000)
    assert (b.train_steps, b.warmup_steps, b.batch_size) == (91_000, 1_000, 64)
    # Section 5: the sequence model's "total training steps of 90000"; other budgets: as stages.
    assert b.sequence_train_steps == 90_000
    assert reproduce.BUDGETS["cpu"].sequence_train_steps == reproduce.BUDGETS["cpu"].train_steps


@pytest.mark.slow
def test_homographynet_is_detones_network_with_its_schedule(tiny_run):
    out, result, _ = tiny_run
    cfg = json.load(open(os.path.join(result["models"]["homographynet"], run_dir.CONFIG_FILE)))
    assert (cfg["model"], cfg["batch_norm"], cfg["lr_schedule"], cfg["learning_rate"],
            cfg["warmup_steps"], cfg["train_steps"]) == (
        "homographynet", "conv", "step", 0.005, 0, reproduce.BUDGETS["tiny"].train_steps)


@pytest.mark.slow
def test_train_only_trains_that_part_and_stops(tiny_run, tmp_path):
    out, _, _ = tiny_run
    cmd = [sys.executable, "-m", "experiments.reproduce", "--budget=tiny", "--source=bundled",
           f"--output_dir={tmp_path}", f"--reuse=data_stage1={os.path.join(out, 'data', 'stage1')}"]
    res = subprocess.run(cmd + ["--train_only=homographynet"], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert os.listdir(tmp_path / "models") == ["homographynet"]
    assert os.path.exists(tmp_path / "models" / "homographynet" / run_dir.FINAL_MODEL)
    assert not os.path.exists(tmp_path / "tables.md")
    res = subprocess.run(cmd + ["--train_only=homographynet,stage7"], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    assert res.returncode != 0 and "['stage7']" in res.stderr


def test_tables_mark_rows_whose_predictions_were_rejected():
    """A hierarchy row whose stage predictions the degenerate rule rejected is marked and
    explained (its MACE is the identity's there, not the network's); a clean run has no note."""
    budget = dataclasses.asdict(reproduce.BUDGETS["tiny"])
    result = {"budget": budget, "test_pairs": 12,
              "fig4_mace": {"Identity": 23.53, "STN-Homography 1 stage": 23.53},
              "fig4_rejected": {"STN-Homography 1 stage": 12},
              "paper": {"fig4_mace": reproduce.PAPER_FIG4, "table1_mace": {},
                        "table2_gpu_ms": reproduce.PAPER_TABLE2_GPU_MS},
              "table1_mace_per_seed": {}, "models": {"stages": [], "homographynet": "h",
                                                     "sequence2": "s", "ablation_seeds": {}},
              "figures": {}}
    latency = {"hierarchy": {}, "policy": "float32"}
    text = reproduce.tables_markdown(result, latency)
    assert "| STN-Homography 1 stage (rejected: see below) | 23.53 |" in text
    assert "| Identity | 23.53 |" in text
    assert "Rejected predictions (the hierarchy's rule" in text
    assert "STN-Homography 1 stage: 12 stage predictions for 12 pairs" in text
    clean = reproduce.tables_markdown({**result, "fig4_rejected": {}}, latency)
    assert "rejected" not in clean


def test_tables_show_the_papers_schedule_from_its_card_on_the_same_test_pairs(tmp_path):
    """The "paper's schedule" column: the shipped card's MACEs under the tables' names, only when
    the card was evaluated on the tables' test pairs (same identity MACE)."""
    from stnh_tf.paper import tables

    card = {"stages": [{"file": "stage1.keras"}, {"file": "stage2.keras"}],
            "evaluation": {"identity": {"mace": 24.1636},
                           "model": {"mace": 2.5, "stages": {"after_1_stages": {"mace": 6.84},
                                                             "after_2_stages": {"mace": 2.5}}}}}
    (tmp_path / "model_card.json").write_text(json.dumps(card))
    got = tables.schedule_results(24.1636, str(tmp_path))
    assert got == {"fig4_mace": {"STN-Homography 1 stage": 6.84, "STN-Homography 2 stages": 2.5},
                   "table1_mace": {"1,1": 6.84}}
    assert tables.schedule_results(23.0, str(tmp_path)) == {"fig4_mace": {}, "table1_mace": {}}
    assert tables.schedule_results(24.1636, str(tmp_path / "none")) == {"fig4_mace": {},
                                                                         "table1_mace": {}}
    one = {"stages": [{"file": "stage1.keras"}],
           "evaluation": {"identity": {"mace": 24.1636}, "model": {"mace": 6.84}}}
    (tmp_path / "model_card.json").write_text(json.dumps(one))
    assert tables.schedule_results(24.1636, str(tmp_path))["fig4_mace"] == {
        "STN-Homography 1 stage": 6.84}
    card["stages"].append({"file": "stage3.keras"})  # 3 stages shipped, 2 evaluated
    (tmp_path / "model_card.json").write_text(json.dumps(card))
    with pytest.raises(ValueError, match="does not cover the 3 stages"):
        tables.schedule_results(24.1636, str(tmp_path))
    budget = dataclasses.asdict(reproduce.BUDGETS["tiny"])
    result = {"budget": budget, "test_pairs": 12,
              "fig4_mace": {"Identity": 24.16, "STN-Homography 1 stage": 18.32,
                            "STN-Homography 2 stages": 9.46},
              "paper": {"fig4_mace": reproduce.PAPER_FIG4, "table1_mace": {"1,1": 5.83},
                        "table2_gpu_ms": reproduce.PAPER_TABLE2_GPU_MS},
              "table1_mace_per_seed": {"1,1": [18.0, 18.5]}, "paper_schedule": got,
              "models": {"stages": [], "homographynet": "h", "sequence2": "s",
                         "ablation_seeds": {}}, "figures": {}}
    text = reproduce.tables_markdown(result, {"hierarchy": {}, "policy": "float32"})
    assert "| STN-Homography 1 stage | 18.32 | 6.84 | 5.83 |" in text
    assert "| STN-Homography 2 stages | 9.46 | 2.50 | 2.60 |" in text
    assert "| Identity | 24.16 |  |  |" in text
    assert "| 1 | 1 | 18.25 | 2 seeds: 18.00, 18.50 | 6.84 | 5.83 |" in text


# ------------------------------------------------------------------------------------------------
# Issue 62, item 1: verdicts, the identity row, rejected rows marked, one number per model, and
# the smoke run's size
# ------------------------------------------------------------------------------------------------
def test_fig4_hatches_and_notes_the_rows_whose_predictions_were_rejected():
    """The data Fig. 4 draws: a rejected row's bar hatched with its count (and "at the identity"
    where its MACE is the identity's), the others plain; the identity a dashed line."""
    from stnh_tf.paper import figures

    results = {"Identity": 23.53, "STN-Homography 1 stage": 294.92,
               "STN-Homography 2 stages": 23.53, "STN-Homography 3 stages": 20.0}
    bars = figures.fig4_bars(results, reproduce.PAPER_FIG4,
                             rejected={"STN-Homography 2 stages": 24,
                                       "STN-Homography 3 stages": 5},
                             predictions={"STN-Homography 2 stages": 24,
                                          "STN-Homography 3 stages": 36})
    assert [(b.name, b.value, b.hatched, b.note) for b in bars] == [
        ("Identity", 23.53, False, ""), ("STN-Homography 1 stage", 294.92, False, ""),
        ("STN-Homography 2 stages", 23.53, True, "rejected: 24 of 24\nat the identity"),
        ("STN-Homography 3 stages", 20.0, True, "rejected: 5 of 36")]
    assert [b.paper for b in bars] == [None, 5.83, 2.6, 1.57]
    fig = figures.mace_bars_figure(bars)
    try:
        ax = fig.axes[0]
        ours = [p for p in ax.patches if p.get_label() != "paper"][:4]
        assert [p.get_height() for p in ours] == pytest.approx([23.53, 294.92, 23.53, 20.0])
        assert [p.get_hatch() or "" for p in ours] == ["", "", "//", "//"]
        notes = [t.get_text() for t in ax.texts if t.get_text().startswith("rejected")]
        assert notes == ["rejected: 24 of 24\nat the identity", "rejected: 5 of 36"]
        dashed = [line for line in ax.lines if line.get_linestyle() == "--"]
        assert len(dashed) == 1 and dashed[0].get_ydata()[0] == pytest.approx(23.53)
    finally:
        import matplotlib.pyplot as plt

        plt.close(fig)


def _result(budget_name, per_seed, identity=24.16):
    budget = dataclasses.asdict(reproduce.BUDGETS[budget_name])
    return {"budget": budget, "test_pairs": 12,
            "fig4_mace": {"Identity": identity, "STN-Homography 1 stage": per_seed["1,1"][0]},
            "paper": {"fig4_mace": reproduce.PAPER_FIG4, "table1_mace": {"1,1": 5.83},
                      "table2_gpu_ms": reproduce.PAPER_TABLE2_GPU_MS},
            "table1_mace_per_seed": per_seed,
            "table1_claim": reproduce.table1_claim(per_seed, identity,
                                                   reproduce.BUDGETS[budget_name].verdicts),
            "models": {"stages": [], "homographynet": "h", "sequence2": "s",
                       "ablation_seeds": {}}, "figures": {}}


def test_table1_has_the_identity_row_and_a_verdict_only_where_the_budget_supports_one():
    """At the cpu budget the claim is judged from the seeds; at tiny, never (the same numbers);
    and not where a compared row is no better than the identity."""
    per_seed = {"1,1": [18.34, 18.30, 17.74], "10,1": [17.44, 16.12, 17.08], "1,10": [25.47]}
    latency = {"hierarchy": {"1": {"d_e_ms": 3.78, "formula_ms": 3.85}}, "policy": "float32",
               "l_m_ms": 3.1, "l_w_ms": 0.75}
    cpu = reproduce.tables_markdown(_result("cpu", per_seed), latency)
    assert "| identity (no model) |  | 24.16 |  |  |  |" in cpu
    assert ("The paper's claim (L2:L1 = 10:1 gives a lower MACE than 1:1): holds at this budget: "
            "every seed of 10:1 (16.12-17.44 px) is below every seed of 1:1 (17.74-18.34 px)."
            ) in cpu
    assert "| 1 | 1 | 18.13 | 3 seeds: 18.34, 18.30, 17.74 |" in cpu
    tiny = reproduce.tables_markdown(_result("tiny", per_seed), latency)
    assert "| identity (no model) |  | 24.16 |  |  |  |" in tiny
    # the hour budget's deviation is stated under the title; no other budget has one
    assert "gradient norm clipped" not in cpu and "gradient norm clipped" not in tiny
    hour = _result("cpu", per_seed)
    hour["budget"] = {**hour["budget"], "sequence_clipnorm": 10.0}
    assert ("The sequence model's global gradient norm clipped at 10 (not the paper's recipe: "
            'docs/reproduce.md, "The hour budget").') in reproduce.tables_markdown(hour, latency)
    assert "no verdict at this budget" in tiny and "holds" not in tiny
    assert reproduce.BUDGETS["tiny"].verdicts is False and reproduce.BUDGETS["cpu"].verdicts
    above = reproduce.table1_claim({"1,1": [294.9, 280.1], "10,1": [250.0, 260.0]}, 23.53)
    assert above["verdict"] == "none" and "not below the identity's 23.53 px" in above["text"]
    overlap = reproduce.table1_claim({"1,1": [5.0, 6.0], "10,1": [5.5, 5.6]}, 23.53)
    assert overlap["verdict"] == "unresolved"
    worse = reproduce.table1_claim({"1,1": [5.0, 5.1], "10,1": [5.5, 5.6]}, 23.53)
    assert worse["verdict"] == "does not hold"
    # Table 2's caption says what the formula column is, with this run's l_m and l_w.
    assert "d_e = (l_m + l_w) n" in cpu and "l_m = 3.10 ms, l_w = 0.75 ms" in cpu
    # Fig. 4's caption says which quantity its 1-stage row is.
    assert "STN-Homography 1 stage is the stage-1 network's own estimate" in cpu


def test_tiny_drops_homographynet_after_its_evaluation_and_never_retrains_it(tmp_path):
    """tiny: HomographyNet's model.keras goes once evaluated (its config, result and evaluation
    stay) and the next run counts it as finished; a reused model and other budgets keep theirs."""
    tiny = reproduce.BUDGETS["tiny"]
    logs = []
    run = reproduce.Reproduction(tiny, str(tmp_path / "out"), source="bundled",
                                 printer=logs.append)
    cfg = run.config("homographynet", data_dir=str(tmp_path / "data"), model="homographynet",
                     **{**presets.MODEL_DEFAULTS["homographynet"],
                        "train_steps": tiny.train_steps})
    run_dir.prepare_model_dir(cfg)
    d = cfg.model_dir
    for name in (run_dir.FINAL_MODEL, run_dir.RESULT_FILE):
        with open(os.path.join(d, name), "w") as f:
            f.write("{}")
    os.makedirs(os.path.join(d, run_dir.CHECKPOINT_DIR))
    assert not run.dropped("homographynet")  # not evaluated yet
    with open(os.path.join(run.out, "eval", "homographynet.json"), "w") as f:
        json.dump({"model": {"mace": 300.0}}, f)
    run.drop_model("homographynet")
    left = set(os.listdir(d))
    assert {run_dir.CONFIG_FILE, run_dir.RESULT_FILE} <= left
    assert not left & {run_dir.FINAL_MODEL, run_dir.CHECKPOINT_DIR}
    assert logs and logs[-1].startswith("[drop] homographynet")
    assert run.dropped("homographynet")
    assert run.train("homographynet", cfg) == d and "train_homographynet" not in run.timings
    # The cached evaluation stands for the model that is gone.
    assert run.evaluate("homographynet", [d]) == {"model": {"mace": 300.0}}
    # Another budget, or a reused model: nothing is removed.
    for budget, reuse in ((reproduce.BUDGETS["cpu"], {}), (tiny, {"homographynet": d})):
        with open(os.path.join(d, run_dir.FINAL_MODEL), "w") as f:
            f.write("{}")
        other = reproduce.Reproduction(budget, str(tmp_path / "other"), printer=logs.append,
                                       reuse=reuse)
        other.drop_model("homographynet")
        assert os.path.exists(os.path.join(d, run_dir.FINAL_MODEL))


@pytest.mark.slow
def test_one_number_per_model_no_verdict_and_a_small_smoke_run(tiny_run):
    """Fig. 4's stage-1 bar is Table 1's 1:1 seed 0 (the same evaluation); no verdict at tiny;
    the output keeps no checkpoints nor the HomographyNet file and stays under 100 MB."""
    out, result, _ = tiny_run
    assert result["fig4_mace"]["STN-Homography 1 stage"] == result["table1_mace_per_seed"]["1,1"][0]
    assert "STN-Homography 1 stage" not in result["fig4_rejected"]
    assert result["table1_claim"]["verdict"] == "none"
    tables = open(os.path.join(out, "tables.md")).read()
    assert "no verdict at this budget" in tables and "| identity (no model) |" in tables
    assert "no verdict at this budget" in open(os.path.join(out, "table1.md")).read()
    for name in result["fig4_rejected"]:
        assert 0 < result["fig4_rejected"][name] <= result["fig4_rejected_of"][name]
    models = os.path.join(out, "models")
    assert not [m for m in os.listdir(models)
                if os.path.exists(os.path.join(models, m, run_dir.CHECKPOINT_DIR))]
    assert not os.path.exists(os.path.join(result["models"]["homographynet"], run_dir.FINAL_MODEL))
    assert os.path.exists(os.path.join(result["models"]["stages"][0], run_dir.FINAL_MODEL))
    size = sum(os.path.getsize(os.path.join(root, f)) for root, _, files in os.walk(out)
               for f in files)
    assert size < 100e6, size


def _run_folder(path, result):
    os.makedirs(path)
    if result is not None:
        with open(os.path.join(path, run_dir.RESULT_FILE), "w") as f:
            f.write(result if isinstance(result, str) else json.dumps(result))
    return str(path)


def test_model_provenance_reads_each_run_folders_own_record(tmp_path):
    """results.json's model_provenance: steps, wall time, commit, machine and backend as each run
    folder's result.json records them; "not recorded" only for what a folder lacks (no
    result.json, an unreadable one, one written before it held the machine); the run is
    assembled exactly where a model was reused."""
    from stnh_tf.paper.model_provenance import assembled_line, provenance_block

    machine = {"git_commit": "abc1234+dirty", "cpu": "Intel(R) Xeon(R) Processor", "cpu_count": 2,
               "gpus": [], "jax_devices": ["cpu", "NVIDIA H100 80GB HBM3"],
               "keras_backend": "jax"}
    runs = {"stage1": _run_folder(tmp_path / "s1", {"final_step": 40, "wall_s_this_run": 12.345,
                                                    "machine": machine, "history": {}}),
            "stage2": _run_folder(tmp_path / "s2", {"final_step": 7, "wall_s_this_run": 3.0}),
            "sequence2": _run_folder(tmp_path / "seq", None),
            "homographynet": _run_folder(tmp_path / "h", "{not json")}
    block = provenance_block(runs, reused={"stage2": "elsewhere"})
    prov = block["model_provenance"]
    assert prov["stage1"] == {"run": runs["stage1"], "steps": 40, "wall_s": 12.3,
                              "commit": "abc1234+dirty",
                              "machine": {"cpu": "Intel(R) Xeon(R) Processor", "cores": 2,
                                          "accelerators": ["NVIDIA H100 80GB HBM3"]},
                              "backend": "jax", "reused": False}
    assert prov["stage2"] == {"run": runs["stage2"], "steps": 7, "wall_s": 3.0,
                              "commit": "not recorded", "machine": "not recorded",
                              "backend": "not recorded", "reused": True}
    for name in ("sequence2", "homographynet"):
        assert {k: v for k, v in prov[name].items() if k != "run"} == {
            "steps": "not recorded", "wall_s": "not recorded", "commit": "not recorded",
            "machine": "not recorded", "backend": "not recorded", "reused": False}
    assert block["assembled"] is True
    assert "**Assembled**: 1 of 4 models were trained elsewhere and reused (stage2)" in (
        assembled_line(block))
    # Only the folders asked for (Table 1's rows), and a run reusing nothing is not assembled.
    kept = provenance_block(runs, reused={"stage2"}, only={runs["stage1"]})
    assert set(kept["model_provenance"]) == {"stage1"} and kept["assembled"] is False
    assert assembled_line(kept).startswith("Every model was trained by this reproduction")


def test_current_results_cells_of_an_assembled_reproduction():
    """The commit cell spans the models' reconstructed commits by date (not by the order given);
    the machine cell lists each machine once, accelerators in place of the CPU; Table 2's
    measurement adds its own span; a JSON without model_provenance keeps recorded()."""
    from stnh_tf.paper import result_cells

    def entry(after, a_date, rec, r_date, machine, backend):
        return {"trained_after": {"commit": after, "date": a_date},
                "recorded_in": {"commit": rec, "date": r_date}, "machine": machine,
                "backend": backend}

    cpu = {"cpu": "Xeon", "cores": 2, "accelerators": []}
    gpu = {"cpu": "not recorded", "cores": 16, "accelerators": ["H100"]}
    prov = {"late": entry("ccc", "2026-11-25T00:00:00Z", "ddd", "2026-11-25T04:00:00Z", cpu,
                          "tensorflow"),
            "early": entry("aaa", "2026-11-23T03:00:00Z", "bbb", "2026-11-23T04:00:00Z", gpu,
                           "jax"),
            "same": entry("aaa", "2026-11-23T03:00:00Z", "bbb", "2026-11-23T04:00:00Z", cpu,
                          "tensorflow")}
    sources = {"results": {"assembled": True, "model_provenance": prov,
                           "latency": entry("eee", "2026-11-23T05:00:00Z", "fff",
                                            "2026-11-23T06:00:00Z", cpu, "tensorflow")},
               "old": {}}
    assert result_cells.provenance_cells(sources, "results") == (
        "assembled: trained between aaa and ddd",
        "Xeon, 2 cores (tensorflow); H100 (jax)")
    assert result_cells.provenance_cells(sources, "results", ["early"], "latency") == (
        "assembled: trained between aaa and bbb; measured between eee and fff",
        "H100 (jax); Xeon, 2 cores (tensorflow)")
    # a model the reproduction did not train (a fresh one has no homographynet_gap) is left out
    assert (result_cells.provenance_cells(sources, "results", ["early", "missing"])
            == result_cells.provenance_cells(sources, "results", ["early"]))
    assert result_cells.provenance_cells(sources, "results", ["missing"]) == (
        "not recorded", "not recorded")
    assert result_cells.provenance_cells(sources, "old") == ("not recorded", "not recorded")


def test_committed_reproduction_provenance_matches_git_history():
    """The committed reproduction (its run folders gone) carries a model_provenance reconstructed
    from git and BENCHMARKS.md for every model its models block names, marked assembled; each
    span's commits exist with the dates recorded, the training's start before its record; and
    Fig. 4, Table 1 and Table 2's current-results rows show no "not recorded" commit or machine.
    Table 2's latency_provenance is reconstructed too, or, once measured again
    (``experiments.reproduce --refresh_latency``), names a commit of this history and the load."""
    from stnh_tf.paper import current_results as cr

    sources = cr.load_sources(ROOT)
    results, table1 = sources["results"], sources["table1"]
    models = results["models"]
    dirs = {*models["stages"], models["homographynet"], models["homographynet_gap"],
            models["sequence2"], *(d for v in models["ablation_seeds"].values() for d in v)}
    assert {e["run"] for e in results["model_provenance"].values()} == dirs
    t1_dirs = {d for key, _ in cr.TABLE1_ROWS for d in table1[key]["model_dirs"]}
    assert {e["run"] for e in table1["model_provenance"].values()} == t1_dirs
    for doc in (results, table1):
        assert doc["assembled"] is True and "run folders are gone" in doc["reconstructed_from"]
    latency = results["latency_provenance"]
    refreshed = "trained_after" not in latency
    if refreshed:  # measured by --refresh_latency: its commit (from a clean checkout) is here
        assert latency["loadavg_at_start"] and latency["loadavg_at_end"]
        commit = latency["commit"].removesuffix("+dirty")
        found = subprocess.run(["git", "cat-file", "-e", f"{commit}^{{commit}}"], cwd=ROOT,
                               capture_output=True)
        if found.returncode != 0:
            pytest.skip(f"commit {latency['commit']} is not in this checkout (a shallow clone)")
    entries = [*results["model_provenance"].values(), *([] if refreshed else [latency]),
               *table1["model_provenance"].values()]
    for e in entries:
        for key in ("trained_after", "recorded_in"):
            commit, date = e[key]["commit"], e[key]["date"]
            found = subprocess.run(["git", "show", "-s", "--format=%aI", commit], cwd=ROOT,
                                   capture_output=True, text=True)
            if found.returncode != 0:
                pytest.skip(f"commit {commit} is not in this checkout (a shallow clone)")
            assert found.stdout.strip().replace("+00:00", "Z") == date, (commit, date)
        assert e["trained_after"]["date"] < e["recorded_in"]["date"]
        assert e["commit"] == (f"between {e['trained_after']['commit']} and "
                               f"{e['recorded_in']['commit']}")
    rows = [r for r in cr.benchmarks_rows(sources) if r[0].startswith("Reproduction")]
    assert len(rows) == 3
    for row in rows:
        measured_again = refreshed and row[0].startswith("Reproduction, Table 2")
        assert row[4].startswith("measured at " if measured_again
                                 else "assembled: trained between ")
        assert all("not recorded" not in cell for cell in row[4:]), row


def test_model_provenance_reads_the_file_training_writes():
    """model_provenance names result.json itself (to stay free of NumPy): the run folder's."""
    from stnh_tf.paper import model_provenance
    from stnh_tf.training import run_dir

    assert model_provenance.RESULT_FILE == run_dir.RESULT_FILE
