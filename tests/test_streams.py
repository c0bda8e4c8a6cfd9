"""On-the-fly training streams (``--image_dir``): PairStream, materialize + ArrayStream, and
training from a folder of images, checked against the TFRecords make_dataset writes from the
same folder."""

import hashlib
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from stnh_tf.data import stage1
from stnh_tf.evaluation import mace as evaluation
from stnh_tf.training import config as train_config
from stnh_tf.training import streams as train_streams
from stnh_tf.training import loop as training
from stnh_tf.training import stage_estimates
from stnh_tf.data import batches
from stnh_tf.data import tfrecords as data
from stnh_tf.data import bundled_photos, pair_datasets, pairs, sources

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
N_IMAGES, PER_IMAGE, BATCH = 4, 3, 4  # 12 samples, 3 batches per data epoch


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """Four bundled photographs copied into a folder (the form users train from)."""
    d = tmp_path_factory.mktemp("images")
    for k, (_, path) in enumerate(bundled_photos.bundled_image_files()[:N_IMAGES]):
        shutil.copy(path, d / f"{k:02d}{os.path.splitext(path)[1]}")
    return str(d)


@pytest.fixture(scope="module")
def records(folder, tmp_path_factory):
    d = str(tmp_path_factory.mktemp("records"))
    log = lambda *a, **k: None
    stage1.make_dataset("folder", d, "train", image_dir=folder, seed=0, num_shards=1, log=log)
    stage1.make_dataset("folder", d, "test", image_dir=folder, seed=1, num_shards=1, log=log)
    return d


def _h(batch):
    return batch[1]["h_bar"]


def _rows(a):
    return sorted(map(tuple, np.round(a, 6)))


def test_pair_stream_epoch0_is_make_dataset_set_and_resume_positions(folder, records):
    stream = pair_datasets.PairStream(folder, BATCH, samples_per_image=PER_IMAGE, seed=0)
    stored = data.load_arrays(records, "train")
    epoch0 = np.concatenate([_h(stream[i]) for i in range(3)])
    assert _rows(epoch0) == _rows(stored["h_bar"])
    # Items of a stream started at step s are items s, s+1, ... of a stream started at 0,
    # across the data-epoch boundary (3 batches an epoch).
    resumed = pair_datasets.PairStream(folder, BATCH, samples_per_image=PER_IMAGE, seed=0,
                                       start_step=2)
    for i in range(4):
        np.testing.assert_array_equal(resumed[i][0]["patch_b"], stream[2 + i][0]["patch_b"])
    # Without fresh_pairs a later epoch repeats the same pairs in a new order.
    epoch1 = np.concatenate([_h(stream[i]) for i in range(3, 6)])
    assert _rows(epoch1) == _rows(epoch0)
    assert not np.array_equal(epoch1, epoch0)


def test_fresh_pairs_draw_new_samples_from_the_documented_rng(folder):
    stream = pair_datasets.PairStream(folder, BATCH, samples_per_image=PER_IMAGE, seed=5,
                                      fresh_pairs=True)
    b = stream.batches
    epoch0 = np.concatenate([_h(stream[i]) for i in range(3)])
    epoch1 = np.concatenate([_h(stream[i]) for i in range(3, 6)])
    assert not set(_rows(epoch1)) & set(_rows(epoch0))
    # Oracle: the first sample of epoch 1, rebuilt from pairs.draw_params with
    # default_rng([seed, image_index, epoch]).
    s = int(b.epoch_order(1)[0])
    pos, k = divmod(s, PER_IMAGE)
    index = b.entries[pos][0]
    params = pairs.draw_params(np.random.default_rng([5, index, 1]), b.protocol)[k]
    expect = pairs.make_pair(sources.as_gray_320x240(b.entries[pos][2]), params, b.protocol)
    np.testing.assert_allclose(stream[3][1]["h_bar"][0], expect["h_bar"], rtol=0, atol=1e-7)
    np.testing.assert_array_equal(stream[3][0]["patch_b"][0, ..., 0],
                                  expect["patch_b"].astype(np.float32) / 255.0)


@pytest.mark.parametrize("workers", [0, 2])
def test_array_stream_serves_the_pair_stream_batches(folder, workers):
    pair_batches = batches.PairBatches(folder, BATCH, samples_per_image=PER_IMAGE, seed=0)
    arrays = batches.materialize(pair_batches, workers=workers, chunk=5)
    assert arrays["patch_a"].shape == (12, 128, 128) and arrays["patch_a"].dtype == np.uint8
    assert arrays["h_bar"].shape == (12, 8) and arrays["h_mask"].shape == (12,)
    # Row s is sample s, exactly as make_pair generates it.
    np.testing.assert_array_equal(arrays["patch_b"][7], pair_batches.sample(7)["patch_b"])
    stream = pair_datasets.PairStream(folder, BATCH, samples_per_image=PER_IMAGE, seed=0,
                                      start_step=1)
    served = pair_datasets.ArrayStream(arrays, pair_batches, start_step=1)
    for i in range(7):  # epochs 0, 1 and 2
        for part_s, part_a in zip(stream[i], served[i]):
            for key in part_s:
                np.testing.assert_array_equal(part_a[key], part_s[key])
    with pytest.raises(ValueError, match="samples"):
        pair_datasets.ArrayStream({k: v[:5] for k, v in arrays.items()}, pair_batches)


@pytest.mark.parametrize("fresh", [False, True])
def test_pair_stream_workers_serve_the_in_process_batches(folder, fresh):
    """Worker processes (own pool, look-ahead) give item for item what the stream computes in
    this process: in order across data epochs, out of order, and after close()."""
    kwargs = dict(samples_per_image=PER_IMAGE, seed=3, start_step=2, fresh_pairs=fresh)
    local = pair_datasets.PairStream(folder, BATCH, **kwargs)
    remote = pair_datasets.PairStream(folder, BATCH, workers=2, prefetch=3, **kwargs)
    try:
        for i in [0, 1, 2, 3, 4, 6, 5, 0, 7]:
            for part_l, part_r in zip(local[i], remote[i]):
                for key in part_l:
                    np.testing.assert_array_equal(part_r[key], part_l[key])
        assert remote._pool is not None and set(remote._pending) == {10, 11}  # steps 2 + 8, 2 + 9
        state = remote.__getstate__()
        assert state["_pool"] is None and state["_pending"] == {}
        remote.close()
        assert remote._pool is None
        np.testing.assert_array_equal(remote[1][0]["patch_b"], local[1][0]["patch_b"])
    finally:
        remote.close()


LOADED_BACKENDS = "sorted({'keras', 'tensorflow', 'jax', 'torch'} & set(__import__('sys').modules))"

# A binary run as ``python -m``: its imports load Keras (as experiments.train_stage's do through
# stnh_tf.training.loop), which multiprocessing would re-run in every worker to rebuild
# ``__main__``.
BINARY = f"""
import json, sys
import keras
from stnh_tf.data import batches
if __name__ == "__main__":
    b = batches.PairBatches(sys.argv[1], 4, samples_per_image=1, seed=0)
    with batches.generator_pool(b, 1) as pool:
        print(json.dumps([pool.apply(eval, ({LOADED_BACKENDS!r},)),
                          pool.apply(eval,
                                     ("'stnh_tf.data.batches' in __import__('sys').modules",)),
                          batches.stack_samples([b.sample(0)])["patch_b"].tolist()
                          == pool.apply(batches._worker_samples,
                                        ((0, 1, False),))["patch_b"].tolist()]))
    print(json.dumps(sorted({{"keras"}} & set(sys.modules))))
"""


@pytest.mark.slow
def test_generator_workers_import_no_deep_learning_backend(folder, tmp_path):
    pair_batches = batches.PairBatches(folder, BATCH, samples_per_image=PER_IMAGE, seed=0)
    with batches.generator_pool(pair_batches, 1) as pool:
        loaded = pool.apply(eval, (LOADED_BACKENDS,))
        assert pool.apply(eval, ("'stnh_tf.data.batches' in __import__('sys').modules",))
    assert loaded == []
    # The same from a binary started with ``python -m`` whose own imports load Keras.
    (tmp_path / "fake_binary.py").write_text(BINARY)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), ROOT]))
    proc = subprocess.run([sys.executable, "-m", "fake_binary", folder], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    worker, main = [json.loads(line) for line in proc.stdout.strip().splitlines()[-2:]]
    assert main == ["keras"]  # the binary itself did load Keras
    assert worker == [[], True, True]


def test_config_needs_exactly_one_source():
    with pytest.raises(ValueError, match="exactly one"):
        train_config.TrainConfig(model_dir="m").validate()
    with pytest.raises(ValueError, match="exactly one"):
        train_config.TrainConfig(data_dir="d", image_dir="i", model_dir="m").validate()
    with pytest.raises(ValueError, match="previous stages"):
        train_config.TrainConfig(image_dir="i", model_dir="m", stage=2).validate()
    with pytest.raises(ValueError, match="in_memory"):
        train_config.TrainConfig(image_dir="i", model_dir="m", stage=2,
                                 prev_stages=("s1",)).validate()
    with pytest.raises(ValueError, match="prev_stages is for"):
        train_config.TrainConfig(data_dir="d", model_dir="m", stage=2,
                                 prev_stages=("s1",)).validate()
    train_config.TrainConfig(image_dir="i", model_dir="m", stage=2, prev_stages=("s1",),
                             in_memory=True).validate()


@pytest.mark.slow  # (a training run each: the make test time)
@pytest.mark.parametrize("in_memory", [False, True])
def test_train_from_image_folder_validates_on_make_dataset_test_pairs(folder, records, tmp_path,
                                                                       narrow, in_memory):
    """Training from a folder runs the paper's losses on generated pairs, and its validation
    pairs (seed 1, three per image) are exactly make_dataset's test split: the validation MACE
    equals the evaluation of the saved model on the TFRecords."""
    cfg = train_config.TrainConfig(image_dir=folder, val_image_dir=folder,
                                   model_dir=str(tmp_path / "m"),
                                   samples_per_image=PER_IMAGE, train_steps=2, warmup_steps=1,
                                   batch_size=BATCH, checkpoint_every=2, val_samples=12,
                                   learning_rate=0.01, in_memory=in_memory)
    result = training.train(cfg, printer=lambda *a: None)
    assert result["final_step"] == 2
    val_mace = result["history"]["val_h_bar_mace"][-1]
    evaluated = evaluation.evaluate([cfg.model_dir], records, "test")
    assert evaluated["count"] == 12
    assert val_mace == pytest.approx(evaluated["model"]["mace"], rel=1e-4)
    saved = json.loads((tmp_path / "m" / "config.json").read_text())
    assert saved["image_dir"] == folder and saved["in_memory"] is in_memory


@pytest.mark.parametrize("val_samples", [7, 12, 50])
def test_both_validation_sources_serve_exactly_val_samples_same_pairs(folder, records, val_samples):
    """From a folder or from TFRecords, validation runs on the first ``val_samples`` test pairs
    (all 12 when more are asked for), batch by batch the same ones: a count that is a multiple
    of neither 3 (pairs per image) nor the batch size included."""
    common = dict(model_dir="unused", batch_size=BATCH, val_samples=val_samples)
    generated = train_streams.generated_validation(
        train_config.TrainConfig(image_dir=folder, val_image_dir=folder, **common))
    stored, steps = train_streams.validation_stream(
        train_config.TrainConfig(data_dir=records, **common), "test")
    stored = list(stored.as_numpy_iterator())
    expected = min(val_samples, 12)
    assert steps == len(generated) == len(stored) == -(-expected // BATCH)
    for i, (x_t, y_t, _) in enumerate(stored):
        x_g, y_g, _ = generated[i]
        np.testing.assert_array_equal(x_g["patch_b"], x_t["patch_b"])
        np.testing.assert_allclose(y_g["h_bar"], y_t["h_bar"], atol=1e-6)
    assert sum(len(b[1]["h_bar"]) for b in stored) == expected


def _fake_stage(patch_a, patch_b):
    """A fixed, pair-dependent estimate, as a trained stage gives (no model)."""
    import zlib

    from stnh_tf import geometry

    out = []
    for b in patch_b:
        rng = np.random.default_rng(zlib.crc32(np.asarray(b).tobytes()))
        out.append(geometry.translation(*rng.uniform(-6, 6, 2)))
    return np.stack(out)


@pytest.fixture
def counted_stage(monkeypatch):
    """Finished stages loaded as :func:`_fake_stage`: the list of the batch sizes it was called
    with."""
    from stnh_tf.modeling import runner

    calls = []

    def stage(patch_a, patch_b):
        calls.append(len(patch_b))
        return _fake_stage(patch_a, patch_b)

    monkeypatch.setattr(runner, "load_model", lambda path: path)
    monkeypatch.setattr(runner, "predictor", lambda model, batch_size: stage)
    return calls


def test_stage_pairs_are_made_again_from_the_estimates_saved_in_the_run_folder(folder, tmp_path,
                                                                               counted_stage):
    """Stage-2 pairs in memory: the first call runs the stage and saves its estimates in the run
    folder; a second call (a resumed run) makes the same pairs from them without the stage; a
    changed stage file, or other pairs, run the stage again."""
    calls = counted_stage
    stage1 = tmp_path / "stage1.keras"
    stage1.write_bytes(b"stage 1")
    cfg = train_config.TrainConfig(image_dir=folder, model_dir=str(tmp_path / "run"), stage=2,
                                   prev_stages=(str(stage1),), samples_per_image=PER_IMAGE,
                                   batch_size=BATCH, in_memory=True, workers=0)

    def make(split="train", **kw):
        pb = batches.PairBatches(folder, BATCH, samples_per_image=PER_IMAGE, seed=0, **kw)
        return train_streams.stage_pairs(cfg, pb, split)

    first = make()
    assert sum(calls) == N_IMAGES * PER_IMAGE
    assert (tmp_path / "run" / "stage_estimates_train.npz").exists()
    calls.clear()
    again = make()
    assert calls == []
    for name in first:
        np.testing.assert_array_equal(again[name], first[name])
    make("val")  # the validation pairs: their own file
    assert sum(calls) == N_IMAGES * PER_IMAGE
    assert (tmp_path / "run" / "stage_estimates_val.npz").exists()
    calls.clear()
    stage1.write_bytes(b"stage 1, trained on")  # another stage
    make()
    assert sum(calls) == N_IMAGES * PER_IMAGE
    calls.clear()
    make(max_images=2)  # other pairs
    assert sum(calls) == 2 * PER_IMAGE


@pytest.mark.slow  # (3 s: three passes over 512 pairs; make test-all)
def test_stage_pairs_hold_one_slice_of_context_at_a_time(folder, tmp_path, monkeypatch,
                                                         counted_stage):
    """Stage-k pairs are made and re-made a slice at a time: the peak of NumPy's allocations stays
    below the result plus 3/4 of the whole set's context (holding the set with context at once, as
    before, cost far more: 22.7 GiB resident for stage 3's 184,800 pairs), and the pairs
    equal those re-made from the whole set at once, with a fresh run and with saved estimates."""
    import tracemalloc

    from stnh_tf import hierarchy

    per_image = 128  # 512 pairs, 18.9 MB of context
    calls = counted_stage
    monkeypatch.setattr(train_streams, "STAGE_SLICE", 16)
    stage1 = tmp_path / "stage1.keras"
    stage1.write_bytes(b"stage 1")
    cfg = train_config.TrainConfig(image_dir=folder, model_dir=str(tmp_path / "run"), stage=2,
                                   prev_stages=(str(stage1),), samples_per_image=per_image,
                                   batch_size=BATCH, in_memory=True, workers=0)
    pb = batches.PairBatches(folder, BATCH, samples_per_image=per_image, seed=0)
    whole = batches.materialize(pb, context=True)
    context_bytes = whole["context_a"].nbytes
    n = len(whole["patch_b"])
    old_key = hashlib.sha256(str(n).encode())  # the key as written before the slices (d947ff0^)
    old_key.update((np.round(whole["h_ba"], 6) + 0.0).tobytes())
    old_key.update(np.ascontiguousarray(whole["context_a"][::max(1, n // 64)]).tobytes())
    old_key.update(hashlib.sha256(b"stage 1").digest())
    reference, _ = hierarchy.next_stage_arrays(whole, [_fake_stage], estimates_dtype=np.float32)
    del whole
    for run in ("fresh", "saved estimates"):
        calls.clear()
        tracemalloc.start()
        try:
            pairs = train_streams.stage_pairs(cfg, pb)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        held = sum(v.nbytes for v in pairs.values())
        # measured: held + 0.45 x the context (the slice, its re-making's temporaries, the 64
        # contexts of the key); the whole set at once: held + 6.4 x the context
        assert peak < held + 0.75 * context_bytes, (run, peak, held, context_bytes)
        for name in pairs:
            np.testing.assert_array_equal(pairs[name], reference[name], err_msg=(run, name))
        assert sum(calls) == (n if run == "fresh" else 0), run
    # the committed stage-3 estimates were saved under the key of the whole set at once
    assert stage_estimates.saved_estimates_key(cfg.model_dir, "train") == old_key.hexdigest()


def test_materialize_slices_cover_the_set_in_order(folder):
    """Slices (rounded up to whole chunks) concatenate to materialize's arrays, in or out of
    worker processes."""
    pb = batches.PairBatches(folder, BATCH, samples_per_image=PER_IMAGE, seed=0)
    whole = batches.materialize(pb, context=True)
    for workers in (0, 2):
        for size, chunk, starts in ((5, 2, [0, 6]),  # 5 rounded up to 3 chunks of 2
                                    (5, 5, [0, 5, 10])):  # the last slice and chunk partial
            got = list(batches.materialize_slices(pb, workers, slice_size=size, chunk=chunk,
                                                  context=True))
            assert [a for a, _ in got] == starts
            for name in whole:
                np.testing.assert_array_equal(np.concatenate([s[name] for _, s in got]),
                                              whole[name])
    with pytest.raises(ValueError, match="slice_size"):
        next(batches.materialize_slices(pb, 0, slice_size=0))


EARLY_CLOSES = """
import contextlib, multiprocessing, sys
from stnh_tf.data import batches

pb = batches.PairBatches(sys.argv[1], 4, samples_per_image=3, seed=0)
for _ in range(3):
    with contextlib.closing(batches.materialize_slices(pb, 2, slice_size=1, chunk=1,
                                                       context=True)) as slices:
        next(slices)
        workers = multiprocessing.active_children()
        assert len(workers) == 2
    assert multiprocessing.active_children() == []
    assert [w.exitcode for w in workers] == [0, 0]  # they ended their tasks, not killed (-15)
print("closed")
"""


def test_materialize_slices_closed_early_stops_its_workers(folder):
    """A caller that stops after the first slice, with chunks still in flight, and closes the
    generator leaves no worker process running, each ended by itself (exit code 0, not killed),
    and is not left waiting: ``Pool.terminate`` there hung within 3-6 such closes (a worker
    killed while it held the result queue's lock), the run of the full suite with it. Closes
    in a child process (three: the exit codes fail the old code at the first), killed if it takes
    120 s."""
    child = subprocess.Popen([sys.executable, "-c", EARLY_CLOSES, folder], cwd=ROOT,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                             start_new_session=True)
    try:
        out, _ = child.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        os.killpg(child.pid, 9)  # the child's pool processes too
        child.communicate()
        pytest.fail("closing materialize_slices early hung")
    assert child.returncode == 0 and out.strip().endswith("closed"), out


@pytest.mark.slow  # (a binary end to end, 6-15 s; make test-all)
def test_stage2_from_image_folder_validates_on_make_stage_dataset_pairs(folder, records, tmp_path,
                                                                       narrow):
    """Stage 2 trains from the folder with the stage-1 model's predictions made in memory; its
    validation pairs are the stage-2 test records make_stage_dataset writes with that model."""
    from stnh_tf.data import stage_k

    common = dict(image_dir=folder, val_image_dir=folder, samples_per_image=PER_IMAGE,
                  train_steps=2, warmup_steps=1, batch_size=BATCH, checkpoint_every=2,
                  val_samples=12, learning_rate=0.01, in_memory=True)
    s1 = train_config.TrainConfig(model_dir=str(tmp_path / "s1"), **common)
    training.train(s1, printer=lambda *a: None)
    s2 = train_config.TrainConfig(model_dir=str(tmp_path / "s2"), stage=2,
                                  prev_stages=(s1.model_dir,), **common)
    result = training.train(s2, printer=lambda *a: None)
    assert result["final_step"] == 2
    r2 = str(tmp_path / "r2")
    stage_k.make_stage_dataset(2, records, r2, "test", model_dir=s1.model_dir, log=lambda *a: None)
    evaluated = evaluation.evaluate([s2.model_dir], r2, "test")
    assert evaluated["count"] == 12
    assert result["history"]["val_h_bar_mace"][-1] == pytest.approx(evaluated["model"]["mace"],
                                                                    rel=1e-3)
    saved = json.loads((tmp_path / "s2" / "config.json").read_text())
    assert saved["stage"] == 2 and saved["prev_stages"] == [s1.model_dir]


@pytest.mark.slow
def test_evaluate_scores_mixed_precision_models_in_float32_on_request(records, tmp_path):
    """``evaluate(compute_dtype="float32")`` scores a model saved in mixed bfloat16 as a float32
    build of the same weights, alone and as a 2-stage hierarchy; by default it runs as saved."""
    from conftest import keras_policy

    from stnh_tf.modeling import models

    rng = np.random.default_rng(5)
    with keras_policy("mixed_bfloat16"):
        mixed = models.build_stn_homography()
    fc2 = mixed.get_layer("regression").get_layer("fc2")
    kernel, bias = fc2.get_weights()
    fc2.set_weights([rng.normal(0, 2e-3, kernel.shape).astype(np.float32), bias])
    reference = models.build_stn_homography()
    reference.set_weights(mixed.get_weights())
    for name, model in (("mixed", mixed), ("reference", reference)):
        os.makedirs(tmp_path / name)
        model.save(tmp_path / name / "model.keras")
    m, r = str(tmp_path / "mixed"), str(tmp_path / "reference")

    as_f32 = evaluation.evaluate([m], records, "test", compute_dtype="float32")["model"]
    ref = evaluation.evaluate([r], records, "test")["model"]
    assert as_f32["count"] == 12
    assert as_f32["mace"] == pytest.approx(ref["mace"], abs=1e-5)
    as_saved = evaluation.evaluate([m], records, "test")["model"]
    assert as_saved["mace"] != pytest.approx(ref["mace"], abs=1e-6)  # bfloat16 rounding
    h2 = evaluation.evaluate([m, m], records, "test", compute_dtype="float32")["model"]["stages"]
    h2_ref = evaluation.evaluate([r, r], records, "test")["model"]["stages"]
    assert h2["after_2_stages"]["mace"] == pytest.approx(h2_ref["after_2_stages"]["mace"], abs=1e-4)


def test_the_stream_benchmark_reads_the_first_max_images_photographs(folder):
    """experiments.benchmark_stream --max_images: the pairs it times (in process, from the
    stream alone, and the inputs of model.fit) come from the first N photographs only."""
    from stnh_tf.evaluation import benchmarks

    result = benchmarks.stream_benchmark([folder], workers=0, samples_per_image=2, batch_size=2,
                                         alone_batches=1, modes=(), max_images=2)
    assert (result["images"], result["max_images"]) == (2, 2)
    pb = batches.PairBatches([folder], 2, samples_per_image=2, max_images=2)
    for mode in ("stream", "fresh"):
        stream = benchmarks._fit_inputs(mode, pb, [folder], 2, 0, 2, 0, False, max_images=2)
        assert [e[1] for e in stream.batches.entries] == [e[1] for e in pb.entries]
        assert len(pb.entries) == 2
