"""stnh_tf.provenance (issue 62, item 7): the commit, machine and library versions that the result
JSON of ship_weights, evaluate, reproduce and paper_schedule record, checked against git, the
packages' own metadata and /proc/cpuinfo; and the model card of ship_weights records them."""

import importlib.metadata
import json
import os
import platform
import re
import subprocess
import sys

import cv2
import numpy as np
import pytest

from stnh_tf import provenance

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
IN_GIT = os.path.isdir(os.path.join(ROOT, ".git"))


def _git(*args):
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True)


def test_machine_info_names_the_commit_the_cpu_and_the_versions():
    info = provenance.machine_info()
    assert info["python"] == platform.python_version()
    assert info["numpy"] == np.__version__ and info["opencv"] == cv2.__version__
    assert info["stnh_tf"] == importlib.metadata.version("stnh-tf")
    assert info["cpu_count"] == os.cpu_count()
    if os.path.exists("/proc/cpuinfo"):
        with open("/proc/cpuinfo") as f:
            names = re.findall(r"^model name\s*:\s*(.*)$", f.read(), re.M)
        if names:
            assert info["cpu"] == names[0].strip()
    for name in ("keras", "tensorflow", "jax"):  # reported only where the caller imported them
        assert (name in info) == (name in sys.modules)
        if name in info:
            assert info[name] == sys.modules[name].__version__
    json.dumps(info)  # a JSON object as it is
    if not IN_GIT:
        assert info["git_commit"] is None
        return
    head = _git("log", "-1", "--format=%H").stdout.strip()
    commit = info["git_commit"]
    assert len(commit.split("+")[0]) >= 7 and head.startswith(commit.split("+")[0])
    # tracked files changed (git diff exits 1) <=> "+dirty"
    assert commit.endswith("+dirty") == (_git("diff", "--quiet", "HEAD").returncode == 1)


def test_the_model_card_records_the_run_that_wrote_it(tmp_path, monkeypatch):
    """ship_weights (here --refresh_check, whose card write every ship_weights command shares)
    records machine_info under ``machine``, on disk as returned; the rest of the card is kept."""
    from stnh_tf.inference import shipped_weights

    monkeypatch.setattr(shipped_weights, "bundled_check", lambda paths: {"count": len(paths)})
    (tmp_path / "model_card.json").write_text(json.dumps({"stages": [], "note": "kept"}))
    card = shipped_weights.refresh_check(str(tmp_path))
    assert card == json.loads((tmp_path / "model_card.json").read_text())
    assert card["note"] == "kept" and card["bundled_check"] == {"count": 0}
    expected = provenance.machine_info()
    for key in ("git_commit", "cpu", "python", "numpy", "stnh_tf"):
        assert card["machine"][key] == expected[key]


def test_current_results_show_the_commit_and_machine_a_json_records():
    """BENCHMARKS' "Current results" shows the commit and machine of each JSON that records
    machine_info, "not recorded" in the rows whose JSON does not; the reproduction's rows, those
    of its models' model_provenance."""
    import copy

    from stnh_tf.paper import current_results as cr

    sources = cr.load_sources(cr.default_root())
    # Table 2 with no load recorded, as reconstructed: one measured again names its own machine
    # and load whatever the machine block (tests/test_refresh_latency.py).
    for key in ("loadavg_at_start", "loadavg_at_end"):
        sources["results"]["latency_provenance"].pop(key, None)
    before = cr.benchmarks_rows(sources)
    sources = copy.deepcopy(sources)
    sources["card"]["machine"] = {"git_commit": "abc1234", "cpu": "Some CPU", "cpu_count": 2,
                                  "keras_backend": "jax", "jax_devices": ["cpu"]}
    sources["results"]["machine"] = {"git_commit": "def5678+dirty", "cpu": "Other CPU",
                                     "cpu_count": 16, "gpus": ["/physical_device:GPU:0"],
                                     "keras_backend": "tensorflow"}
    after = cr.benchmarks_rows(sources)
    changed = {b[0].split(":")[0]: (a[4:], b[4:]) for a, b in zip(before, after) if a != b}
    fig4, table2 = "Reproduction at the CPU budget, Fig. 4", "Reproduction, Table 2"
    assert set(changed) == {"Shipped default, `estimate` on bare 128x128 patches (default search), "
                            "the card's 60 bundled pairs", fig4, table2}  # (Table 2: its text)
    assert changed["Shipped default, `estimate` on bare 128x128 patches (default search), the "
                   "card's 60 bundled pairs"][1] == ("abc1234", "Some CPU, 2 cores (jax)")
    # The reproduction's rows show where its models were trained (model_provenance); a machine
    # block (a run that evaluated its models itself) adds its commit and machine to Fig. 4's, and
    # Table 2 keeps its own measurement's (latency_provenance).
    (commit, machine), (new_commit, new_machine) = changed[fig4]
    assert commit.startswith("assembled: trained between ") and cr.NOT_RECORDED not in machine
    assert (new_commit, new_machine) == (f"{commit}; evaluated at def5678+dirty",
                                         f"{machine}; /physical_device:GPU:0 (tensorflow)")
    assert changed[table2][0] == changed[table2][1]
    # A results.json without model_provenance (written before issue 78): its machine block alone.
    del sources["results"]["model_provenance"]
    old = {b[0].split(":")[0]: b[4:] for b in cr.benchmarks_rows(sources)}
    for row in (fig4, table2):
        assert old[row] == ("def5678+dirty",
                            "Other CPU, 16 cores; /physical_device:GPU:0 (tensorflow)")


def test_the_commit_and_load_are_those_of_the_runs_start(monkeypatch):
    """machine_info reports the commit and load average of the moment provenance was imported
    (a binary's start: experiments.common imports it), not those when a long run writes its
    JSON: here a commit and a load that came during the run are not taken."""
    started = provenance.machine_info()
    monkeypatch.setattr(provenance, "git_commit", lambda: "abc1234+dirty")
    monkeypatch.setattr(os, "getloadavg", lambda: (99.0, 99.0, 99.0), raising=False)
    info = provenance.machine_info()
    assert info["git_commit"] == started["git_commit"] == provenance.STARTED["git_commit"]
    assert info.get("loadavg_at_start") == started.get("loadavg_at_start")
    assert info.get("loadavg_at_start") != [99.0, 99.0, 99.0]
    # a binary's first import of the project records them
    out = subprocess.run([sys.executable, "-c", "import sys, experiments.common; "
                          "print('stnh_tf.provenance' in sys.modules)"], cwd=ROOT,
                         capture_output=True, text=True, check=True).stdout.strip()
    assert out == "True"
