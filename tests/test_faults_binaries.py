"""A hostile read of the command-line binaries (2026-12-07), kept as tests: ``evaluate
--json_out`` and ``plot_hbar_histogram --output`` replaced another dataset's ``metadata.json`` or
a run's ``config.json``; ``loss_weight_ablation --weights=`` rewrote Table 1 as an empty
table; a row's bad loss weights, ``semi_supervised``'s bad speed flags
and ``--close_px=nan`` were found after minutes of data making and training, or never.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from stnh_tf import paths
from stnh_tf.data import stage1
from stnh_tf.evaluation import summaries

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _run(*args):
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("data"))
    stage1.make_dataset("bundled", out, "test", seed=1, max_images=2, samples_per_image=1,
                        num_shards=1, num_workers=1, log=lambda *_: None)
    return out


def test_an_output_never_replaces_a_record_the_project_keeps(dataset, tmp_path):
    """``evaluate --json_out=D/metadata.json`` (another dataset's) wrote its result there and
    the dataset could no longer be read; a run's ``config.json`` went the same way. Every
    ``--json_out`` (``summaries.check_json_out``) refuses a file whose ``format`` is one of
    this project's records, a shard or a model, before the work; a result JSON of its own, or a
    new file, stays writable."""
    from stnh_tf.training import run_dir
    from stnh_tf.training.config import TrainConfig

    metadata = os.path.join(dataset, "metadata.json")
    run_dir.prepare_model_dir(TrainConfig(model_dir=str(tmp_path / "run"), data_dir=dataset))
    config = str(tmp_path / "run" / "config.json")
    before = {p: open(p, "rb").read() for p in (metadata, config)}
    for path, kind in ((metadata, "stnh_tf.dataset"), (config, "stnh_tf.train_config")):
        with pytest.raises(FileExistsError, match=f"is a {kind} record, which this output "
                                                  "would replace"):
            summaries.check_json_out(path)
    shard = next(os.path.join(dataset, n) for n in os.listdir(dataset) if n.endswith(".tfrecord"))
    with pytest.raises(FileExistsError, match="a shard or model file"):
        summaries.check_json_out(shard)
    assert {p: open(p, "rb").read() for p in before} == before
    result = tmp_path / "result.json"
    summaries.write_json_out({"count": 2, "identity": {"mace": 1.0}}, str(result), "evaluate")
    summaries.check_json_out(str(result), "evaluate")  # its own: written over on a re-run
    assert paths.project_record(str(result)) is None
    summaries.check_json_out(str(tmp_path / "new" / "result.json"))


def test_an_output_never_replaces_a_model_card_a_ledger_or_a_document(tmp_path):
    """``benchmark_camera_pairs --json_out=stnh_tf/weights/model_card.json`` (no ``--model``:
    the stage files were the only inputs checked) replaced the shipped weights' card with a
    benchmark result, and the paper schedule's ``ledger.json`` (a list) or ``README.md`` went
    the same way: a card and a ledger are records now, and a file that is not JSON is not an
    earlier result. The package's own card and ledger are refused as they are; an empty file
    stays writable, a JSON file the binary did not write does not (``written_by``)."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    card = os.path.join(root, "stnh_tf", "weights", "model_card.json")
    ledger = os.path.join(root, "paper_schedule", "ledger.json")
    for path, what in ((card, "a model card"), (ledger, "a ledger of training chunks"),
                       (os.path.join(root, "README.md"), "exists and is not JSON")):
        before = open(path, "rb").read()
        with pytest.raises(FileExistsError, match=what):
            summaries.check_json_out(path)
        assert open(path, "rb").read() == before
    for blank in (b"", b"\n"):
        (tmp_path / "empty.json").write_bytes(blank)
        summaries.check_json_out(str(tmp_path / "empty.json"))
    (tmp_path / "rows.json").write_text(json.dumps([{"mace": 1.0}]))  # not a result of its own
    with pytest.raises(FileExistsError, match="not an earlier result of evaluate"):
        summaries.check_json_out(str(tmp_path / "rows.json"), "evaluate")


@pytest.mark.slow
def test_the_binaries_refuse_at_once(dataset, tmp_path):
    """Each refused in one line before any data is made or model trained: make_dataset's
    ``--image_dir`` with another source (ignored before); a ``--reuse`` of a
    folder that does not exist (a model was trained there instead); an empty ``--weights``; a row with a negative loss weight (it trained the rows before it first);
    ``semi_supervised --close_px=nan`` (accepted: no row ever counted as close) and
    ``--steps_per_execution=0`` (refused after the data); ``plot_hbar_histogram`` whose
    statistics JSON would replace a dataset's ``metadata.json``, and a ``--bins=0``."""
    common = ["--budget=tiny", "--source=bundled"]
    cases = [
        (["experiments.loss_weight_ablation", "--weights=", *common,
          f"--output_dir={tmp_path / 'a'}"], "--weights entries are l2:l1, one or more"),
        (["experiments.loss_weight_ablation", "--weights=1:1,-1:1", *common,
          f"--output_dir={tmp_path / 'b'}"], "l2_weight must be a finite number >= 0"),
        (["experiments.semi_supervised", "--close_px=nan", *common,
          f"--output_dir={tmp_path / 'c'}"], "--close_px must be a finite number"),
        (["experiments.semi_supervised", "--steps_per_execution=0", *common,
          f"--output_dir={tmp_path / 'd'}"], "steps_per_execution must be an integer >= 1"),
        (["experiments.reproduce", "--train_only=homographynet", *common,
          f"--reuse=homographynet={tmp_path / 'typo'}", f"--output_dir={tmp_path / 'e'}"],
         "does not exist; --reuse names finished models and datasets"),
        # --budget=hour: refused before its timed probe (minutes of training), not after it
        (["experiments.reproduce", "--budget=hour", "--source=bundled",
          f"--reuse=homographynet={tmp_path / 'typo'}", f"--output_dir={tmp_path / 'g'}"],
         "does not exist; --reuse names finished models and datasets"),
        (["experiments.reproduce", "--budget=hour", "--source=bundled", "--train_only=stage9",
          f"--output_dir={tmp_path / 'i'}"], "--train_only names must be among"),
        # a repeated row (counted as more seeds of it); an empty folder as a finished model
        # (a model was trained in it, recorded as reused)
        (["experiments.loss_weight_ablation", "--weights=10:1,10:1.0", *common,
          f"--output_dir={tmp_path / 'j'}"], "more than once"),
        (["experiments.loss_weight_ablation", "--weights=0.1:1", *common,
          f"--reuse=ablation_l2-0.1_l1-1={tmp_path}", f"--output_dir={tmp_path / 'k'}"],
         "holds no model.keras or result.json: not a finished model"),
    ]
    for args, message in cases:
        proc = _run(*args)
        assert proc.returncode != 0 and message in proc.stderr, (args, proc.stderr[-2000:])
        assert "Traceback" not in proc.stderr and "[plan]" not in proc.stdout
        out = [a.split("=", 1)[1] for a in args if a.startswith("--output_dir=")][0]
        assert not os.path.exists(os.path.join(out, "data")), args
        assert not os.path.exists(os.path.join(out, "models")), args
    assert not (tmp_path / "typo").exists()  # no model trained in a mistyped --reuse folder
    proc = _run("data_prep.make_dataset", "--source=bundled", f"--image_dir={tmp_path}",
                f"--output_dir={tmp_path / 'f'}")  # --image_dir was ignored, exit 0
    assert proc.returncode != 0 and "--image_dir is for --source=folder" in proc.stderr
    assert not (tmp_path / "f").exists()
    other = tmp_path / "other"
    stage1.make_dataset("bundled", str(other), "test", seed=2, max_images=1,
                        samples_per_image=1, num_shards=1, num_workers=1, log=lambda *_: None)
    before = (other / "metadata.json").read_bytes()
    proc = _run("experiments.plot_hbar_histogram", f"--data_dir={dataset}", "--split=test",
                f"--output={other / 'metadata.png'}")
    assert proc.returncode != 0 and "stnh_tf.dataset record" in proc.stderr, proc.stderr[-2000:]
    assert (other / "metadata.json").read_bytes() == before
    assert not (other / "metadata.png").exists()
    log = tmp_path / "stage1_0-1000_cpu.log"
    log.write_text("I1207 callbacks.py:83] step 500/1000 lr=0.05 h_bar_mace=9.0 (1 steps/s)\n")
    before = log.read_bytes()
    proc = _run("experiments.plot_learning_curves", f"--logs={tmp_path / '*.log'}",
                f"--output={tmp_path / 'c.png'}", f"--json_out={log}")
    assert proc.returncode != 0 and "--json_out" in proc.stderr, proc.stderr[-2000:]
    assert log.read_bytes() == before  # (was: replaced by the curve's JSON)
    proc = _run("experiments.plot_hbar_histogram", f"--data_dir={dataset}", "--split=test",
                f"--output={tmp_path / 'h.png'}", "--bins=0")
    assert proc.returncode != 0 and "bins" in proc.stderr and "Traceback" not in proc.stderr


def test_the_demo_refuses_test_pairs_of_another_seed(tmp_path):
    """``demo --seed=7 --samples_per_image=5`` into a folder holding seed 0's test pairs used
    them and reported seed 7: refused now, naming both; the same seed and count reuse them."""
    from stnh_tf.paper import demo

    made = tmp_path / "bundled_test"
    stage1.make_dataset("bundled", str(made), "test", seed=0, max_images=2, samples_per_image=1,
                        num_shards=1, num_workers=1, log=lambda *_: None)
    with pytest.raises(ValueError, match="holds test pairs of seed 0 and 1 a photograph; this "
                                         "demo asks for seed 7 and 5"):
        demo.run_demo(str(tmp_path), 7, 5, 0, printer=lambda *_: None)


def test_a_reproduction_refuses_its_stage1_pairs_made_under_other_flags(tmp_path):
    """``reproduce`` (and ``loss_weight_ablation``, ``semi_supervised``) reused the stage-1 pairs
    of an earlier run in its ``--output_dir`` whatever the flags: the first 2 photographs'
    pairs went on being used under ``max_images=3`` and reported as such. Refused now, naming
    the differences; the same flags reuse them; a dataset named by ``--reuse`` stays the
    user's."""
    import dataclasses

    from stnh_tf.paper import reproduce

    tiny = reproduce.BUDGETS["tiny"]
    two = dataclasses.replace(tiny, max_images=2, test_max_images=2)
    out = str(tmp_path / "run")
    quiet = dict(source="bundled", printer=lambda *_: None)
    made = reproduce.Reproduction(two, out, **quiet).stage1_data()
    assert reproduce.Reproduction(two, out, **quiet).stage1_data() == made
    three = dataclasses.replace(two, max_images=3)
    with pytest.raises(ValueError, match=r"holds the stage-1 train pairs of other flags "
                                         r"\{'max_images': \(2, 3\)\}"):
        reproduce.Reproduction(three, out, **quiet).stage1_data()
    reused = reproduce.Reproduction(three, str(tmp_path / "other"),
                                    reuse={"data_stage1": made}, **quiet)
    assert reused.stage1_data() == made


def test_a_run_of_some_table1_rows_keeps_the_others(tmp_path):
    """``loss_weight_ablation --weights=10:1`` wrote ``table1.json`` with that row alone: the
    earlier table's other rows were dropped although their models were still there. The rows it
    keeps are those whose models are all finished and trained as many steps; others (a model
    gone, trained at another ``--steps``, an unreadable config) are left out."""
    from stnh_tf.paper import tables
    from stnh_tf.training import run_dir

    def model(name, steps, final=True, config=None):
        d = tmp_path / "models" / name
        d.mkdir(parents=True)
        (d / run_dir.CONFIG_FILE).write_text(config or json.dumps({"train_steps": steps}))
        if final:
            (d / run_dir.FINAL_MODEL).write_text("a finished model")
        return str(d)

    rows = {"1,1": [model("stage1", 40)], "1,10": [model("a", 40), model("b", 40)],
            "1,0.1": [model("c", 40), model("d", 40, final=False)],  # a seed unfinished
            "0.1,1": [model("e", 60)],  # another --steps
            "2,1": [model("f", 40, config="{")]}
    earlier = {k: {"mace": 5.0, "model_dirs": v} for k, v in rows.items()}
    table = tmp_path / "table1.json"
    table.write_text(json.dumps({**earlier, "10,1": {"model_dirs": ["x"]},
                                 "model_provenance": {}, "assembled": False}))
    kept = tables.earlier_table1_rows(str(table), {(10.0, 1.0): ["new"]}, 40)
    assert kept == {(1.0, 1.0): rows["1,1"], (1.0, 10.0): rows["1,10"]}
    assert tables.earlier_table1_rows(str(table), {(1.0, 1.0): ["new"]}, 40) == {
        (1.0, 10.0): rows["1,10"]}  # a row run again is the new one
    assert tables.earlier_table1_rows(str(tmp_path / "none.json"), {}, 40) == {}
    table.write_text("[1, 2]")
    with pytest.raises(ValueError, match="not a Table 1 written by this project"):
        tables.earlier_table1_rows(str(table), {}, 40)
