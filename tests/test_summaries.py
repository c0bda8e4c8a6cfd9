"""The short tables the evaluating binaries print (issue 62, item 2): their numbers are the JSON's,
the identity's row is there once, a method whose mean is above the identity's gets the line
"worse than the identity", and ``--json_out`` keeps the full JSON."""

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from stnh_tf.evaluation import summaries

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _corner_errors(h, h_true):
    """Mean corner error (px) per pair of the 128-px patch, written out here."""
    corners = np.array([[0, 0, 1], [128, 0, 1], [128, 128, 1], [0, 128, 1]], np.float64).T
    h = np.broadcast_to(h, np.shape(h_true))
    p, q = h @ corners, h_true @ corners
    return np.linalg.norm(p[:, :2] / p[:, 2:] - q[:, :2] / q[:, 2:], axis=-2).mean(axis=-1)


def _parse(text):
    """``{method: [MACE, median, worse]}`` of the table's rows (columns: 2+ spaces apart), the
    number of identity rows, and the methods of the "worse than the identity" lines."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("method "))
    rows, identities = {}, 0
    for line in lines[start + 1:]:
        if line.startswith("worse than the identity:") or not re.search(r"\d\s*$|-\s*$", line):
            break
        cells = re.split(r"\s{2,}", line.strip())
        identities += cells[0] == "identity"
        rows[cells[0]] = cells[1:]
    worse = [re.match(r"worse than the identity: (.*) \(mean ", line).group(1)
             for line in lines if line.startswith("worse than the identity:")]
    return rows, identities, worse


def _check(text, expected: dict, identity: dict):
    """The table shows the ``identity`` summary and ``expected`` (``{method: summary}``) as in
    the JSON, in order, the identity once, and the worse-than-identity lines of exactly the
    methods above it."""
    rows, identities, worse = _parse(text)
    assert identities == 1
    assert list(rows) == ["identity", *expected]
    assert rows["identity"] == [f"{identity['mace']:.2f}", f"{identity['median']:.2f}", "-"]
    for method, s in expected.items():
        cells = rows[method]
        assert cells[0] == f"{s['mace']:.2f}" and cells[1] == f"{s['median']:.2f}", method
        assert cells[2] == f"{s['worse_than_identity']} of {s['count']}", method
    assert worse == [m for m, s in expected.items() if s["mace"] > identity["mace"]]


def test_summary_table_format_and_the_worse_line():
    """Rows in order after the identity's; a line for each method above the identity only."""
    text = summaries.summary_table(
        summaries.Row("identity", 24.164, 23.9, None, 300),
        [summaries.Row("2 stages", 30.836, 29.1, 263, 300),
         summaries.Row("sift", 1.06, 0.5, 3, 300)], title="300 pairs", notes=["a note"])
    assert text.splitlines() == [
        "300 pairs",
        "method    MACE (px)  median (px)  worse than identity",
        "identity      24.16        23.90                    -",
        "2 stages      30.84        29.10           263 of 300",
        "sift           1.06         0.50             3 of 300",
        "worse than the identity: 2 stages (mean 30.84 px against the identity's 24.16 px)",
        "a note"]


def test_emit_prints_the_table_writes_the_json_or_prints_only_the_json(tmp_path):
    result = {"count": 2, "x": [1.5, "inf"]}
    printed = []
    summaries.emit(result, "the table", str(tmp_path / "r.json"), printer=printed.append,
                   writer="evaluate")
    assert printed == ["the table", f"JSON: {tmp_path / 'r.json'}"]
    assert json.loads((tmp_path / "r.json").read_text()) == {**result, "written_by": "evaluate"}
    printed.clear()
    summaries.emit(result, "the table", "-", printer=printed.append)
    assert len(printed) == 1 and json.loads(printed[0]) == result
    printed.clear()
    summaries.emit(result, "the table", None, printer=printed.append)
    assert printed == ["the table"]


class _EveryOtherShifted:
    """A stand-in baseline: the truth shifted by 25 px in x on odd pairs, the truth on even."""

    def __init__(self, h_true):
        from stnh_tf.evaluation import baselines

        class Shifted(baselines._Estimator):
            name = "shifted"

            def __init__(self):
                self.i = 0

            def _estimate_uint8(self, a, b, size=128):
                h = h_true[self.i] @ (np.array([[1, 0, 25.0], [0, 1, 0], [0, 0, 1]])
                                      if self.i % 2 else np.eye(3))
                self.i += 1
                return h, True

        self.estimator = Shifted()


def test_baselines_count_the_pairs_worse_than_the_identity():
    """``worse_than_identity`` of a baseline: its pairs whose corner error (written out here)
    exceeds the identity's; the truth on even pairs is never worse, a 25-px shift sometimes."""
    from stnh_tf.evaluation import baselines

    rng = np.random.default_rng(3)
    h_true = np.stack([np.eye(3) + np.array([[0, 0, t], [0, 0, u], [0, 0, 0]])
                       for t, u in rng.uniform(-30, 30, (10, 2))])
    patches = np.zeros((10, 128, 128), np.uint8)
    res = baselines.evaluate_baseline(_EveryOtherShifted(h_true).estimator, patches, patches,
                                      h_true)
    shifted = h_true @ np.array([[1, 0, 25.0], [0, 1, 0], [0, 0, 1]])
    h_est = np.where(np.arange(10)[:, None, None] % 2, shifted, h_true)
    expected = int((_corner_errors(h_est, h_true) > _corner_errors(np.eye(3), h_true)).sum())
    assert 0 < expected < 5  # (some odd pairs are worse than the identity, not all)
    assert res["worse_than_identity"] == expected
    ident = baselines.evaluate_baseline("identity", patches, patches, h_true)
    assert ident["worse_than_identity"] == 0


@pytest.fixture(scope="module")
def test_pairs(tmp_path_factory):
    """3 bundled photographs x 3 pairs (stage-1 test pairs)."""
    from stnh_tf.data import stage1

    out = str(tmp_path_factory.mktemp("pairs"))
    stage1.make_dataset("bundled", out, "test", max_images=3, seed=5, num_workers=1,
                        log=lambda m: None)
    return out


@pytest.fixture(scope="module")
def untrained_model(tmp_path_factory):
    """An untrained STN-Homography stage saved as a .keras file, its last layer's bias moved
    off the identity by 0.6 in h13 (about 38 px of translation): estimates worse than the
    identity on most pairs."""
    import keras

    from stnh_tf.modeling import models

    keras.utils.set_random_seed(0)
    model = models.build_stn_homography()
    weights = model.get_weights()
    assert weights[-1].shape == (8,)  # the last layer's bias: H_bar's 8 entries
    weights[-1][2] += 0.6
    model.set_weights(weights)
    path = str(tmp_path_factory.mktemp("model") / "untrained.keras")
    model.save(path)
    return path


def test_evaluation_table_shows_the_numbers_of_evaluate(test_pairs, untrained_model):
    """A single model, a hierarchy and the baselines: every row is the JSON's, the identity's
    once although the identity is also a requested baseline."""
    from stnh_tf.evaluation import mace

    result = mace.evaluate([untrained_model], test_pairs, "test", ["identity", "orb_ransac"])
    text = summaries.evaluation_table(result)
    _check(text, {untrained_model: result["model"],
                  "orb_ransac": result["baselines"]["orb_ransac"]}, result["identity"])
    assert text.splitlines()[0] == f"MACE on 9 pairs of {test_pairs} (test)"
    # Every stored pair names its photograph (image_id): the bootstrap resamples the 3 of them.
    assert result["model"]["photographs"] == result["identity"]["photographs"] == 3
    assert sum(line.startswith("by photograph: ") for line in text.splitlines()) == 1
    # The untrained model is worse than the identity, ORB + RANSAC is not: both cases shown.
    assert result["model"]["mace"] > result["identity"]["mace"] > (
        result["baselines"]["orb_ransac"]["mace"])
    hier = mace.evaluate([untrained_model] * 2, test_pairs, "test")
    _check(summaries.evaluation_table(hier),
           {f"hierarchy, {k} stage{'s' if k > 1 else ''}":
            hier["model"]["stages"][f"after_{k}_stages"] for k in (1, 2)},
           hier["identity"])


@pytest.mark.slow
def test_evaluate_binary_prints_the_table_and_writes_the_json(test_pairs, tmp_path):
    """The binary (a subprocess importing TensorFlow: about 20 s on 2 shared cores)."""
    out = tmp_path / "e.json"
    proc = subprocess.run([sys.executable, "-m", "experiments.evaluate", f"--data_dir={test_pairs}",
                           "--baselines=identity,orb_ransac", f"--json_out={out}"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(out.read_text())
    _check(proc.stdout, {"orb_ransac": result["baselines"]["orb_ransac"]}, result["identity"])
    assert proc.stdout.rstrip().endswith(f"JSON: {out}") and "{" not in proc.stdout


def test_tuning_table_shows_the_grid():
    from stnh_tf.evaluation import baseline_tuning

    result = baseline_tuning.run_tuning(None, num_pairs=6, seed=0, grid="none")
    others = {k: v for k, v in result["results"].items() if k != "identity"}
    _check(summaries.tuning_table(result), others, result["results"]["identity"])


def test_implausibility_table_rows_and_flag_shares():
    """The estimator and the identity on the ordinary pairs, each case's flagged share."""
    result = {"model": "m", "ordinary": {"count": 10, "flagged": 0.1, "mace": 30.5,
                                         "mace_median": 28.0, "worse_than_identity": 7,
                                         "identity_mace": 24.0, "identity_median": 23.5},
              "rotated_180": {"count": 10, "flagged": 1.0}}
    text = summaries.implausibility_table(result)
    _check(text, {"estimator": {"mace": 30.5, "median": 28.0, "worse_than_identity": 7,
                                "count": 10}}, {"mace": 24.0, "median": 23.5})
    assert text.splitlines()[-1] == "flagged implausible: ordinary 10.0%, rotated 180 100.0%"


@pytest.mark.parametrize("module", ["stnh_tf.evaluation.summaries", "stnh_tf.paper.tables",
                                    "stnh_tf.paper.figures"])
def test_doctests(module):
    import doctest
    import importlib

    result = doctest.testmod(importlib.import_module(module))
    assert result.attempted > 0 and result.failed == 0
