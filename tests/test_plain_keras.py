"""Models open with plain ``keras.models.load_model`` after ``import stnh_tf`` (issue 78, item 3):
every shipped ``.keras`` file, in a fresh process that imports only the package first, holds the
weights stored in its archive and predicts what :func:`stnh_tf.modeling.runner.load_model`'s
model predicts; docs/weights.md's fine-tuning example runs as written (2 steps on a tiny
dataset); the post-import hook registers every class the package registers."""

import ast
import glob
import io
import os
import re
import subprocess
import sys
import zipfile

import h5py
import keras
import numpy as np
import pytest

from stnh_tf import modeling
from stnh_tf.data import stage1
from stnh_tf.inference import model_files
from stnh_tf.modeling import runner

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SHIPPED = sorted(glob.glob(os.path.join(model_files.default_weights_dir(), "**", "*.keras"),
                           recursive=True))

PLAIN_LOAD = r"""
import sys
import numpy as np
import stnh_tf
loaded = sorted(m for m in sys.modules if m.startswith(("keras", "tensorflow", "stnh_tf.model")))
assert not loaded, loaded  # the registration waits for Keras' own import
import keras
batch, out_dir = np.load(sys.argv[1]), sys.argv[2]
for i, path in enumerate(sys.argv[3:]):
    arrays = {}
    for compile in (True, False):
        model = keras.models.load_model(path, compile=compile)
        pred = model.predict_on_batch({"patch_a": batch["a"], "patch_b": batch["b"]})
        arrays.update({f"{compile}/{k}": np.asarray(v, np.float32) for k, v in pred.items()})
    arrays.update({f"weight/{j}": np.asarray(w) for j, w in enumerate(model.get_weights())})
    np.savez(f"{out_dir}/{i}.npz", **arrays)
"""


def _archive_weights(path):
    """Every array of a ``.keras`` archive's ``model.weights.h5``, read with h5py."""
    with zipfile.ZipFile(path) as z:
        h5 = h5py.File(io.BytesIO(z.read("model.weights.h5")), "r")
    arrays = []
    h5.visititems(lambda name, obj: arrays.append(obj[()]) if isinstance(obj, h5py.Dataset)
                  else None)
    return arrays


def _check_plain_load(paths, tmp_path):
    """Load ``paths`` with plain Keras (``compile`` True and False) in a fresh process whose only
    import before Keras is ``import stnh_tf``; check each model's weights against its archive's
    and its outputs on a random batch against :func:`runner.load_model`'s model's (float
    tolerance; measured: identical, the same graph and weights)."""
    rng = np.random.default_rng(0)
    batch = {k: rng.uniform(0, 1, (4, 128, 128, 1)).astype(np.float32) for k in "ab"}
    np.savez(tmp_path / "batch.npz", **batch)
    proc = subprocess.run([sys.executable, "-c", PLAIN_LOAD, str(tmp_path / "batch.npz"),
                           str(tmp_path), *paths], cwd=ROOT, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    for i, path in enumerate(paths):
        got = np.load(tmp_path / f"{i}.npz")
        stored = _archive_weights(path)  # the archive's arrays, each matched once
        weights = [got[k] for k in got.files if k.startswith("weight/")]
        assert len(weights) == len(stored), path
        for w in weights:
            match = next(j for j, s in enumerate(stored)
                         if s.shape == w.shape and np.array_equal(s, w))
            stored.pop(match)
        reference = runner.load_model(path)
        expected = reference.predict_on_batch({"patch_a": batch["a"], "patch_b": batch["b"]})
        assert set(expected) == {"h_bar", "patch_a_warp"}, path
        for compile in (True, False):
            for name, value in expected.items():
                np.testing.assert_allclose(got[f"{compile}/{name}"], np.asarray(value, np.float32),
                                           rtol=1e-5, atol=1e-6, err_msg=f"{path} {name}")


@pytest.mark.slow
def test_the_paper_schedule_stage_1_opens_with_plain_keras_after_import_stnh_tf(tmp_path):
    """The issue's file. Before, ``keras.models.load_model(".../paper_schedule/stage1.keras")``
    raised "TypeError: Functional could not be deserialized" (with ``compile=False`` too): the
    layers were registered only when stnh_tf.modeling.layers was imported, which
    ``import stnh_tf`` does not do."""
    path = os.path.join(model_files.default_weights_dir(), model_files.PAPER_SCHEDULE_WEIGHTS,
                        "stage1.keras")
    _check_plain_load([path], tmp_path)


@pytest.mark.slow  # a fresh TensorFlow process and 8 models loaded twice (16-31 s on 2 cores)
def test_every_shipped_model_opens_with_plain_keras_after_import_stnh_tf(tmp_path):
    assert len(SHIPPED) >= 2, SHIPPED
    _check_plain_load(SHIPPED, tmp_path)


def _registered_in_sources():
    """``(modules, names)``: the modules of stnh_tf and the Keras names (``stnh_tf>Name``) of the
    classes and functions they decorate with ``register_keras_serializable``."""
    package = os.path.join(ROOT, "stnh_tf")
    registering, names = set(), set()
    for path in glob.glob(os.path.join(package, "**", "*.py"), recursive=True):
        tree = ast.parse(open(path).read())
        for node in ast.walk(tree):
            if isinstance(node, (ast.ClassDef, ast.FunctionDef)) and any(
                    "register_keras_serializable" in ast.unparse(d) for d in node.decorator_list):
                module = os.path.relpath(path, ROOT)[:-3].replace(os.sep, ".")
                registering.add(module)
                names.add(f"stnh_tf>{node.name}")
    return registering, names


def test_the_hook_registers_every_class_and_function_the_package_registers():
    """:data:`stnh_tf.modeling.KERAS_OBJECT_MODULES` lists every module that registers an object
    with Keras (read from the sources), and each registered name resolves after the hook."""
    registering, names = _registered_in_sources()
    assert registering == set(modeling.KERAS_OBJECT_MODULES)
    assert names and all(keras.saving.get_registered_object(n) is not None for n in names)


def _fine_tuning_code():
    """docs/weights.md's fine-tuning example, shrunk to 2 steps of batch 4."""
    with open(os.path.join(ROOT, "docs", "weights.md")) as f:
        text = f.read()
    section = text.split("## Opening them with Keras, and fine-tuning them", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    for old, new in (("train_steps=2_000", "train_steps=2"), ("warmup_steps=100", "warmup_steps=1"),
                     ("batch_size=64", "batch_size=4")):
        assert code.count(old) == 1, old
        code = code.replace(old, new)
    return code


@pytest.mark.slow  # (a training run: the make test time)
def test_the_fine_tuning_example_of_docs_weights_runs(tmp_path, monkeypatch):
    """The example as written (but for its steps and batch), in a folder holding a tiny
    ``data/coco_mini`` (bundled photographs): it trains the shipped stage with SGD momentum 0.9
    for 2 steps, moves its weights, and saves a file that plain Keras opens again."""
    stage1.make_dataset("bundled", str(tmp_path / "data" / "coco_mini"), "train", seed=0,
                        num_shards=1, max_images=4, log=lambda *a, **k: None)
    monkeypatch.chdir(tmp_path)
    scope = {}
    exec(compile(_fine_tuning_code(), "docs/weights.md", "exec"), scope)  # noqa: S102
    model = scope["model"]
    assert isinstance(model.optimizer, keras.optimizers.SGD) and model.optimizer.momentum == 0.9
    assert int(keras.ops.convert_to_numpy(model.optimizer.iterations)) == 2
    shipped = [np.asarray(w) for w in keras.models.load_model(scope["path"]).get_weights()]
    tuned = [np.asarray(w) for w in model.get_weights()]
    assert max(np.abs(u - v).max() for u, v in zip(tuned, shipped)) > 0
    saved = keras.models.load_model(tmp_path / "runs" / "finetune" / "stage1.keras")
    for u, v in zip(saved.get_weights(), tuned):
        np.testing.assert_array_equal(u, v)


@pytest.mark.slow
def test_keras_imported_before_stnh_tf_has_the_objects_registered_at_import():
    """The other order: ``import stnh_tf`` after Keras registers at once (no hook to wait for),
    in a fresh process: Keras then knows every name the sources register."""
    code = ("import keras, stnh_tf\n"
            "print(' '.join(n for n in keras.saving.get_custom_objects()\n"
            "               if n.startswith('stnh_tf>')))\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert set(proc.stdout.split()) == _registered_in_sources()[1]
