"""The package's layers (stnh_tf/__init__.py): who may import whom, the names the subpackages
re-export, and the doctests of the modules that need no deep-learning backend."""

import ast
import doctest
import importlib
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGE = os.path.join(ROOT, "stnh_tf")

# Layer of each part of stnh_tf -> the parts it may import (itself always). The NumPy core is the
# top-level modules.
ALLOWED = {
    "core": {"core"},
    "modeling": {"core"},
    "data": {"core", "modeling"},
    "training": {"core", "modeling", "data"},
    "inference": {"core", "modeling", "data"},
    "evaluation": {"core", "modeling", "data", "training", "inference"},
    "paper": {"core", "modeling", "data", "training", "inference", "evaluation"},
}
# Deep-learning backends: the NumPy core and these modules never import them at module level.
BACKENDS = ("tensorflow", "keras", "jax", "torch")
BACKEND_FREE = ("core", "data/sources", "data/pairs", "data/batches", "data/pools",
                "data/features", "data/labels", "data/paper_motions", "training/config",
                "training/presets", "paper/result_cells", "paper/model_provenance",
                "evaluation/card_evaluation", "paper/fig4_render",
                "paper/learning_curves",
                "training/run_dir", "training/run_records", "training/file_parts",
                "training/ledger",
                "evaluation/onednn_profile", "inference/options",
                "inference/checks", "inference/search", "inference/pipeline", "inference/ecc")


def _part(path):
    rel = os.path.relpath(path, PACKAGE)
    return rel.split(os.sep)[0] if os.sep in rel else "core"


def _imports(path, top_level_only=False):
    """(line, imported module) of every stnh_tf/data_prep/experiments/backend import in a file."""
    tree = ast.parse(open(path).read())
    nodes = tree.body if top_level_only else ast.walk(tree)
    for node in nodes:
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            yield node.lineno, names
        elif isinstance(node, ast.Import):
            yield node.lineno, [a.name for a in node.names]


def _module_part(name):
    parts = name.split(".")
    if parts[0] != "stnh_tf" or len(parts) == 1:
        return None
    if parts[1] in ALLOWED:
        return parts[1]
    return "core" if os.path.isfile(os.path.join(PACKAGE, parts[1] + ".py")) else None


def _sources():
    for folder, _, files in os.walk(PACKAGE):
        for f in files:
            if f.endswith(".py"):
                yield os.path.join(folder, f)


def test_imports_follow_the_layers():
    """Every import in stnh_tf (also inside functions) goes to its own layer or one above it, and
    never to the binaries (data_prep, experiments)."""
    bad = []
    for path in _sources():
        if path == os.path.join(PACKAGE, "__init__.py"):
            continue
        part = _part(path)
        for line, names in _imports(path):
            for name in names:
                if name.split(".")[0] in ("data_prep", "experiments"):
                    bad.append(f"{os.path.relpath(path, ROOT)}:{line} imports {name}")
                target = _module_part(name)
                if target and target != part and target not in ALLOWED[part]:
                    bad.append(f"{os.path.relpath(path, ROOT)}:{line} ({part}) imports {name} "
                               f"({target})")
    assert not bad, "\n".join(bad)


def test_the_numpy_core_imports_no_backend_at_module_level():
    bad = []
    for path in _sources():
        rel = os.path.relpath(path, PACKAGE)[:-3]
        if not (_part(path) == "core" or rel in BACKEND_FREE):
            continue
        for line, names in _imports(path, top_level_only=True):
            bad += [f"{rel}:{line} imports {n}" for n in names if n.split(".")[0] in BACKENDS]
    assert not bad, "\n".join(bad)


def test_the_options_and_pipeline_load_no_backend():
    """In a fresh process the estimator's options, checks, search and pipeline import neither
    TensorFlow nor Keras (a worker or a tool can use them without a backend)."""
    code = ("import sys\n"
            "import stnh_tf.inference.pipeline, stnh_tf.inference.options\n"
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'tensorflow', 'keras'}))\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == "[]"


def test_package_level_names_resolve():
    """The names each package re-exports (imported on first use): ``stnh_tf.HomographyEstimator``,
    ``stnh_tf.geometry``, ``stnh_tf.training.train``, ``stnh_tf.data.load_split``, ...; the flat
    module paths before the subpackages (``stnh_tf.layers``) are gone."""
    import stnh_tf
    from stnh_tf import data, evaluation, inference, training
    from stnh_tf.data import tfrecords
    from stnh_tf.evaluation import mace
    from stnh_tf.inference import estimator, pipeline
    from stnh_tf.training import loop

    assert stnh_tf.HomographyEstimator is estimator.HomographyEstimator
    assert stnh_tf.geometry.PATCH_SIZE == 128
    assert training.train is loop.train and data.load_split is tfrecords.load_split
    assert evaluation.evaluate is mace.evaluate
    assert inference.HomographyEstimator is estimator.HomographyEstimator
    assert inference.Estimate is pipeline.Estimate
    assert training.config.TrainConfig is stnh_tf.training.config.TrainConfig  # a submodule
    with pytest.raises(AttributeError):
        training.no_such_name
    with pytest.raises(AttributeError):
        inference.alignment_ncc  # served by the removed shim; stnh_tf.inference.checks has it
    for old in ("stnh_tf.layers", "stnh_tf.train_config", "stnh_tf.alignment"):
        with pytest.raises(ModuleNotFoundError):
            importlib.import_module(old)


def test_modules_stay_small():
    """No module of the package is over 460 lines (the layout's goal: ~400)."""
    long = {os.path.relpath(p, ROOT): n for p in _sources()
            if (n := sum(1 for _ in open(p))) > 460}
    assert not long, long


DOCTEST_MODULES = ("stnh_tf.geometry", "stnh_tf.pixels", "stnh_tf.paths", "stnh_tf.provenance",
                   "stnh_tf.data.sources",
                   "stnh_tf.training.config", "stnh_tf.training.presets", "stnh_tf.data.labels",
                   "stnh_tf.inference.options", "stnh_tf.inference.checks",
                   "stnh_tf.inference.search", "stnh_tf.inference.ecc",
                   "stnh_tf.data.paper_motions", "stnh_tf.evaluation.card_evaluation",
                   "stnh_tf.evaluation.ablation",
                   "stnh_tf.paper.model_provenance", "stnh_tf.paper.fig4_render",
                   "stnh_tf.paper.learning_curves", "stnh_tf.paper.budgets",
                   "stnh_tf.training.file_parts", "stnh_tf.training.ledger",
                   "stnh_tf.evaluation.onednn_profile",
                   "stnh_tf.paper.hour_budget", "stnh_tf.inference.overlays")


@pytest.mark.parametrize("name", DOCTEST_MODULES)
def test_doctests(name):
    """The examples in the docstrings of the modules that need no backend run and hold."""
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0, f"{name} has no doctest"
    assert result.failed == 0, f"{result.failed} of {name}'s doctests failed"


def test_each_committed_run_record_has_its_model_beside_it():
    """A committed run's record ``<name>.json`` (a training configuration or a chunked stage) has
    its model ``<name>.keras`` beside it (``config.json`` of a checkpoint folder aside): so that
    models set aside for device calls (``experiments.device_photographs --set_aside``) cannot be
    committed as deleted unnoticed. The semi-supervised experiment's records are the exception:
    its models are not kept in the tree (BENCHMARKS.md, "Semi-supervised training", says how to
    get them back); their evaluations are."""
    import json

    tracked = subprocess.run(["git", "ls-files", "-z", "*.json"], cwd=ROOT, capture_output=True,
                             check=True).stdout.decode().split("\0")
    records = []
    for rel in tracked:
        if not rel or os.path.basename(rel) == "config.json":
            continue
        with open(os.path.join(ROOT, rel)) as f:
            record = json.load(f)
        if isinstance(record, dict) and record.get("format") in (
                "stnh_tf.train_config", "stnh_tf.chunked_stage"):
            records.append(rel)
    assert "paper_schedule/stage1.json" in records and len(records) >= 8
    missing = [rel for rel in records if not rel.startswith("semi_supervised/")
               and not os.path.exists(os.path.join(ROOT, rel[:-len(".json")] + ".keras"))]
    assert not missing
