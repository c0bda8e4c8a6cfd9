"""A hostile review of the reproduction flows (issue 79's fourth round): each test fails on the
code before it.

Data loss: ``semi_supervised --repo_dir`` of another budget had its committed evaluations and
models replaced by a smoke test's; a re-run of ``reproduce`` dropped ``--refresh_latency``'s
provenance and the rows ``loss_weight_ablation`` had added to Table 1; ``loss_weight_ablation
--steps=N`` replaced the budget's Table 1 by a table of other steps. Silently wrong: the
evaluation cache was kept for another model older than it (``--reuse``, ``cp -p``) or other test
pairs; an evaluation restored from a repository of other pairs was shown as this run's; a kept
Table 1 row lost its provenance."""

from __future__ import annotations

import json
import os

import pytest

from stnh_tf.paper import eval_cache, model_provenance, reproduce, semi_supervised, table2
from stnh_tf.training import run_dir

QUIET = lambda *a, **k: None  # noqa: E731


def _model(folder, text="a model", steps=2, result=None):
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, run_dir.FINAL_MODEL), "w") as f:
        f.write(text)
    with open(os.path.join(folder, run_dir.CONFIG_FILE), "w") as f:
        json.dump({"train_steps": steps}, f)
    if result is not None:
        with open(os.path.join(folder, run_dir.RESULT_FILE), "w") as f:
            json.dump(result, f)
    return str(folder)


def test_the_evaluation_cache_follows_the_models_and_pairs(tmp_path):
    a, b = _model(tmp_path / "a", "model a"), _model(tmp_path / "b", "model b")
    path = str(tmp_path / "eval.json")
    key = eval_cache.key([a], "pairs-1")
    with open(path, "w") as f:
        json.dump({"model": {"mace": 3.0}, eval_cache.CACHE_KEY: key}, f)
    assert eval_cache.cached(path, key, [a])["model"]["mace"] == 3.0
    # another model whose file is older than the evaluation (a --reuse, a cp -p): not the same
    os.utime(os.path.join(b, run_dir.FINAL_MODEL), (0, 0))
    assert eval_cache.cached(path, eval_cache.key([b], "pairs-1"), [b]) is None
    assert eval_cache.cached(path, eval_cache.key([a], "pairs-2"), [a]) is None  # other pairs
    os.remove(os.path.join(a, run_dir.FINAL_MODEL))  # removed once evaluated: kept
    assert eval_cache.cached(path, eval_cache.key([a], "pairs-1"), [a]) is not None
    with open(path, "w") as f:  # written before the record: the mtime rule of then
        json.dump({"model": {"mace": 4.0}}, f)
    assert eval_cache.cached(path, eval_cache.key([b], "pairs-1"), [b])["model"]["mace"] == 4.0


def test_a_refreshed_latency_keeps_its_provenance_in_results():
    latency = {"hierarchy": {"1": {"d_e_ms": 4.5}}, "sequence": {"1": {"forward_ms": 4.0}},
               "provenance": {"commit": "abc", "machine": {"cpu": "x"}}}
    fields = table2.results_fields(latency)
    assert fields["latency_provenance"] == latency["provenance"]
    assert "latency_provenance" not in table2.results_fields(
        {k: v for k, v in latency.items() if k != "provenance"})


@pytest.fixture()
def tiny(tmp_path):
    return reproduce.Reproduction(reproduce.BUDGETS["tiny"], str(tmp_path / "out"),
                                  source="bundled", printer=QUIET)


def test_table1_keeps_rows_writes_other_steps_beside_and_records_every_rows_provenance(
        tiny, tmp_path, monkeypatch):
    import dataclasses

    def fake_evaluate(key, model_dirs=(), baselines=()):
        return {"model": {"mace": float(len(key))}, "identity": {"mace": 24.0}}

    monkeypatch.setattr(tiny, "evaluate", fake_evaluate)
    steps = tiny.budget.ablation_train_steps
    models = os.path.join(tiny.out, "models")
    elsewhere = _model(tmp_path / "elsewhere" / "ablation_l2-10_l1-1", steps=steps,
                       result={"final_step": steps, "machine": {"git_commit": "c0ffee"}})
    rows = {(1.0, 1.0): [_model(os.path.join(models, "stage1"), steps=steps)],
            (10.0, 1.0): [elsewhere]}
    tiny.table1(rows)
    # a later run of one row keeps the other, and the kept row keeps its provenance (reused)
    tiny.table1({(1.0, 1.0): rows[(1.0, 1.0)]})
    table = json.load(open(os.path.join(tiny.out, "table1.json")))
    assert table["10,1"]["model_dirs"] == [elsewhere]
    assert table["model_provenance"]["ablation_l2-10_l1-1"]["reused"] is True
    assert table["model_provenance"]["ablation_l2-10_l1-1"]["commit"] == "c0ffee"
    assert table["assembled"] is True
    # --steps=N: its table is written beside the budget's, which stays
    before = open(os.path.join(tiny.out, "table1.json")).read()
    tiny.budget = dataclasses.replace(tiny.budget, ablation_steps=steps + 5)
    other = _model(tmp_path / "o" / "ablation_l2-3_l1-1", steps=steps + 5)
    tiny.table1({(3.0, 1.0): [other]})
    assert open(os.path.join(tiny.out, "table1.json")).read() == before
    beside = json.load(open(os.path.join(tiny.out, f"table1_steps{steps + 5}.json")))
    assert [k for k in beside if "," in k] == ["3,1"]
    assert os.path.exists(os.path.join(tiny.out, f"table1_steps{steps + 5}.md"))


def test_a_reused_model_appears_once_in_table1s_provenance(tiny, tmp_path, monkeypatch):
    """A model given by ``--reuse=stage1=DIR`` whose folder is not named ``stage1`` was listed
    twice in Table 1's provenance (under its name and its folder's), "2 of 2 models reused"."""
    monkeypatch.setattr(tiny, "evaluate", lambda key, model_dirs=(), baselines=(): {
        "model": {"mace": 5.0}, "identity": {"mace": 24.0}})
    steps = tiny.budget.ablation_train_steps
    reused = _model(tmp_path / "elsewhere" / "my_first_stage", steps=steps)
    own = _model(os.path.join(tiny.out, "models", "ablation_l2-10_l1-1"), steps=steps)
    tiny.reuse, tiny.models = {"stage1": reused}, {"stage1": reused}
    tiny.table1({(1.0, 1.0): [reused], (10.0, 1.0): [own]})
    table = json.load(open(os.path.join(tiny.out, "table1.json")))
    assert sorted(table["model_provenance"]) == ["ablation_l2-10_l1-1", "stage1"]
    assert table["model_provenance"]["stage1"]["reused"] is True
    assert table["model_provenance"]["ablation_l2-10_l1-1"]["reused"] is False
    assert "1 of 2 models were trained elsewhere" in model_provenance.assembled_line(table)


def test_a_repository_of_another_budget_is_refused_before_anything_is_copied(tiny, tmp_path):
    experiment = semi_supervised.SemiSupervised(tiny)
    repo = tmp_path / "repo"
    (repo / "eval").mkdir(parents=True)
    cpu_config = reproduce.Reproduction(reproduce.BUDGETS["cpu"], str(tmp_path / "cpu"),
                                        source="bundled", printer=QUIET).config(
        "stage1", data_dir="d").to_json()
    (repo / "stage1.json").write_text(json.dumps(cpu_config))
    (repo / "stage1.keras").write_text("the committed model")
    (repo / "eval" / "stage1_alone.json").write_text('{"count": 300}')
    before = {p: p.read_bytes() for p in repo.rglob("*") if p.is_file()}
    _model(tiny.model_dir("stage1"), steps=tiny.budget.train_steps)
    os.makedirs(os.path.join(tiny.out, "eval"), exist_ok=True)
    with open(os.path.join(tiny.out, "eval", "stage1_alone.json"), "w") as f:
        f.write('{"count": 12}')
    for step in (experiment.save, experiment.restore):
        with pytest.raises(ValueError, match="trained with another budget .*train_steps"):
            step(str(repo))
        assert {p: p.read_bytes() for p in repo.rglob("*") if p.is_file()} == before
