"""Keras backend portability: the layers, models and training under ``KERAS_BACKEND=jax`` /
``torch``.

The suite runs under TensorFlow; each other backend runs in one subprocess (the backend is chosen
at Keras' import), in the slow suite. References: OpenCV for the warp, the TensorFlow backend for the values and
gradients (themselves checked against OpenCV and finite differences in test_layers), and models
saved under each backend loaded under the other; two training steps under each backend against
the same two steps under TensorFlow, from the same weights; and ``experiments/gpu_recipe.sh`` end
to end (two stages) with TensorFlow hidden, as on the GPU machine (slow). The models are
conftest's narrow network (every layer of the paper's, 1/16 of its widths). A backend that is not
installed is skipped with the reason (JAX: the test extra installs ``jax[cpu]``; PyTorch:
``pip install torch``, not in the test extra, whose CI would otherwise download a CUDA build).
"""

import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys

import keras
import numpy as np
import pytest
import tensorflow as tf

from conftest import (NARROW_FILTERS, cv2_warp, inside_mask, narrow_network, norm_matrix,
                      paper_homography, to_bar)
from stnh_tf.training import config as train_config
from stnh_tf.training import loop as training
from stnh_tf.data import bundled_photos
from stnh_tf.modeling import models, runner
from stnh_tf.modeling.layers import SpatialTransformer

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _needs(module):
    return pytest.mark.skipif(importlib.util.find_spec(module) is None,
                              reason=f"{module} is not installed: that backend is not tested")


# Slow: each backend's subprocess imports TensorFlow and that backend, and compiles and trains.
BACKENDS = [pytest.param(b, marks=[_needs(b), pytest.mark.slow]) for b in ("jax", "torch")]
# Models saved under TensorFlow (last layers perturbed so outputs depend on the input) and run
# under the other backend: one stage, the 2-stage sequence model (HomographyMerge), HomographyNet.
SAVED_MODELS = ("stn", "sequence2", "homographynet")

BACKEND_SCRIPT = r"""
import json, os, sys
work, backend = sys.argv[1], sys.argv[2]
os.environ["KERAS_BACKEND"] = backend
import keras, numpy as np
from stnh_tf.training import config as train_config
from stnh_tf.training import loop as training
from stnh_tf.modeling import models, runner
from stnh_tf.modeling.layers import SpatialTransformer
assert keras.backend.backend() == backend
models.CONV_FILTERS = tuple(json.loads(sys.argv[4]))  # conftest's narrow network
z = np.load(os.path.join(work, "inputs.npz"))
out = {}

def grad_of(f, x):
    if backend == "jax":
        import jax
        return np.asarray(jax.grad(f)(x))
    import torch
    t = torch.tensor(x, requires_grad=True)
    f(t).backward()
    return t.grad.numpy()

# Layer forward and the gradient of a weighted sum of the warp w.r.t. H_bar.
stn = SpatialTransformer()
out["warp"] = keras.ops.convert_to_numpy(stn([z["images"], z["h8"]]))
weights = keras.ops.convert_to_tensor(z["weights"])
out["grad"] = grad_of(lambda h8: keras.ops.sum(stn([z["images"], h8]) * weights), z["h8"])
# Models saved under TensorFlow, run under this backend (every h_bar output).
for name in sys.argv[3].split(","):
    m = keras.models.load_model(os.path.join(work, f"tf_{name}.keras"), compile=False)
    for o in [k for k in m.output_names if k.startswith("h_bar")]:
        out[f"tf_{name}:{o}"] = runner.compiled_forward(m, o)(z["a"], z["b"])
# Two training steps from a folder of images, pairs generated on the fly, from the weights of
# init.keras (saved under TensorFlow), as the test repeats them under TensorFlow.
cfg = train_config.TrainConfig(**json.loads(sys.argv[5]),
                               model_dir=os.path.join(work, backend + "_run"))
res = training.train(cfg, printer=lambda *a: None)
m2 = keras.models.load_model(os.path.join(cfg.model_dir, "model.keras"), compile=False)
out["trained"] = runner.compiled_forward(m2)(z["a"], z["b"])
np.savez(os.path.join(work, backend + "_out.npz"), **out)
tiny_fit = None
if backend == "jax":  # which calls of fit copy the training state back into the model
    from stnh_tf.training.callbacks import NonFiniteGuard, ProgressLogger
    tiny = keras.Sequential([keras.Input((3,)), keras.layers.Dense(1)])
    tiny.compile(optimizer=keras.optimizers.SGD(keras.optimizers.schedules.CosineDecay(0.1, 20)),
                 loss="mse", steps_per_execution=2)
    syncs, lines, sync = [], [], tiny.jax_state_sync
    def counted():
        syncs.append(bool(getattr(tiny, "_jax_state", None)) and not tiny._jax_state_synced)
        sync()
    tiny.jax_state_sync = counted
    x = np.linspace(-1, 1, 60, dtype="float32").reshape(20, 3)
    tiny.fit(x, x[:, :1], batch_size=2, epochs=2, shuffle=False, verbose=0,
             callbacks=[NonFiniteGuard(), ProgressLogger(4, 20, lines.append)])
    tiny_fit = {"syncs": sum(syncs), "lines": lines}
print(json.dumps({"final_step": res["final_step"], "history": res["history"],
                  "backend": keras.backend.backend(), "tiny_fit": tiny_fit}))
"""


def _tf_model(name):
    build = {"stn": models.build_stn_homography,
             "sequence2": lambda: models.build_sequence_stn_homography(2),
             "homographynet": models.build_homographynet}[name]
    with narrow_network():
        model = build()
    rng = np.random.default_rng(len(name))
    for layer in model._flatten_layers():
        if layer.name == "fc2":  # identity-initialised: perturb so the output varies
            layer.kernel.assign(rng.normal(0, 1e-3, layer.kernel.shape).astype(np.float32))
    return model


@pytest.fixture(scope="module", params=BACKENDS)
def backend_run(request, tmp_path_factory, photo_patches):
    backend = request.param
    work = tmp_path_factory.mktemp(backend)
    rng = np.random.default_rng(3)
    images = np.stack(list(photo_patches.values()))[..., None].astype(np.float32)
    bars = [to_bar(paper_homography(rng)) for _ in range(len(images))]
    h8 = np.stack(bars).reshape(-1, 9)[:, :8].astype(np.float32)
    weights = rng.normal(size=images.shape).astype(np.float32)
    a = images[:2] / 255.0
    b = images[2:] / 255.0
    keras.utils.set_random_seed(0)
    tf_models = {name: _tf_model(name) for name in SAVED_MODELS}
    for name, model in tf_models.items():
        model.save(work / f"tf_{name}.keras")
    tf_models["stn"].save(work / "init.keras")  # the start of the training steps
    np.savez(work / "inputs.npz", images=images, h8=h8, weights=weights, a=a, b=b)
    img_dir = work / "images"
    img_dir.mkdir()
    for k, (_, path) in enumerate(bundled_photos.bundled_image_files()[:2]):
        shutil.copy(path, img_dir / f"{k}{os.path.splitext(path)[1]}")
    train = dict(image_dir=str(img_dir), samples_per_image=2, train_steps=2, warmup_steps=1,
                 batch_size=4, checkpoint_every=2, val_samples=0, learning_rate=0.01,
                 dropout=0.0, init_from=[str(work / "init.keras")])
    env = dict(os.environ, KERAS_BACKEND=backend, JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", BACKEND_SCRIPT, str(work), backend,
                           ",".join(SAVED_MODELS), json.dumps(NARROW_FILTERS), json.dumps(train)],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-4000:]
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    out = dict(np.load(work / f"{backend}_out.npz"))
    return {"backend": backend, "work": work, "summary": summary, "out": out, "images": images,
            "h8": h8, "bars": bars, "weights": weights, "a": a, "b": b, "tf_models": tf_models,
            "train": train}


def test_warp_matches_opencv_and_tensorflow(backend_run):
    warp = backend_run["out"]["warp"]
    m = norm_matrix()
    for i, h_bar in enumerate(backend_run["bars"]):
        h_pix = np.linalg.inv(m) @ h_bar @ m
        mask = inside_mask(h_pix)
        ref = cv2_warp(backend_run["images"][i, ..., 0], h_pix)
        assert np.abs(warp[i, ..., 0] - ref)[mask].mean() < 0.5
    tf_warp = keras.ops.convert_to_numpy(SpatialTransformer()([backend_run["images"],
                                                               backend_run["h8"]]))
    np.testing.assert_allclose(warp, tf_warp, atol=2e-3)


def test_gradient_matches_tensorflow(backend_run):
    h8 = tf.Variable(backend_run["h8"])
    with tf.GradientTape() as tape:
        loss = tf.reduce_sum(SpatialTransformer()([backend_run["images"], h8])
                             * backend_run["weights"])
    tf_grad = tape.gradient(loss, h8).numpy()
    grad = backend_run["out"]["grad"]
    assert np.abs(tf_grad).max() > 1.0  # a real, non-trivial gradient
    np.testing.assert_allclose(grad, tf_grad, rtol=2e-3, atol=1e-2 * np.abs(tf_grad).max())


@pytest.mark.parametrize("name", SAVED_MODELS)
def test_tensorflow_models_run_the_same_under_backend(backend_run, name):
    model = backend_run["tf_models"][name]
    outputs = [k for k in model.output_names if k.startswith("h_bar")]
    assert len(outputs) == (2 if name == "sequence2" else 1)
    for o in outputs:
        tf_out = runner.compiled_forward(model, o)(backend_run["a"], backend_run["b"])
        assert np.ptp(tf_out, axis=0).max() > 1e-4  # the perturbed model depends on its input
        np.testing.assert_allclose(backend_run["out"][f"tf_{name}:{o}"], tf_out, atol=1e-5)


def test_model_trained_under_backend_runs_under_tensorflow(backend_run):
    model = keras.models.load_model(backend_run["work"] / f"{backend_run['backend']}_run"
                                    / "model.keras", compile=False)
    back = runner.compiled_forward(model)(backend_run["a"], backend_run["b"])
    np.testing.assert_allclose(back, backend_run["out"]["trained"], atol=1e-5)
    # ... and training changed the output away from that of its start, init.keras.
    init = keras.models.load_model(backend_run["work"] / "init.keras", compile=False)
    assert np.abs(back - runner.compiled_forward(init)(backend_run["a"],
                                                       backend_run["b"])).max() > 1e-4


def test_training_steps_under_backend_match_tensorflow(backend_run, tmp_path):
    """The backend's two SGD steps (generated pairs, from init.keras's weights, no dropout) end
    where the same two steps under TensorFlow end, with the same losses on the way; the steps
    moved the weights. Measured (JAX on the 2-core CPU): the weights differ by 7e-6 of the
    distance they moved and the losses by 1e-7 (float32 reduction order), hence the bounds 1e-4;
    a step lost, or the start not taken from init.keras, differs by the whole distance."""
    s = backend_run["summary"]
    assert s["backend"] == backend_run["backend"] and s["final_step"] == 2
    run = backend_run["work"] / f"{backend_run['backend']}_run"
    assert (run / "checkpoint" / "ckpt-00000002.weights.h5").exists()
    cfg = train_config.TrainConfig(**backend_run["train"], model_dir=str(tmp_path / "tf_run"))
    with narrow_network():
        ref = training.train(cfg, printer=lambda *a: None)
    for key in ("loss", "h_bar_loss", "patch_a_warp_loss"):
        assert np.all(np.isfinite(s["history"][key])) and s["history"][key][0] > 0
        np.testing.assert_allclose(s["history"][key], ref["history"][key], rtol=1e-4,
                                   err_msg=key)
    got, want = (runner.load_model(d).get_weights() for d in (run, cfg.model_dir))
    init = keras.models.load_model(backend_run["work"] / "init.keras",
                                   compile=False).get_weights()
    assert len(got) == len(want) == len(init)
    moved = max(np.abs(w - i).max() for w, i in zip(want, init))
    assert moved > 1e-3
    assert max(np.abs(g - w).max() for g, w in zip(got, want)) <= 1e-4 * moved


def test_training_callbacks_copy_the_jax_state_back_only_where_they_print(backend_run):
    """Under JAX, reading the model inside a callback copies the whole training state back into
    it. A fit of 2 epochs x 5 calls (2 steps each) with the loop's per-step callbacks, reporting
    every 4 steps: the state is copied at the 5 reports and at the first epoch's end (the second
    ends on a report), not after each of the 10 calls; the reported steps and learning rates are
    the global step's and the schedule's for that step's update (Keras' CosineDecay under
    TensorFlow, at the step before)."""
    if backend_run["backend"] != "jax":
        pytest.skip("only the JAX backend copies its training state back into the model")
    tiny = backend_run["summary"]["tiny_fit"]
    steps = [4, 8, 12, 16, 20]
    assert [int(line.split()[1].split("/")[0]) for line in tiny["lines"]] == steps
    schedule = keras.optimizers.schedules.CosineDecay(0.1, 20)
    assert [line.split()[2] for line in tiny["lines"]] == [
        f"lr={float(schedule(s - 1)):.5g}" for s in steps]  # (the rate step s was made with)
    assert tiny["syncs"] == len(steps) + 1


HIDE_TENSORFLOW = '''
"""Hide TensorFlow, as on a GPU machine without it: imports fail, find_spec finds nothing."""
import importlib.abc
import importlib.util
import sys


class _HideTensorFlow(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "tensorflow" or name.startswith("tensorflow."):
            raise ModuleNotFoundError(f"No module named {name!r} (hidden)", name=name)
        return None


sys.meta_path.insert(0, _HideTensorFlow())
_find_spec = importlib.util.find_spec
importlib.util.find_spec = lambda name, package=None: (
    None if name.split(".")[0] == "tensorflow" else _find_spec(name, package))
'''


@pytest.mark.slow
@_needs("jax")
def test_gpu_recipe_trains_two_stages_without_tensorflow(tmp_path):
    """experiments/gpu_recipe.sh under JAX on a machine without TensorFlow: stage 1 from the
    folder, stage 2 from pairs made with stage 1's predictions, both packed to bring back."""
    hide = tmp_path / "hide"
    hide.mkdir()
    (hide / "sitecustomize.py").write_text(HIDE_TENSORFLOW)
    images = tmp_path / "images"
    images.mkdir()
    for k, (_, path) in enumerate(bundled_photos.bundled_image_files()[:2]):
        shutil.copy(path, images / f"{k}{os.path.splitext(path)[1]}")
    out = tmp_path / "gpu"
    env = dict(os.environ, PYTHONPATH=f"{hide}{os.pathsep}{ROOT}", JAX_PLATFORMS="cpu",
               PYTHON=sys.executable, STAGES="2", SAMPLES_PER_IMAGE="2", WORKERS="1",
               SKIP_LATENCY="1")
    env.pop("KERAS_BACKEND", None)  # the script's default: jax
    proc = subprocess.run(["bash", os.path.join(ROOT, "experiments", "gpu_recipe.sh"), str(images),
                           str(images), str(out), "--train_steps=2", "--warmup_steps=1",
                           "--checkpoint_every=2", "--batch_size=4", "--learning_rate=0.001"],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert "TensorFlow is not installed" in proc.stderr  # the hiding took effect
    assert re.search(r"stage-2 train pairs: \d+ made with context .* 1 previous stages loaded",
                     proc.stderr), proc.stderr[-4000:]
    for k in (1, 2):
        config = json.loads((out / f"stage{k}" / "config.json").read_text())
        assert config["stage"] == k
        assert config["prev_stages"] == ([str(out / "stage1")] if k == 2 else [])
        assert json.loads((out / f"stage{k}" / "result.json").read_text())["final_step"] == 2
        listing = subprocess.run(["tar", "-tzf", str(out / f"stage{k}.tar.gz")], check=True,
                                 capture_output=True, text=True).stdout.split()
        assert f"stage{k}/model.keras" in listing
        assert not any("checkpoint" in name for name in listing)


@pytest.mark.slow
@_needs("jax")
def test_semi_supervised_rows_run_in_memory_without_tensorflow(tmp_path):
    """experiments.semi_supervised --in_memory under JAX with TensorFlow hidden, as its rows run
    on the GPU machine (docs/gpu.md): the smoke budget's four rows train and are evaluated on
    pairs made in memory, and go to the repository folder."""
    hide = tmp_path / "hide"
    hide.mkdir()
    (hide / "sitecustomize.py").write_text(HIDE_TENSORFLOW)
    files = [path for _, path in bundled_photos.bundled_image_files()[:6]]
    for name, chosen in (("train", files[:4]), ("test", files[4:])):
        (tmp_path / name).mkdir()
        for k, path in enumerate(chosen):
            shutil.copy(path, tmp_path / name / f"{k}{os.path.splitext(path)[1]}")
    env = dict(os.environ, PYTHONPATH=f"{hide}{os.pathsep}{ROOT}", JAX_PLATFORMS="cpu",
               KERAS_BACKEND="jax")
    args = ["--budget=tiny", "--in_memory", f"--image_dir={tmp_path / 'train'}",
            f"--test_image_dir={tmp_path / 'test'}", f"--output_dir={tmp_path / 'out'}",
            f"--repo_dir={tmp_path / 'repo'}"]
    run_hidden = ("import importlib.util, runpy, sys\n"
                  "assert importlib.util.find_spec('tensorflow') is None  # hidden\n"
                  f"sys.argv = ['semi_supervised', *{args!r}]\n"
                  "runpy.run_module('experiments.semi_supervised', run_name='__main__')\n")
    proc = subprocess.run([sys.executable, "-c", run_hidden], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    result = json.loads((tmp_path / "out" / "semi_supervised.json").read_text())
    assert result["pairs"] == "in memory" and result["test_pairs"] == 6
    assert result["train_pairs_total"] == 8 and result["claim"]["verdict"] == "none"
    assert not (tmp_path / "out" / "data").exists()
    for row in result["rows"]:
        for d in row["model_dirs"]:
            config = json.loads((tmp_path / "out" / "models" / os.path.basename(d)
                                 / "config.json").read_text())
            assert config["in_memory"] and config["image_dir"] == str(tmp_path / "train")
            name = os.path.basename(d)
            assert (tmp_path / "repo" / f"{name}.keras").exists()
            assert json.loads((tmp_path / "repo" / "eval"
                               / f"{'stage1_alone' if name == 'stage1' else name}.json"
                               ).read_text())["in_memory"]
