"""Keras backend portability: the layers, models and training under ``KERAS_BACKEND=jax``.

The suite runs under TensorFlow; the JAX side runs in one subprocess (the backend is chosen at
Keras' import). References: OpenCV for the warp, the TensorFlow backend for the values and
gradients (themselves checked against OpenCV and finite differences in test_layers), and models
saved under each backend loaded under the other; and ``experiments/gpu_recipe.sh`` end to end
(two stages) with TensorFlow hidden, as on the GPU machine. Skipped, with the reason, where JAX is
not installed (``pip install "jax[cpu]"``; the test extra installs it).
"""

import importlib.util
import json
import os
import shutil
import subprocess
import sys

import keras
import numpy as np
import pytest
import tensorflow as tf

from conftest import cv2_warp, inside_mask, norm_matrix, paper_homography, to_bar
from stnh_tf import models, sources
from stnh_tf.layers import SpatialTransformer

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

pytestmark = pytest.mark.skipif(importlib.util.find_spec("jax") is None,
                                reason="JAX is not installed: backend portability not tested")

JAX_SCRIPT = r"""
import json, os, sys
os.environ["KERAS_BACKEND"] = "jax"
import jax, keras, numpy as np
from stnh_tf import evaluation, training
from stnh_tf.layers import SpatialTransformer
assert keras.backend.backend() == "jax"
work = sys.argv[1]
z = np.load(os.path.join(work, "inputs.npz"))
out = {}
# Layer forward and the gradient of a weighted sum of the warp w.r.t. H_bar.
stn = SpatialTransformer()
out["warp"] = np.asarray(stn([z["images"], z["h8"]]))
def f(h8):
    return (stn([z["images"], h8]) * z["weights"]).sum()
out["grad"] = np.asarray(jax.grad(f)(z["h8"]))
# A model saved under TensorFlow, run under JAX.
m = keras.models.load_model(os.path.join(work, "tf_model.keras"), compile=False)
out["tf_model_under_jax"] = evaluation.compiled_forward(m)(z["a"], z["b"])
# Two training steps under JAX from a folder of images, pairs generated on the fly.
cfg = training.TrainConfig(image_dir=os.path.join(work, "images"), model_dir=os.path.join(work, "jax_run"),
                           samples_per_image=2, train_steps=2, warmup_steps=1, batch_size=4,
                           checkpoint_every=2, val_samples=0, learning_rate=0.01)
res = training.train(cfg, printer=lambda *a: None)
m2 = keras.models.load_model(os.path.join(cfg.model_dir, "model.keras"), compile=False)
out["jax_model_under_jax"] = evaluation.compiled_forward(m2)(z["a"], z["b"])
np.savez(os.path.join(work, "jax_out.npz"), **out)
print(json.dumps({"final_step": res["final_step"], "loss": res["history"]["loss"][-1],
                  "backend": keras.backend.backend()}))
"""


@pytest.fixture(scope="module")
def jax_run(tmp_path_factory, photo_patches):
    work = tmp_path_factory.mktemp("backends")
    rng = np.random.default_rng(3)
    images = np.stack(list(photo_patches.values()))[..., None].astype(np.float32)
    bars = [to_bar(paper_homography(rng)) for _ in range(len(images))]
    h8 = np.stack(bars).reshape(-1, 9)[:, :8].astype(np.float32)
    weights = rng.normal(size=images.shape).astype(np.float32)
    a = images[:2] / 255.0
    b = images[2:] / 255.0
    keras.utils.set_random_seed(0)
    tf_model = models.build_stn_homography()
    tf_model.save(work / "tf_model.keras")
    np.savez(work / "inputs.npz", images=images, h8=h8, weights=weights, a=a, b=b)
    img_dir = work / "images"
    img_dir.mkdir()
    for k, (_, path) in enumerate(sources.bundled_image_files()[:2]):
        shutil.copy(path, img_dir / f"{k}{os.path.splitext(path)[1]}")
    env = dict(os.environ, KERAS_BACKEND="jax", JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", JAX_SCRIPT, str(work)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-4000:]
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    out = dict(np.load(work / "jax_out.npz"))
    return {"work": work, "summary": summary, "out": out, "images": images, "h8": h8,
            "bars": bars, "weights": weights, "a": a, "b": b, "tf_model": tf_model}


def test_jax_warp_matches_opencv_and_tensorflow(jax_run):
    warp = jax_run["out"]["warp"]
    m = norm_matrix()
    for i, h_bar in enumerate(jax_run["bars"]):
        h_pix = np.linalg.inv(m) @ h_bar @ m
        mask = inside_mask(h_pix)
        ref = cv2_warp(jax_run["images"][i, ..., 0], h_pix)
        assert np.abs(warp[i, ..., 0] - ref)[mask].mean() < 0.5
    tf_warp = keras.ops.convert_to_numpy(SpatialTransformer()([jax_run["images"], jax_run["h8"]]))
    np.testing.assert_allclose(warp, tf_warp, atol=2e-3)


def test_jax_gradient_matches_tensorflow(jax_run):
    h8 = tf.Variable(jax_run["h8"])
    with tf.GradientTape() as tape:
        loss = tf.reduce_sum(SpatialTransformer()([jax_run["images"], h8]) * jax_run["weights"])
    tf_grad = tape.gradient(loss, h8).numpy()
    grad = jax_run["out"]["grad"]
    assert np.abs(tf_grad).max() > 1.0  # a real, non-trivial gradient
    np.testing.assert_allclose(grad, tf_grad, rtol=2e-3, atol=1e-2 * np.abs(tf_grad).max())


def test_weights_move_between_backends(jax_run):
    from stnh_tf import evaluation

    # TensorFlow-saved model under JAX == under TensorFlow.
    tf_out = evaluation.compiled_forward(jax_run["tf_model"])(jax_run["a"], jax_run["b"])
    np.testing.assert_allclose(jax_run["out"]["tf_model_under_jax"], tf_out, atol=1e-5)
    # JAX-trained model under TensorFlow == under JAX.
    model = keras.models.load_model(jax_run["work"] / "jax_run" / "model.keras", compile=False)
    back = evaluation.compiled_forward(model)(jax_run["a"], jax_run["b"])
    np.testing.assert_allclose(back, jax_run["out"]["jax_model_under_jax"], atol=1e-5)
    # ... and training changed the output away from the identity initialisation.
    assert np.abs(back).max() > 0 and not np.allclose(back, tf_out)


def test_training_steps_under_jax(jax_run):
    s = jax_run["summary"]
    assert s["backend"] == "jax" and s["final_step"] == 2 and np.isfinite(s["loss"])
    assert (jax_run["work"] / "jax_run" / "checkpoint" / "ckpt.weights.h5").exists()


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


def test_gpu_recipe_trains_two_stages_without_tensorflow(tmp_path):
    """experiments/gpu_recipe.sh under JAX on a machine without TensorFlow: stage 1 from the
    folder, stage 2 from pairs made with stage 1's predictions, both packed to bring back."""
    hide = tmp_path / "hide"
    hide.mkdir()
    (hide / "sitecustomize.py").write_text(HIDE_TENSORFLOW)
    images = tmp_path / "images"
    images.mkdir()
    for k, (_, path) in enumerate(sources.bundled_image_files()[:2]):
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
    assert "stage-2 pairs from 1 previous stages" in proc.stderr
    for k in (1, 2):
        config = json.loads((out / f"stage{k}" / "config.json").read_text())
        assert config["stage"] == k
        assert config["prev_stages"] == ([str(out / "stage1")] if k == 2 else [])
        assert json.loads((out / f"stage{k}" / "result.json").read_text())["final_step"] == 2
        listing = subprocess.run(["tar", "-tzf", str(out / f"stage{k}.tar.gz")], check=True,
                                 capture_output=True, text=True).stdout.split()
        assert f"stage{k}/model.keras" in listing
        assert not any("checkpoint" in name for name in listing)
