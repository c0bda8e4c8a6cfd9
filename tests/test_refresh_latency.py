"""``experiments.reproduce --refresh_latency`` (:mod:`stnh_tf.paper.table2`): Table 2 of an
existing reproduction measured again and written back with its provenance (issue 78, item 6), on
a copy of the committed ``docs/reproduce_cpu`` at 2 timed runs; and the current-results cells
that name the machine and the load it records."""

import json
import os
import re
import shutil
import subprocess
import sys

import pytest

from stnh_tf import provenance
from stnh_tf.paper import current_results as cr
from stnh_tf.paper import result_cells, table2

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
COMMITTED = os.path.join(ROOT, "docs", "reproduce_cpu")


def _copy(tmp_path, runs=2, warmup=1):
    """A copy of the committed reproduction's results.json and tables.md in ``tmp_path``, its
    budget's latency runs set to ``runs`` and ``warmup`` (the file's layout kept); its text."""
    with open(os.path.join(COMMITTED, "results.json")) as f:
        text = f.read()
    result = json.loads(text)
    assert json.dumps(result, indent=2) == text  # (the layout a rewrite keeps)
    result["budget"].update(latency_runs=runs, latency_warmup=warmup)
    text = json.dumps(result, indent=2)
    (tmp_path / "results.json").write_text(text)
    shutil.copy(os.path.join(COMMITTED, "tables.md"), tmp_path / "tables.md")
    return text


@pytest.mark.slow  # (4 s: the latency binary; make test-all)
def test_refresh_writes_what_the_latency_function_measured_and_nothing_else(tmp_path,
                                                                             monkeypatch):
    from stnh_tf.evaluation import mace

    old_text = _copy(tmp_path)
    old = json.loads(old_text)
    old_tables = (tmp_path / "tables.md").read_text()
    calls, real = [], mace.latency

    def spy(*args, **kwargs):
        calls.append((args, kwargs, real(*args, **kwargs)))
        return calls[-1][2]

    monkeypatch.setattr(mace, "latency", spy)
    loads = iter([(0.25, 0.5, 0.75), (1.5, 1.0, 0.9)])  # just before, just after measuring
    monkeypatch.setattr(os, "getloadavg", lambda: next(loads))
    lines = []
    returned = table2.refresh(str(tmp_path), printer=lines.append)

    # One call of the library's latency function at the budget: 2 runs, 1 warm-up, bfloat16,
    # untrained models (no model folders), sequence models included.
    assert len(calls) == 1
    args, kwargs, measured = calls[0]
    assert args == ([],) and kwargs == {"runs": 2, "warmup": 1, "policy": "mixed_bfloat16",
                                        "sequence": True}
    written = json.loads((tmp_path / "results.json").read_text())
    assert written == returned
    assert written["table2_latency_ms"] == {k: measured["hierarchy"][k]["d_e_ms"]
                                            for k in ("1", "2", "3")}
    assert written["sequence_latency_ms"] == {k: measured["sequence"][k]["forward_ms"]
                                              for k in ("1", "2", "3")}
    assert written["table2_latency_ms"] != old["table2_latency_ms"]
    # Every other key byte for byte, in its place: the old values put back give the old text.
    assert list(written) == list(old)
    assert json.dumps({**written, **{k: old[k] for k in table2.REFRESHED_KEYS}},
                      indent=2) == old_text
    prov = written["latency_provenance"]
    info = provenance.machine_info()
    assert prov["loadavg_at_start"] == [0.25, 0.5, 0.75] and prov["loadavg_at_end"] == [1.5, 1.0,
                                                                                        0.9]
    assert prov["commit"] == (provenance.STARTED["git_commit"] or "not recorded")
    assert prov["machine"] == {"cpu": info["cpu"], "cores": os.cpu_count(),
                               "accelerators": sorted(info.get("gpus", []))}
    assert prov["backend"] == info["keras_backend"] and prov["command"] == info["command"]
    assert prov["models"] == ("untrained, built under mixed_bfloat16 (latency does not depend on "
                              "the weights)")
    assert (prov["runs"], prov["warmup"], prov["policy"]) == (2, 1, "mixed_bfloat16")
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", prov["date"])
    assert "trained_after" not in prov and "note" not in prov  # (the reconstruction's, replaced)
    # The measurement's terms beside it, and tables.md's Table 2 alone redrawn from them.
    with open(tmp_path / "eval" / "latency.json") as f:
        assert json.load(f) == {**measured, "provenance": prov}
    tables = (tmp_path / "tables.md").read_text()
    head, tail = old_tables.index("## Table 2"), old_tables.index("## Models")
    assert tables.startswith(old_tables[:head]) and tables.endswith(old_tables[tail:])
    for k, paper in (("1", "4.87"), ("2", "11.46"), ("3", "17.85")):
        d_e = measured["hierarchy"][k]["d_e_ms"]
        assert f"| {k} | {d_e:.2f} | {measured['hierarchy'][k]['formula_ms']:.2f} | {paper} |" \
            in tables
    assert f"l_m = {measured['l_m_ms']:.2f} ms" in tables
    assert lines[-1].endswith("; load 0.25 at start and 1.50 at end")
    # The cells of the current results now name this machine and that load.
    sources = {**cr.load_sources(ROOT), "results": written}
    cell = result_cells.latency_machine(sources)
    assert info["cpu"] in cell and "load 0.25 at start and 1.50 at end" in cell
    assert "not recorded" not in cell


@pytest.mark.parametrize("content", [None, "{not json", json.dumps({"budget": {"name": "cpu"}})])
def test_refresh_refuses_a_folder_without_a_readable_results_json_and_writes_nothing(
        tmp_path, monkeypatch, content):
    from stnh_tf.evaluation import mace

    monkeypatch.setattr(mace, "latency", lambda *a, **k: pytest.fail("measured"))
    if content is not None:
        (tmp_path / "results.json").write_text(content)
    before = sorted(os.listdir(tmp_path))
    with pytest.raises(ValueError, match=r"results\.json.*nothing written"):
        table2.refresh(str(tmp_path), printer=lambda line: None)
    assert sorted(os.listdir(tmp_path)) == before
    if content is not None:
        assert (tmp_path / "results.json").read_text() == content


REFUSALS = r"""
import json, sys
from absl import flags
from experiments import reproduce
lines = []
for argv in json.loads(sys.argv[1]):
    flags.FLAGS.unparse_flags()
    flags.FLAGS(["reproduce", *argv])
    try:
        reproduce.main([])
        lines.append(None)
    except SystemExit as e:
        lines.append(str(e))
print(json.dumps(lines))
"""


@pytest.mark.slow
def test_the_binary_refuses_in_one_line_and_takes_output_dir_alone(tmp_path):
    """experiments.reproduce --refresh_latency ends with one line, having written nothing, on a
    folder without results.json, and refuses the flags of a reproduction's run (its budget is
    results.json's)."""
    empty, folder = tmp_path / "empty", tmp_path / "folder"
    empty.mkdir()
    folder.mkdir()
    _copy(folder)
    cases = [[f"--output_dir={empty}", "--refresh_latency"],
             [f"--output_dir={folder}", "--refresh_latency", "--budget=tiny", "--reuse=stage1=x"]]
    out = subprocess.run([sys.executable, "-c", REFUSALS, json.dumps(cases)], cwd=ROOT,
                         capture_output=True, text=True, timeout=120, check=True)
    missing, flags = json.loads(out.stdout.strip().splitlines()[-1])
    assert missing == (f"reproduce: {empty}/results.json: no readable results.json of a "
                       f"reproduction ([Errno 2] No such file or directory: '{empty}/results.json')"
                       "; nothing written.")
    assert flags.startswith("reproduce: --refresh_latency") and flags.endswith(
        "it takes --output_dir alone (received --budget, --reuse).")
    assert os.listdir(empty) == [] and sorted(os.listdir(folder)) == ["results.json", "tables.md"]


def test_table2_cells_name_the_machine_and_load_the_refresh_records():
    """README's and BENCHMARKS.md's Table 2 cells: "its load not recorded" for a latency_provenance
    without the load (the committed one, as reconstructed); the machine, commit, date and loads
    of a refreshed one."""
    sources = cr.load_sources(ROOT)
    for key in ("loadavg_at_start", "loadavg_at_end"):  # (should the committed one be refreshed)
        sources["results"]["latency_provenance"].pop(key, None)
    assert result_cells.latency_machine(sources).endswith("its load not recorded")
    committed = next(r for r in cr.benchmarks_rows(sources)
                     if r[0].startswith("Reproduction, Table 2"))
    assert committed[2].startswith("`python -m experiments.reproduce --budget=cpu ...`")
    assert committed[4].startswith("assembled: trained between ")
    sources["results"] = {**sources["results"], "latency_provenance": {
        "commit": "abc1234", "machine": {"cpu": "Some Xeon", "cores": 2, "accelerators": []},
        "backend": "tensorflow", "date": "2027-01-02T03:04:05Z",
        "loadavg_at_start": [0.07, 0.2, 0.3], "loadavg_at_end": [1.21, 0.5, 0.4]}}
    expected = ("Some Xeon, 2 cores (tensorflow), code abc1234, 2027-01-02, 1-minute load 0.07 "
                "at start and 1.21 at end")
    assert result_cells.latency_machine(sources) == expected
    row = next(r for r in cr.benchmarks_rows(sources) if r[0].startswith("Reproduction, Table 2"))
    assert f"on {expected} " in row[1]
    assert row[2].startswith("`python -m experiments.reproduce --output_dir=docs/reproduce_cpu "
                             "--refresh_latency`")
    # (untrained models: the stages' training is no part of it)
    assert row[4:] == ("measured at abc1234 on untrained models", "Some Xeon, 2 cores (tensorflow)")
    assert f"(ours: mixed bfloat16 on {expected}; the paper: its GPU)" in cr.readme_block(sources)
