"""Training options beside the paper's recipe: the optimizer table, weight decay, gradient-norm
clipping, the L2 reduction, the named presets; the photometric change of patch_b; training and
data generation from several image folders."""

import json
import os
import shutil
import subprocess
import sys

import cv2
import keras
import numpy as np
import pytest

from stnh_tf.data import stage1
from stnh_tf.training import run_dir
from stnh_tf.training import config as train_config
from stnh_tf.training import loop as training
from stnh_tf.training import presets
from stnh_tf.data import batches
from stnh_tf.data import tfrecords as data
from stnh_tf.data import pairs, sources
from stnh_tf.data import bundled_photos
from stnh_tf.modeling import models, runner

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PHOTO = pairs.PhotometricChange()


def _quiet(*args, **kwargs):
    pass


@pytest.fixture(scope="module")
def two_folders(tmp_path_factory):
    """Two folders of two bundled photographs each, with the same file names in both."""
    files = [p for _, p in bundled_photos.bundled_image_files()[:4]]
    out = []
    for k in range(2):
        d = tmp_path_factory.mktemp(f"folder{k}")
        for j, path in enumerate(files[2 * k:2 * k + 2]):
            shutil.copy(path, d / f"{j:02d}{os.path.splitext(path)[1]}")
        out.append(str(d))
    return out


# ------------------------------------------------------------------------------------------------
# Optimizers, L2 reduction, presets
# ------------------------------------------------------------------------------------------------
def test_compiled_optimizer_is_the_named_one_with_its_settings():
    base = dict(data_dir="d", model_dir="m", warmup_steps=0, train_steps=100)
    model = models.build_stn_homography()
    training.compile_model(model, train_config.TrainConfig(**base))
    sgd = model.optimizer
    assert type(sgd) is keras.optimizers.SGD and sgd.momentum == pytest.approx(0.9)
    assert sgd.weight_decay is None and sgd.global_clipnorm is None
    assert float(sgd.learning_rate) == pytest.approx(0.05)

    cfg = train_config.TrainConfig(**base, optimizer="adamw", learning_rate=1e-3, weight_decay=1e-4,
                                   clipnorm=2.0)
    training.compile_model(model, cfg)
    adamw = model.optimizer
    assert type(adamw) is keras.optimizers.AdamW
    assert adamw.weight_decay == pytest.approx(1e-4) and adamw.global_clipnorm == pytest.approx(2.0)
    assert float(adamw.learning_rate) == pytest.approx(1e-3)
    # AdamW without a weight decay decays nothing (Keras' own default would be 0.004).
    assert training.build_optimizer(
        train_config.TrainConfig(**base, optimizer="adamw")).weight_decay == 0
    adam = training.build_optimizer(train_config.TrainConfig(**base, optimizer="adam"))
    assert type(adam) is keras.optimizers.Adam and adam.weight_decay is None


def test_clipnorm_bounds_the_update_and_weight_decay_shrinks_weights():
    """One SGD step (no momentum) on a known gradient: the step is lr * clipped gradient, then
    the decoupled decay multiplies the variable by (1 - lr * wd)."""
    base = dict(data_dir="d", model_dir="m", warmup_steps=0, train_steps=100, momentum=0.0,
                learning_rate=0.1)
    grad = np.array([3.0, 4.0], np.float32)  # norm 5
    for clip, wd, expected_step in ((0.0, 0.0, 0.1 * grad), (1.0, 0.0, 0.1 * grad / 5.0),
                                    (0.0, 0.5, 0.1 * grad)):
        var = keras.Variable(np.array([1.0, -2.0], np.float32))
        opt = training.build_optimizer(train_config.TrainConfig(**base, clipnorm=clip,
                                                                weight_decay=wd))
        opt.apply_gradients([(keras.ops.convert_to_tensor(grad), var)])
        decayed = np.array([1.0, -2.0]) * (1.0 - 0.1 * wd)
        np.testing.assert_allclose(np.asarray(var), decayed - expected_step, rtol=1e-6)


def test_l2_sum_is_eight_times_the_mean_on_a_known_batch():
    """The compiled total loss is l1 + l2_mean (paper default) or l1 + 8 * l2_mean, with both
    terms recomputed in NumPy from the model's predictions."""
    x, y, _ = batches.PairBatches("bundled", 8, samples_per_image=4, max_images=2, seed=3).batch(0)
    model = models.build_stn_homography()
    fc2 = model.get_layer("regression").get_layer("fc2")
    kernel, bias = fc2.get_weights()
    fc2.set_weights([np.random.default_rng(0).normal(0, 1e-3, kernel.shape).astype(np.float32),
                     bias])
    pred = model.predict(x, verbose=0)
    l2_mean = np.mean((pred["h_bar"] - y["h_bar"]) ** 2)
    l2_sum = np.mean(np.sum((pred["h_bar"] - y["h_bar"]) ** 2, axis=-1))
    l1 = np.mean(np.abs(pred["patch_a_warp"] - y["patch_a_warp"]))
    assert l2_sum == pytest.approx(8 * l2_mean, rel=1e-6)
    for reduction, expected in (("mean", l1 + l2_mean), ("sum", l1 + l2_sum)):
        training.compile_model(model, train_config.TrainConfig(data_dir="d", model_dir="m",
                                                               l2_reduction=reduction))
        loss = model.evaluate(x, y, verbose=0, return_dict=True)["loss"]
        assert loss == pytest.approx(expected, rel=1e-4)


@pytest.mark.parametrize("field, value, message", [
    ("optimizer", "rmsprop", "optimizer must be one of"),
    ("weight_decay", -1e-4, "weight_decay must be"),
    ("weight_decay", float("nan"), "weight_decay must be"),
    ("clipnorm", -1.0, "clipnorm must be"),
    ("learning_rate", 0.0, "learning_rate must be"),
    ("l2_reduction", "max", "l2_reduction must be one of"),
    ("recipe", "turbo", "recipe must be one of"),
    ("image_dir", " , ", "image_dir names no folder"),
    ("input_norm", "batch", "input_norm must be one of"),
])
def test_bad_recipe_values_are_clear_errors(field, value, message):
    kw = {"image_dir": "imgs"} if field != "image_dir" else {}
    cfg = train_config.TrainConfig(model_dir="m", **kw, **{field: value})
    with pytest.raises(ValueError, match=message):
        cfg.validate()


def test_four_point_models_keep_their_input_scaling():
    cfg = train_config.TrainConfig(image_dir="imgs", model_dir="m", model="homographynet_gap",
                                   input_norm="patch")
    with pytest.raises(ValueError, match="input_norm must be 'unit'"):
        cfg.validate()


def test_photometric_needs_generated_pairs():
    with pytest.raises(ValueError, match="make_dataset --photometric"):
        train_config.TrainConfig(data_dir="d", model_dir="m", photometric=True).validate()


def _train_binary(args):
    return subprocess.run([sys.executable, "-m", "experiments.train_stage", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)


@pytest.mark.slow
def test_binary_recipe_preset_then_explicit_flags_and_bad_values(two_folders, tmp_path):
    """``--recipe=fast`` sets its preset, a flag given explicitly wins, config.json records the
    resolved values; a bad value fails before anything is written. (Slow: two binary runs. The
    fast suite has the presets' resolution in test_flags and test_homographynet_recipe, the
    binary's training and its refusal of a bad flag in test_training.)"""
    model_dir = tmp_path / "fast"
    res = _train_binary([f"--image_dir={','.join(two_folders)}", f"--model_dir={model_dir}",
                         "--recipe=fast", "--learning_rate=5e-4", "--train_steps=1",
                         "--warmup_steps=0", "--batch_size=4", "--checkpoint_every=1",
                         "--val_samples=0", "--photometric"])
    assert res.returncode == 0, res.stderr[-3000:]
    saved = json.loads((model_dir / "config.json").read_text())
    fast = presets.RECIPES["fast"]
    assert saved["recipe"] == "fast" and saved["optimizer"] == fast["optimizer"] == "adamw"
    assert saved["weight_decay"] == fast["weight_decay"] and saved["learning_rate"] == 5e-4
    assert saved["warmup_steps"] == 0 and saved["photometric"] is True
    assert saved["image_dir"] == ",".join(two_folders)

    bad = tmp_path / "bad"
    res = _train_binary([f"--image_dir={two_folders[0]}", f"--model_dir={bad}",
                         "--weight_decay=-1", "--train_steps=1", "--warmup_steps=0",
                         "--checkpoint_every=1"])
    assert res.returncode != 0 and "weight_decay must be" in res.stderr
    assert not bad.exists()


@pytest.mark.slow
def test_resume_with_the_new_options_matches_the_uninterrupted_run(two_folders, tmp_path, narrow):
    """AdamW + clipping + L2 sum + photometric fresh pairs from two folders: interrupted after
    the step-4 checkpoint and resumed, the run ends with the uninterrupted run's weights. (Slow:
    three runs. The fast suite resumes the paper's recipe in test_training and positions the
    generated streams, fresh pairs included, in test_streams.)"""
    def cfg(name):
        return train_config.TrainConfig(
            image_dir=",".join(two_folders), model_dir=str(tmp_path / name), optimizer="adamw",
            learning_rate=1e-3, weight_decay=1e-4, clipnorm=1.0, l2_reduction="sum",
            photometric=True, fresh_pairs=True, samples_per_image=2, batch_size=4,
            train_steps=6, warmup_steps=2, checkpoint_every=2, log_every=1, val_samples=0)

    training.train(cfg("straight"), printer=_quiet)

    class Interrupt(keras.callbacks.Callback):
        def on_epoch_end(self, epoch, logs=None):
            if epoch == 1:
                raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        training.train(cfg("resumed"), printer=_quiet, extra_callbacks=[Interrupt()])
    lines = []
    training.train(cfg("resumed"), printer=lines.append)
    assert any("resuming" in ln and "step 4" in ln for ln in lines)
    straight = runner.load_model(str(tmp_path / "straight")).get_weights()
    resumed = runner.load_model(str(tmp_path / "resumed")).get_weights()
    for a, b in zip(straight, resumed):
        np.testing.assert_array_equal(a, b)


def test_run_without_the_new_fields_resumes_as_the_paper_recipe(tmp_path):
    """A config.json written before the recipe fields existed is the paper's recipe."""
    cfg = train_config.TrainConfig(data_dir="d", model_dir=str(tmp_path))
    legacy = {k: v for k, v in cfg.to_json().items()
              if k not in ("optimizer", "weight_decay", "clipnorm", "l2_reduction", "photometric",
                           "recipe")}
    (tmp_path / "config.json").write_text(json.dumps(legacy))
    assert run_dir._config_diff(cfg, str(tmp_path / "config.json")) == {}
    adam = train_config.TrainConfig(data_dir="d", model_dir=str(tmp_path), optimizer="adam")
    assert run_dir._config_diff(adam, str(tmp_path / "config.json")) == {
        "optimizer": ("sgd", "adam")}


# ------------------------------------------------------------------------------------------------
# Photometric change of patch_b
# ------------------------------------------------------------------------------------------------
def _image(k=0):
    return sources.as_gray_320x240(bundled_photos.bundled_image_files()[k][1])


def test_photometric_pairs_keep_the_geometry():
    """Same seed with and without the change: same squares, perturbations, h_ba, patch_a,
    patch_a_t and context; patch_b is the plain patch_b changed. And the true H still aligns
    the pair: patch_a warped by h_ba (OpenCV) and changed the same way (noise aside) matches the
    changed patch_b inside the warp, where the identity does not."""
    image = _image()
    plain = pairs.draw_params(pairs.image_rng(7, 0), pairs.Protocol())
    changed = pairs.draw_params(pairs.image_rng(7, 0), pairs.Protocol(photometric=PHOTO))
    protocol = pairs.Protocol(photometric=PHOTO)
    for p, c in zip(plain, changed):
        assert (p.x0, p.y0) == (c.x0, c.y0) and np.array_equal(p.offsets, c.offsets)
        a, b = pairs.make_pair(image, p), pairs.make_pair(image, c, protocol)
        for key in ("patch_a", "patch_a_t", "context_a", "h_ba", "h_bar", "square_xy"):
            np.testing.assert_array_equal(a[key], b[key])
        np.testing.assert_array_equal(b["patch_b"], pairs.apply_photometric(a["patch_b"],
                                                                            c.photometric))
        assert np.abs(a["patch_b"].astype(int) - b["patch_b"]).mean() > 1.0
        warped = cv2.warpPerspective(a["patch_a"], a["h_ba"], (128, 128),
                                     flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
        inside = cv2.warpPerspective(np.full((128, 128), 255, np.uint8), a["h_ba"], (128, 128),
                                     flags=cv2.WARP_INVERSE_MAP | cv2.INTER_NEAREST) == 255
        inside = cv2.erode(inside.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        noiseless = c.photometric[:3] + (0.0, 0)
        expected = pairs.apply_photometric(warped, noiseless).astype(float)
        aligned = np.abs(expected - b["patch_b"])[inside].mean()
        unaligned = np.abs(pairs.apply_photometric(a["patch_a"], noiseless).astype(float)
                           - b["patch_b"])[inside].mean()
        sigma = c.photometric[3] * 255
        assert aligned < 2.0 + 1.0 * sigma, (aligned, sigma)
        assert unaligned > 3 * aligned


def test_photometric_draws_are_seeded_and_within_their_ranges():
    protocol = pairs.Protocol(samples_per_image=8, photometric=PHOTO)
    draws = np.array([prm.photometric[:4] for i in range(100)
                      for prm in pairs.draw_params(pairs.image_rng(0, i), protocol)])
    gamma, contrast, brightness, sigma = draws.T
    assert gamma.min() >= 1 / 1.5 and gamma.max() <= 1.5
    assert gamma.min() < 1 / 1.45 and gamma.max() > 1.45  # the whole range is used
    assert abs(np.mean(np.log(gamma))) < 0.05  # log-uniform about 1
    assert contrast.min() >= 0.7 and contrast.max() <= 1.3 and np.ptp(contrast) > 0.55
    assert brightness.min() >= -0.15 and brightness.max() <= 0.15 and np.ptp(brightness) > 0.27
    assert sigma.min() >= 0 and sigma.max() <= 0.02 and sigma.max() > 0.019
    again = pairs.draw_params(pairs.image_rng(0, 3), protocol)
    first = pairs.draw_params(pairs.image_rng(0, 3), protocol)
    assert [p.photometric for p in again] == [p.photometric for p in first]
    other = pairs.draw_params(pairs.image_rng(1, 3), protocol)
    assert [p.photometric for p in other] != [p.photometric for p in first]
    # The noise itself is seeded: the same change gives the same pixels.
    patch = _image()[:128, :128]
    change = first[0].photometric
    np.testing.assert_array_equal(pairs.apply_photometric(patch, change),
                                  pairs.apply_photometric(patch, change))


def test_apply_photometric_matches_its_formula():
    patch = np.arange(256, dtype=np.uint8).reshape(16, 16)
    x = patch / 255.0
    expected = np.clip(np.rint(((x ** 1.3 - 0.5) * 0.8 + 0.5 - 0.1) * 255), 0, 255)
    np.testing.assert_allclose(pairs.apply_photometric(patch, (1.3, 0.8, -0.1, 0.0, 0)),
                               expected, atol=1)
    np.testing.assert_array_equal(pairs.apply_photometric(patch, (1.0, 1.0, 0.0, 0.0, 0)), patch)


def test_make_dataset_and_generated_batches_give_the_same_photometric_pairs(two_folders,
                                                                             tmp_path):
    """``make_dataset --photometric`` over two folders writes the pairs ``PairBatches`` makes
    from the same folders, and records the change in metadata.json; the unchanged split has the
    same geometry."""
    out, plain = str(tmp_path / "photo"), str(tmp_path / "plain")
    stage1.make_dataset("folder", out, "test", image_dir=",".join(two_folders), seed=1,
                        num_shards=1, log=_quiet, photometric=True)
    stage1.make_dataset("folder", plain, "test", image_dir=two_folders, seed=1, num_shards=1,
                        log=_quiet)
    meta = data.read_metadata(out)["splits"]["test"]
    assert meta["protocol"]["photometric"] == {"gamma_max": 1.5, "contrast_range": 0.3,
                                               "brightness_range": 0.15, "noise_max": 0.02}
    assert data.read_metadata(plain)["splits"]["test"]["protocol"]["photometric"] is None
    stored, stored_plain = data.load_arrays(out, "test"), data.load_arrays(plain, "test")
    generated = batches.PairBatches(two_folders, 12, seed=1, shuffle=False,
                                 photometric=True).batch(0)
    np.testing.assert_array_equal(generated[0]["patch_b"], stored["patch_b"])
    np.testing.assert_array_equal(stored["h_bar"], stored_plain["h_bar"])
    np.testing.assert_array_equal(stored["patch_a"], stored_plain["patch_a"])
    assert not np.array_equal(stored["patch_b"], stored_plain["patch_b"])


# ------------------------------------------------------------------------------------------------
# Several image folders
# ------------------------------------------------------------------------------------------------
def test_several_folders_are_listed_folder_after_folder(two_folders):
    one = sources.scan_image_folder(two_folders[0])
    assert sources.scan_image_folders(two_folders[0]) == one
    assert sources.scan_image_folders([two_folders[0]]) == one
    both = sources.scan_image_folders(",".join(two_folders))
    second = sources.scan_image_folder(two_folders[1])
    assert both.files == one.files + second.files
    assert [both.image_id(p) for p in both.files] == (
        [f"0:{os.path.basename(p)}" for p in one.files]
        + [f"1:{os.path.basename(p)}" for p in second.files])
    # The same folder twice lists its images once.
    assert sources.scan_image_folders(two_folders[:1] * 2).files == one.files
    pair_batches = batches.PairBatches(two_folders, 4, samples_per_image=3)
    assert pair_batches.num_samples == 12
    assert [e[1] for e in pair_batches.entries] == [both.image_id(p) for p in both.files]
    for spec in ("", ",", [], " , "):
        with pytest.raises(sources.SourceError, match="no image folder"):
            sources.split_folders(spec)
    with pytest.raises(sources.SourceError, match="does not exist"):
        sources.scan_image_folders([two_folders[0], two_folders[0] + "-missing"])
