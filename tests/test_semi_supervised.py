"""Training with missing labels (issue 47): ``label_fraction``, ``drop_unlabeled`` and
``unlabeled_image_dir``. The labeled pairs are the asked share, seeded, the same from TFRecords
and from generated pairs (streamed, fresh, in memory, stage k); an unlabeled pair's H_bar never
reaches the loss; an all-unlabeled run is the L1 loss alone; an unlabeled pair costs the same
computation as a labeled one."""

import json
import os
import shutil

import keras
import numpy as np
import pytest
import tensorflow as tf

from stnh_tf.data import batches, labels, sources, stage1
from stnh_tf.data import tfrecords as data
from stnh_tf.modeling import runner
from stnh_tf.training import config as train_config
from stnh_tf.training import loop as training
from stnh_tf.training import model_kinds
from stnh_tf.training import streams


def _quiet(*args, **kwargs):
    pass


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    """Bundled photographs, 4 images x 3 pairs (train, two shards) and 4 x 3 (test)."""
    d = str(tmp_path_factory.mktemp("semi_data"))
    stage1.make_dataset("bundled", d, "train", seed=0, num_shards=2, max_images=4, log=_quiet)
    stage1.make_dataset("bundled", d, "test", seed=1, num_shards=1, max_images=4, log=_quiet)
    return d


def _cfg(data_dir, model_dir, **kw):
    base = dict(data_dir=data_dir, model_dir=str(model_dir), train_steps=1, warmup_steps=0,
                batch_size=12, checkpoint_every=1, log_every=1, val_samples=0,
                learning_rate=0.01)
    base.update(kw)
    return train_config.TrainConfig(**base)


def _weights(model_dir):
    return [np.asarray(w) for w in runner.load_model(str(model_dir)).get_weights()]


# -- the draw ----------------------------------------------------------------------------------
def _reference_draw(seed, i):
    """The label draw written out with Python integers (mod 2**32 explicitly)."""
    def mix(x):
        x ^= x >> 16
        x = (x * 0x7FEB352D) % 2**32
        x ^= x >> 15
        x = (x * 0x6C8E9CF5) % 2**32
        return x ^ (x >> 16)

    s = mix((seed ^ 0x6C61626C) % 2**32)
    return mix(mix((i % 2**32) ^ s))


def test_label_draw_is_seeded_and_keeps_the_asked_share():
    idx = np.arange(200_000)
    for seed in (0, 7):
        want = [_reference_draw(seed, int(i)) for i in idx[:3000]]
        assert labels.label_draws(seed, idx[:3000]).tolist() == want
    for f in (0.1, 0.5, 0.9):
        share = labels.labeled(3, idx, f).mean()
        assert abs(share - f) < 4 * np.sqrt(f * (1 - f) / len(idx)), (f, share)
    # Nested in the fraction; another seed draws another set (overlap ~ F^2, independent).
    a, b = labels.labeled(0, idx, 0.1), labels.labeled(0, idx, 0.2)
    assert np.all(b[a]) and b.sum() > a.sum()
    other = labels.labeled(1, idx, 0.1)
    assert abs((a & other).mean() - 0.01) < 4 * np.sqrt(0.01 * 0.99 / len(idx))
    assert labels.labeled(5, idx, 1.0).all() and not labels.labeled(5, idx, 0.0).any()
    # TensorFlow's draw (tf.data pipelines) is the same function.
    np.testing.assert_array_equal(labels.tf_labeled(3, tf.constant(idx), 0.3).numpy(),
                                  labels.labeled(3, idx, 0.3))
    with pytest.raises(ValueError, match="label_fraction"):
        labels.labeled(0, idx, 1.5)


# -- the pairs ---------------------------------------------------------------------------------
def _by_index(stream_batches, arrays):
    """(index, h_mask, h_bar) of every pair in ``stream_batches``, the index found by matching
    the pair's patch_b to the stored pairs (``arrays``: load_arrays)."""
    out = []
    stored = arrays["patch_b"][..., 0]
    for x, y, w in stream_batches:
        for pb, hm, hb in zip(x["patch_b"].numpy()[..., 0], w["h_bar"].numpy(),
                              y["h_bar"].numpy()):
            i = int(np.flatnonzero(np.all(stored == pb, axis=(1, 2)))[0])
            out.append((int(arrays["index"][i]), float(hm), hb))
    return out


def test_tfrecords_and_generated_pairs_leave_the_same_pairs_unlabeled(tiny_data):
    """The TFRecord stream and PairBatches (same images, seed 0) mask exactly the pairs whose
    draw says so, zero their H_bar, keep the others' stored H_bar; drop_unlabeled keeps the
    labeled ones alone, as many as count_labeled counts."""
    arrays = data.load_arrays(tiny_data, "train")
    labeled = labels.labeled(0, arrays["index"], 0.5)
    assert 0 < labeled.sum() < len(labeled)
    ds = data.load_split(tiny_data, "train", 4, shuffle=False, repeat=False, label_fraction=0.5)
    seen = _by_index(ds, arrays)
    assert sorted(i for i, _, _ in seen) == sorted(arrays["index"].tolist())
    for i, mask, h_bar in seen:
        row = int(np.flatnonzero(arrays["index"] == i)[0])
        assert mask == float(labeled[row])
        np.testing.assert_array_equal(h_bar, arrays["h_bar"][row] if labeled[row] else 0.0)
    dropped = data.load_split(tiny_data, "train", 1, shuffle=False, repeat=False,
                              label_fraction=0.5, drop_unlabeled=True)
    kept = sorted(i for i, _, _ in _by_index(dropped, arrays))
    assert kept == sorted(arrays["index"][labeled].tolist())
    assert data.count_labeled(tiny_data, "train", 0.5, 0) == (int(labeled.sum()), len(labeled))

    gen = batches.PairBatches("bundled", 12, samples_per_image=3, seed=0, max_images=4,
                              shuffle=False, label_fraction=0.5)
    stacked = gen.stacked_batch(0)  # samples 0..11 = indices 0..11 (no image skipped)
    order = np.argsort(arrays["index"])
    np.testing.assert_array_equal(stacked["h_mask"], labeled[order].astype(np.float32))
    want = np.where(labeled[order][:, None], arrays["h_bar"][order], 0.0)
    np.testing.assert_allclose(stacked["h_bar"], want, atol=1e-6)
    only = batches.PairBatches("bundled", 1, samples_per_image=3, seed=0, max_images=4,
                               shuffle=False, label_fraction=0.5, drop_unlabeled=True)
    assert only.num_samples == labeled.sum()
    np.testing.assert_allclose(only.stacked_batch(0)["h_bar"][0],
                               arrays["h_bar"][order][labeled[order]][0], atol=1e-6)


def test_fresh_pairs_keep_the_slots_decision_every_epoch():
    gen = batches.PairBatches("bundled", 8, samples_per_image=4, seed=2, max_images=4,
                              label_fraction=0.5)
    expect = labels.labeled(2, np.arange(16), 0.5)  # image i's sample k has index 4 i + k
    first = None
    for epoch in (0, 1):
        ids = gen.epoch_order(epoch)[:8]
        got = gen.stacked_batch(0, epoch, fresh=True)
        np.testing.assert_array_equal(got["h_mask"], expect[ids].astype(np.float32))
        assert np.all(got["h_bar"][~expect[ids]] == 0)
        assert np.all(np.abs(got["h_bar"][expect[ids]]).sum(axis=1) > 0)
        if first is None:
            first = {int(s): h for s, h in zip(ids, got["h_bar"])}
        else:  # a fresh pair of a labeled slot: a new H_bar
            assert all(not np.allclose(first[int(s)], h) for s, h in zip(ids, got["h_bar"])
                       if int(s) in first and expect[s])


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """Two folders of bundled photographs: ``labeled`` (2 images) and ``unlabeled`` (2 others)."""
    root = tmp_path_factory.mktemp("folders")
    files = [path for _, path in sources.bundled_image_files()[:4]]
    for name, chosen in (("labeled", files[:2]), ("unlabeled", files[2:])):
        (root / name).mkdir()
        for k, path in enumerate(chosen):
            shutil.copyfile(path, root / name / f"{name[0]}{k}{os.path.splitext(path)[1]}")
    return str(root / "labeled"), str(root / "unlabeled")


def test_unlabeled_images_add_masked_pairs_and_leave_the_labeled_ones(folders):
    lab, unl = folders
    alone = batches.PairBatches(lab, 4, samples_per_image=2, seed=0, shuffle=False)
    mixed = batches.PairBatches(lab, 4, samples_per_image=2, seed=0, shuffle=False,
                                unlabeled_images=[unl, lab])  # lab again: left out
    assert (alone.num_samples, mixed.num_samples) == (4, 8)
    a, m = alone.stacked_batch(0), mixed.stacked_batch(0)
    for key in a:
        np.testing.assert_array_equal(m[key], a[key])  # the labeled pairs are unchanged
    u = mixed.stacked_batch(1)
    np.testing.assert_array_equal(u["h_mask"], np.zeros(4, np.float32))
    np.testing.assert_array_equal(u["h_bar"], np.zeros((4, 8), np.float32))
    assert [mixed.sample(s)["index"] for s in range(8)] == list(range(8))
    assert mixed.sample(5)["image_id"].startswith("unlabeled:")
    assert u["patch_a"].shape == a["patch_a"].shape and np.any(u["patch_a"] != a["patch_a"])


def test_stage_k_in_memory_keeps_the_unlabeled_h_bar_zero(folders, monkeypatch, tmp_path):
    """Stage-2 pairs re-made in memory (here from an identity 'stage 1'): the unlabeled pairs'
    stage-2 H_bar stays zeros, the labeled ones' is what next_stage_arrays makes."""
    from stnh_tf import hierarchy

    lab, unl = folders
    monkeypatch.setattr(runner, "load_model", lambda d: None)
    monkeypatch.setattr(runner, "predictor",
                        lambda m, batch_size=64: lambda a, b: np.broadcast_to(np.eye(3),
                                                                              (len(a), 3, 3)))
    (tmp_path / "s1.keras").write_bytes(b"stage 1")  # read for the saved estimates' key
    cfg = train_config.TrainConfig(image_dir=lab, unlabeled_image_dir=unl,
                                   model_dir=str(tmp_path / "m"), stage=2, in_memory=True,
                                   prev_stages=(str(tmp_path / "s1.keras"),),
                                   samples_per_image=2, batch_size=4, label_fraction=0.5)
    cfg.validate()
    pb = batches.PairBatches(lab, 4, samples_per_image=2, seed=0, shuffle=False,
                             **streams.label_options(cfg))
    pairs = streams.stage_pairs(cfg, pb)
    arrays = batches.materialize(pb, context=True)
    ref, _ = hierarchy.next_stage_arrays(arrays, [lambda a, b: np.broadcast_to(np.eye(3),
                                                                                (len(a), 3, 3))])
    mask = pb.labeled
    assert mask[4:].sum() == 0 and 0 < mask[:4].sum() < 4  # unlabeled images; F=0.5 of lab
    np.testing.assert_array_equal(pairs["h_mask"], mask.astype(np.float32))
    np.testing.assert_array_equal(pairs["h_bar"][~mask], 0.0)
    np.testing.assert_allclose(pairs["h_bar"][mask], ref["h_bar"][mask])
    assert np.all(np.abs(ref["h_bar"][~mask]).sum(axis=1) > 0)  # there was a target to hide


# -- training ----------------------------------------------------------------------------------
def _altered_stream(where):
    """A stream_fn: the run's TFRecord stream with H_bar of the pairs ``where`` selects
    (``"masked"`` or ``"labeled"``) replaced by large values."""
    def stream_fn(cfg, split, start_step):
        def alter(x, y, w):
            pick = w["h_bar"] == 0 if where == "masked" else w["h_bar"] > 0
            noise = tf.reshape(tf.range(8, dtype=tf.float32), (1, 8)) * 100.0 + 7.0
            h_bar = tf.where(pick[:, None], y["h_bar"] + noise, y["h_bar"])
            return x, {**y, "h_bar": h_bar}, w
        return streams.training_stream(cfg, split, start_step).map(alter)
    return stream_fn


@pytest.mark.slow  # (make test-all)
def test_the_unlabeled_pairs_h_bar_never_reaches_the_loss(tiny_data, tmp_path, narrow):
    """One step on a batch of labeled and unlabeled pairs: changing the unlabeled pairs' H_bar
    leaves every weight bit-identical; changing the labeled pairs' H_bar does not."""
    # shuffle_buffer=1: the first batch of 12 is the split's 12 pairs (both shards, whole).
    first = next(iter(streams.training_stream(_cfg(tiny_data, "u", label_fraction=0.5,
                                                   shuffle_buffer=1))))
    mask = first[2]["h_bar"].numpy()
    assert 0 < mask.sum() < len(mask)
    runs = {}
    for name, stream_fn in (("plain", None), ("masked", _altered_stream("masked")),
                            ("labeled", _altered_stream("labeled"))):
        cfg = _cfg(tiny_data, tmp_path / name, label_fraction=0.5, shuffle_buffer=1)
        training.train(cfg, printer=_quiet, stream_fn=stream_fn)
        runs[name] = _weights(cfg.model_dir)
    for a, b in zip(runs["plain"], runs["masked"]):
        np.testing.assert_array_equal(a, b)
    assert any(not np.array_equal(a, b) for a, b in zip(runs["plain"], runs["labeled"]))
    saved = json.load(open(tmp_path / "plain" / "config.json"))
    assert (saved["label_fraction"], saved["drop_unlabeled"], saved["unlabeled_image_dir"]) == (
        0.5, False, "")


@pytest.mark.slow  # (make test-all)
def test_an_all_unlabeled_run_is_the_l1_loss_alone(tiny_data, tmp_path, narrow):
    """label_fraction=0 trains exactly as l2_weight=0 on labeled pairs (the L2 term adds no
    gradient), and differs from the supervised run."""
    runs, hist = {}, {}
    for name, kw in (("unlabeled", dict(label_fraction=0.0)), ("l1", dict(l2_weight=0.0)),
                     ("both", {})):
        cfg = _cfg(tiny_data, tmp_path / name, train_steps=2, checkpoint_every=2, batch_size=4,
                   **kw)
        hist[name] = training.train(cfg, printer=_quiet)["history"]
        runs[name] = _weights(cfg.model_dir)
    for a, b in zip(runs["unlabeled"], runs["l1"]):
        np.testing.assert_array_equal(a, b)
    assert hist["unlabeled"]["h_bar_loss"] == [0.0]
    assert hist["unlabeled"]["patch_a_warp_loss"] == pytest.approx(hist["l1"]["patch_a_warp_loss"],
                                                                   rel=1e-6)
    assert any(not np.array_equal(a, b) for a, b in zip(runs["unlabeled"], runs["both"]))


def test_unlabeled_pairs_cost_the_same_computation(tiny_data, narrow):
    """The streams' batches have the same structure, shapes and dtypes with or without labels,
    and one traced training step (forward, both losses, gradients, update) serves a labeled and
    an unlabeled batch: the same graph, so the same work per step."""
    specs = [data.load_split(tiny_data, "train", 4, label_fraction=f, drop_unlabeled=d,
                             ).element_spec for f, d in ((1.0, False), (0.1, False), (0.5, True))]
    assert specs[0] == specs[1] == specs[2]
    gen = [batches.PairBatches("bundled", 4, samples_per_image=3, max_images=4, label_fraction=f,
                               shuffle=False).batch(0) for f in (1.0, 0.0)]
    shapes = [tf.nest.map_structure(lambda a: (a.shape, a.dtype), b) for b in gen]
    assert shapes[0] == shapes[1]
    assert gen[1][2]["h_bar"].sum() == 0 and gen[0][2]["h_bar"].sum() == 4

    cfg = _cfg(tiny_data, "unused", batch_size=4)
    model = training.compile_model(model_kinds.build_model(cfg), cfg)
    labeled = next(iter(data.load_split(tiny_data, "train", 4, shuffle=False)))
    unlabeled = next(iter(data.load_split(tiny_data, "train", 4, shuffle=False,
                                          label_fraction=0.0)))
    model.train_on_batch(*labeled)  # builds the optimizer's variables
    step = tf.function(lambda x, y, w: model.train_step((x, y, w)))
    step(*labeled)
    step(*unlabeled)
    assert step.experimental_get_tracing_count() == 1
    ops = step.get_concrete_function(*unlabeled).graph.get_operations()
    assert any(op.type == "Conv2D" for op in ops)


def test_label_options_are_checked_before_the_run_starts(tiny_data, folders, tmp_path):
    def problems(**kw):
        base = dict(model_dir="m", data_dir=tiny_data)
        base.update(kw)
        return " ".join(train_config.TrainConfig(**base).problems())

    assert "label_fraction must be a number in [0, 1]" in problems(label_fraction=1.5)
    assert "give image_dir" in problems(unlabeled_image_dir=folders[1])
    assert "leaves no pair to train on" in problems(label_fraction=0.0, drop_unlabeled=True)
    both = train_config.TrainConfig(model_dir="m", data_dir=tiny_data, label_fraction=2.0,
                                    unlabeled_image_dir="u", drop_unlabeled=True).problems()
    assert len(both) == 3 and "give image_dir" in both[1] and "give one of them" in both[2]
    assert "no photometric loss" in problems(label_fraction=0.5, model="homographynet_gap")
    assert "l1_weight is 0" in problems(label_fraction=0.5, l1_weight=0.0)
    assert problems(label_fraction=0.5, drop_unlabeled=True, model="homographynet_gap") == ""
    assert problems(image_dir=folders[0], data_dir="", unlabeled_image_dir=folders[1]) == ""
    # drop_unlabeled leaving fewer labeled pairs than a batch: refused before model_dir exists.
    labeled = data.count_labeled(tiny_data, "train", 0.1, 0)[0]
    assert labeled < 4
    with pytest.raises(ValueError, match=f"{labeled} of the 12 train pairs"):
        training.train(_cfg(tiny_data, tmp_path / "few", batch_size=4, label_fraction=0.1,
                            drop_unlabeled=True), printer=_quiet)
    with pytest.raises(ValueError, match="fewer than one batch"):
        training.train(train_config.TrainConfig(
            image_dir=folders[0], model_dir=str(tmp_path / "few2"), samples_per_image=2,
            batch_size=4, label_fraction=0.5, drop_unlabeled=True, train_steps=1,
            warmup_steps=0, checkpoint_every=1, val_samples=0), printer=_quiet)
    assert not os.path.exists(tmp_path / "few") and not os.path.exists(tmp_path / "few2")


@pytest.mark.slow  # (make test-all)
def test_resume_refuses_another_label_fraction_and_takes_a_moved_unlabeled_folder(
        folders, tmp_path, narrow):
    """Generated pairs in memory with unlabeled images mixed in, interrupted after step 1: the
    same run with another label_fraction is refused (its results would differ); the unlabeled
    folder may be named anew (resume-free, like image_dir) and the run finishes."""
    lab, unl = folders

    class Stop(keras.callbacks.Callback):
        def on_epoch_end(self, epoch, logs=None):
            raise KeyboardInterrupt

    cfg = train_config.TrainConfig(image_dir=lab, unlabeled_image_dir=unl, in_memory=True,
                                   model_dir=str(tmp_path / "run"), samples_per_image=2,
                                   batch_size=4, train_steps=2, warmup_steps=0,
                                   checkpoint_every=1, val_samples=0, learning_rate=0.01,
                                   label_fraction=0.5)
    with pytest.raises(KeyboardInterrupt):
        training.train(cfg, printer=_quiet, extra_callbacks=[Stop()])
    other = train_config.TrainConfig(**{**cfg.to_json(), "label_fraction": 0.25})
    with pytest.raises(ValueError, match="label_fraction"):
        training.train(other, printer=_quiet)
    moved = shutil.copytree(unl, tmp_path / "moved")
    again = train_config.TrainConfig(**{**cfg.to_json(), "unlabeled_image_dir": str(moved)})
    assert training.train(again, printer=_quiet)["final_step"] == 2
    saved = json.load(open(tmp_path / "run" / "config.json"))
    assert (saved["unlabeled_image_dir"], saved["label_fraction"]) == (str(moved), 0.5)


# -- the experiment ----------------------------------------------------------------------------
def _experiment(tmp_path, maces, data_dir):
    """A CPU-budget SemiSupervised on ``data_dir``'s pairs whose models' MACEs are
    ``maces[(row.key, seed)]`` (nothing trained)."""
    from stnh_tf.paper import reproduce, semi_supervised

    run = reproduce.Reproduction(reproduce.BUDGETS["cpu"], str(tmp_path), printer=_quiet,
                                 reuse={"data_stage1": data_dir})
    exp = semi_supervised.SemiSupervised(run)
    asked = []

    def mace(row, seed):
        asked.append((row.key, seed))
        return maces[(row.key, seed)]

    exp.mace = mace
    return exp, asked


def test_rows_within_a_pixel_get_a_second_seed(tiny_data, tmp_path):
    from stnh_tf.paper import semi_supervised

    maces = {("all", 0): 18.0, ("labeled_alone", 0): 24.0, ("labeled_plus_unlabeled", 0): 18.7,
             ("none", 0): 21.0, ("all", 1): 18.2, ("labeled_plus_unlabeled", 1): 19.9}
    exp, asked = _experiment(tmp_path, maces, tiny_data)
    assert [r.title for r in exp.rows] == ["100% labels", "10% labels alone",
                                           "10% labels + 90% unlabeled", "0% labels (L1 only)"]
    got = exp.measure()
    # 18.0 and 18.7 are within 1 px: both get seed 1; 24 and 21 stay at one seed.
    assert got == {"all": [18.0, 18.2], "labeled_alone": [24.0],
                   "labeled_plus_unlabeled": [18.7, 19.9], "none": [21.0]}
    assert sorted(asked) == sorted(maces)
    # Then the means 18.1 and 19.3 are 1.2 px apart; none is within 1 px of 21 or 24: done.
    verdict = semi_supervised.claim(got, exp.rows)
    assert verdict["verdict"] == "holds"
    assert verdict["difference_px"] == pytest.approx(24.0 - 19.3)
    over = semi_supervised.claim({"labeled_alone": [18.0, 18.5],
                                  "labeled_plus_unlabeled": [18.4, 19.0]}, exp.rows)
    assert over["verdict"] == "unresolved" and "within the seeds' spread" in over["text"]
    worse = semi_supervised.claim({"labeled_alone": [18.0], "labeled_plus_unlabeled": [19.0]},
                                  exp.rows)
    assert worse["verdict"] == "does not hold"
    assert exp.model_name(exp.rows[0], 0) == "stage1"
    assert exp.model_name(exp.rows[0], 1) == "ablation_l2-1_l1-1_seed1"  # Table 1's 1:1 seed 1
    assert exp.model_name(exp.rows[1], 1) == "semi_labels-0.1_drop_seed1"
    cfg = exp.config(exp.rows[2], 1)
    assert (cfg.label_fraction, cfg.drop_unlabeled, cfg.seed, cfg.train_steps) == (
        0.1, False, 1, 4000)


@pytest.mark.slow
def test_tiny_experiment_writes_the_table_from_the_models(tmp_path):
    """The smoke budget end to end (bundled photographs; about a minute): four rows, the labeled
    counts recounted here from the stored pairs' indices, every MACE recomputed from its model
    on the stored test pairs, and a second run that trains nothing."""
    from stnh_tf.paper import reproduce, semi_supervised
    from test_reproduce import _model_mace

    logs = []
    run = reproduce.Reproduction(reproduce.BUDGETS["tiny"], str(tmp_path), source="bundled",
                                 printer=logs.append)
    result = semi_supervised.SemiSupervised(run).table()
    assert [r["key"] for r in result["rows"]] == ["all", "labeled_alone",
                                                  "labeled_plus_unlabeled", "none"]
    index = data.load_arrays(run.data_dir(1), "train")["index"]
    test = data.load_arrays(run.data_dir(1), "test")
    assert result["test_pairs"] == len(test["index"]) and result["train_pairs_total"] == len(index)
    for r in result["rows"]:
        for seed, d in zip(r["seeds"], r["model_dirs"]):
            want = int(labels.labeled(seed, index, r["label_fraction"]).sum())
            assert r["labeled_pairs"][seed] == want
            assert r["train_pairs"][seed] == (want if r["drop_unlabeled"] else len(index))
            saved = json.load(open(os.path.join(d, "config.json")))
            assert (saved["label_fraction"], saved["drop_unlabeled"], saved["seed"]) == (
                r["label_fraction"], r["drop_unlabeled"], seed)
        assert r["mace_per_seed"] == pytest.approx([_model_mace(d, test)
                                                    for d in r["model_dirs"]], rel=1e-4)
    table = open(tmp_path / "semi_supervised.md").read()
    assert reproduce.SMOKE_NOTE in table and result["claim"]["text"] in table
    assert table.count("\n| ") == 6  # header, rule, four rows
    logs.clear()
    again = semi_supervised.SemiSupervised(reproduce.Reproduction(
        reproduce.BUDGETS["tiny"], str(tmp_path), source="bundled", printer=logs.append)).table()
    assert not [line for line in logs if line.startswith("[train]")]
    assert again["rows"] == result["rows"]


def test_save_and_restore_carry_the_models_to_another_machine(tiny_data, tmp_path, narrow):
    """A finished model goes to the repository folder without optimizer state (same weights) with
    its config; an unfinished one as its checkpoint; both come back into a fresh output folder,
    and a second restore changes nothing."""
    from stnh_tf.paper import reproduce, semi_supervised
    from stnh_tf.training import run_dir

    def experiment(out):
        run = reproduce.Reproduction(reproduce.BUDGETS["tiny"], str(out), printer=_quiet,
                                     reuse={"data_stage1": tiny_data})
        return semi_supervised.SemiSupervised(run)

    first, repo = experiment(tmp_path / "a"), str(tmp_path / "repo")
    done, busy = (first.model_name(first.rows[k], 0) for k in (2, 3))
    for name in (done, busy):
        training.train(_cfg(tiny_data, first.run.model_dir(name), batch_size=4, label_fraction=0.5),
                       printer=_quiet)
    os.remove(os.path.join(first.run.model_dir(busy), run_dir.FINAL_MODEL))  # checkpoint only
    # Evaluated here, on the stored test pairs (as mace() does; these models have no budget).
    done_mace = first.run.evaluate(done, [first.run.model_dir(done)])["model"]["mace"]
    assert first.save(repo) == {done: "finished", busy: 1}
    assert first.save(repo) == {busy: 1}  # a finished model is saved once
    assert not os.path.exists(os.path.join(repo, "resume", done))

    second = experiment(tmp_path / "b")
    assert second.restore(repo) == {done: "finished", busy: 1}
    for a, b in zip(_weights(first.run.model_dir(done)), _weights(second.run.model_dir(done))):
        np.testing.assert_array_equal(a, b)
    assert json.load(open(os.path.join(second.run.model_dir(done), "config.json"))) == json.load(
        open(os.path.join(first.run.model_dir(done), "config.json")))
    ckpt = [os.path.join(e.run.model_dir(busy), run_dir.CHECKPOINT_DIR) for e in (first, second)]
    assert run_dir.read_checkpoint_state(ckpt[1])["step"] == 1
    with open(run_dir.checkpoint_weights_path(ckpt[0]), "rb") as f0, \
            open(run_dir.checkpoint_weights_path(ckpt[1]), "rb") as f1:
        assert f0.read() == f1.read()
    assert second.restore(repo) == {}
    # The evaluation came along: the restored model is not evaluated again.
    key = os.path.join(second.run.out, "eval", f"{done}.json")
    assert json.load(open(key))["model"]["mace"] == done_mace
    os.utime(key, (1e9, 1e9))  # older than the model: evaluated again, to the same value
    again = second.run.evaluate(done, [second.run.model_dir(done)])["model"]["mace"]
    assert again == pytest.approx(done_mace, rel=1e-4)
    assert os.path.getmtime(key) > 1e9


def test_a_model_evaluated_elsewhere_is_not_trained_again(tiny_data, tmp_path):
    """An evaluation committed without its model (Table 1's 1:1 seed 1, trained and evaluated
    on another machine) is restored and used as the row's MACE; with a checkpoint of that model
    in the folder, the evaluation no longer stands for it."""
    from stnh_tf.paper import reproduce, semi_supervised
    from stnh_tf.training import run_dir

    logs = []
    run = reproduce.Reproduction(reproduce.BUDGETS["tiny"], str(tmp_path / "out"),
                                 printer=logs.append, reuse={"data_stage1": tiny_data})
    exp = semi_supervised.SemiSupervised(run)
    name = exp.model_name(exp.rows[0], 1)
    assert name == "ablation_l2-1_l1-1_seed1"
    repo = tmp_path / "repo"
    os.makedirs(repo / "eval")
    with open(repo / "eval" / f"{name}.json", "w") as f:
        json.dump({"count": 12, "model": {"mace": 17.25}}, f)
    assert exp.restore(str(repo)) == {}
    assert exp.evaluated_elsewhere(name) == {"count": 12, "model": {"mace": 17.25}}
    assert exp.mace(exp.rows[0], 1) == 17.25
    assert not [line for line in logs if line.startswith("[train]")]
    row = {"row": "100% labels", "mace": 17.5, "mace_per_seed": [17.75, 17.25],
           "labeled_pairs": [24], "train_pairs": [24], "evaluated_elsewhere": [1]}
    table = semi_supervised.markdown({"train_steps": 2, "budget": "cpu", "test_pairs": 12,
                                      "train_pairs_total": 24, "batch_size": 4, "close_px": 1.0,
                                      "rows": [row], "claim": {"text": "claim"}})
    assert "| 100% labels | 24 | 24 | 17.50 | 2 seeds: 17.25-17.75 |  |" in table
    assert "without their models (trained and evaluated on the same test pairs on another " \
           "machine, e.g. Table 1's): 100% labels seed 1." in table
    # A checkpoint of the model (a run of it started here): mace() trains and evaluates it.
    training.train(_cfg(tiny_data, run.model_dir(name), batch_size=4), printer=_quiet)
    os.remove(os.path.join(run.model_dir(name), run_dir.FINAL_MODEL))
    assert exp.evaluated_elsewhere(name) is None
