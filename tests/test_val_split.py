"""Issue 78, item 1: a ``val`` split of photographs apart from the training and test ones
(``data_prep.make_dataset --val_fraction``, :mod:`stnh_tf.data.holdout`), the default of
``--val_split``; a dataset without one is not validated on (one line says so), the test split
only where named (one line says so). The held-out photographs are checked against an oracle
computed here from the photographs' names (sha256, the documented rule); the pairs against a
dataset written without a hold-out. Photographs: copies of a bundled one under made-up names."""

import hashlib
import os
import shutil

import numpy as np
import pytest

from stnh_tf.data import bundled_photos, holdout, stage1, stage_k
from stnh_tf.data import tfrecords as data
from stnh_tf.training import config as train_config
from stnh_tf.training import loop as training
from stnh_tf.training import run_dir

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FRACTION = 0.4
TRAIN_NAMES = [f"photo_{k:02d}.png" for k in range(12)] + ["sub/a.png", "sub/b.png"]
TEST_NAMES = ["t0.png", "t1.png", "t2.png"]
QUIET = lambda *a, **k: None  # noqa: E731


def _oracle_held_out(name: str, fraction: float) -> bool:
    """The documented rule, written here with hashlib: the first 8 bytes of the sha256 of the
    photograph's path in its folder, big-endian, below fraction * 2**64."""
    return int(hashlib.sha256(name.encode()).hexdigest()[:16], 16) < fraction * 2 ** 64


def _folder(root, names):
    photo = bundled_photos.bundled_image_files()[0][1]
    for name in names:
        os.makedirs(os.path.dirname(os.path.join(root, name)), exist_ok=True)
        shutil.copy(photo, os.path.join(root, name))
    return str(root)


def _ids(d, split):
    return [str(i) for i in data.load_arrays(d, split)["image_id"]]


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("photos")
    return _folder(tmp / "train", TRAIN_NAMES), _folder(tmp / "test", TEST_NAMES)


@pytest.fixture(scope="module")
def datasets(photos, tmp_path_factory):
    """``held``: train and val with --val_fraction, test from the test folder; ``full``: train
    without a hold-out (the paper's: every photograph) and the same test split."""
    train, test = photos
    tmp = tmp_path_factory.mktemp("datasets")
    held, full = str(tmp / "held"), str(tmp / "full")
    kw = dict(samples_per_image=2, num_shards=1, log=QUIET)
    for split in holdout.SPLITS:
        stage1.make_dataset("folder", held, split, image_dir=train, seed=0,
                            val_fraction=FRACTION, **kw)
    stage1.make_dataset("folder", full, "train", image_dir=train, seed=0, **kw)
    for d in (held, full):
        stage1.make_dataset("folder", d, "test", image_dir=test, seed=1, **kw)
    return held, full


def test_the_default_validation_split_is_val():
    assert train_config.TrainConfig().val_split == holdout.VAL_SPLIT == "val"


def test_make_dataset_writes_a_val_split_apart_from_train_and_test(datasets):
    """The val photographs are those the oracle holds out, the train photographs the others,
    none of them a test photograph; each photograph's pairs are those of the dataset written
    without a hold-out (same seed: its index in the full listing); the metadata and the counts
    line say what went where."""
    held, full = datasets
    val_names = {n for n in TRAIN_NAMES if _oracle_held_out(n, FRACTION)}
    assert 0 < len(val_names) < len(TRAIN_NAMES)  # (both sides hold photographs)
    got = {split: _ids(held, split) for split in ("train", "val", "test")}
    assert set(got["val"]) == val_names
    assert set(got["train"]) == set(TRAIN_NAMES) - val_names
    assert set(got["test"]) == set(TEST_NAMES)
    assert not set(got["train"]) & set(got["val"]) and not set(got["val"]) & set(got["test"])
    everything = data.load_arrays(full, "train")
    for split in holdout.SPLITS:
        arrays = data.load_arrays(held, split)
        rows = [i for i, n in enumerate(everything["image_id"]) if str(n) in set(got[split])]
        for name in ("patch_a", "patch_b", "h_ba", "index"):
            np.testing.assert_array_equal(arrays[name], everything[name][rows], err_msg=name)
    meta = data.read_metadata(held)["splits"]
    assert (meta["val"]["val_fraction"], meta["val"]["held_apart"], meta["val"]["num_items"]) == (
        FRACTION, len(TRAIN_NAMES) - len(val_names), len(val_names))
    from stnh_tf.data import folder_counts

    assert folder_counts.split_counts(meta["train"]).line() == (
        f"photographs: {len(TRAIN_NAMES) - len(val_names)} used; in the val split "
        f"(--val_fraction={FRACTION:g}): {len(val_names)}")
    assert data.read_metadata(full)["splits"]["train"]["val_fraction"] == 0.0


def test_the_held_out_photographs_do_not_depend_on_the_folders_order(photos, tmp_path):
    """Two folders listed either way round: the same photographs held out (by their paths in
    their folders, the ``k:`` of the listing aside), and a larger fraction a superset."""
    train, _ = photos
    one = _folder(tmp_path / "one", TRAIN_NAMES[:7])
    two = _folder(tmp_path / "two", TRAIN_NAMES[7:])

    def held(folders, fraction=FRACTION):
        items = stage1.folder_items(folders, 0, "val", fraction)[0]
        return {i.item_id.split(":", 1)[1] for i in items}

    assert held([one, two]) == held([two, one]) == {
        n for n in TRAIN_NAMES if _oracle_held_out(n, FRACTION)}
    assert held([one, two], 0.1) <= held([one, two]) <= held([one, two], 0.9)


@pytest.mark.parametrize("split, fraction, image_dir, message", [
    ("val", 0.0, "train", "--split=val writes the photographs held out"),
    ("val", 0.25, "train", "holds a train split written with --val_fraction=0.4"),
    ("train", 0.0, "train", "holds a val split written with --val_fraction=0.4"),
    ("val", FRACTION, "test", "holds a train split of other photographs"),
    ("test", FRACTION, "test", "--split=test keeps all its photographs"),
    ("val", 1.0, "train", "--val_fraction must be a number in \\[0, 1\\)"),
])
def test_a_split_that_would_share_photographs_is_refused_before_writing(
        datasets, photos, tmp_path, split, fraction, image_dir, message):
    """Beside the other split of a hold-out, another fraction or other photographs; a val split
    without a fraction, a fraction for the test split: refused in one line, nothing written."""
    held, _ = datasets
    copy = str(tmp_path / "copy")
    shutil.copytree(held, copy)
    before = {n: os.path.getmtime(os.path.join(copy, n)) for n in os.listdir(copy)}
    folder = dict(zip(("train", "test"), photos))[image_dir]
    with pytest.raises(ValueError, match=message):
        stage1.make_dataset("folder", copy, split, image_dir=folder, val_fraction=fraction,
                            overwrite=True, log=QUIET)
    assert {n: os.path.getmtime(os.path.join(copy, n)) for n in os.listdir(copy)} == before


def test_coco2014_refuses_a_fraction_before_any_download(tmp_path):
    with pytest.raises(ValueError, match="--source=folder"):
        stage1.make_dataset("coco2014", str(tmp_path / "d"), "train", val_fraction=0.1)
    assert not (tmp_path / "d").exists()


def test_stage_data_is_made_for_the_val_split_too(datasets):
    held, full = datasets
    assert stage_k.default_splits(held) == ["train", "val", "test"]
    assert stage_k.default_splits(full) == ["train", "test"]


def _said(lines):
    """The lines a run prints about what it validates on."""
    return [x for x in lines if x.startswith(("no validation", "validation on", "validation:"))]


def _cfg(data_dir, model_dir, **kw):
    return train_config.TrainConfig(**{
        "data_dir": data_dir, "model_dir": str(model_dir), "train_steps": 2, "warmup_steps": 1,
        "batch_size": 4, "checkpoint_every": 2, "val_samples": 4, "learning_rate": 0.01, **kw})


NO_VAL_LINE = ("no validation: {} has no 'val' split (the test split validates only where "
               "--val_split=test says so); write one with data_prep.make_dataset --split=val "
               "--val_fraction=F (docs/data.md)")
TEST_LINE = ("validation on the 'test' split of {} (--val_split), the test pairs: monitoring "
             "only; a test number of this run is then not apart from what was watched")


@pytest.mark.slow  # (4 s: training runs; make test-all)
def test_a_run_never_validates_silently_on_test(datasets, tmp_path, narrow):
    """Default: the val split where the dataset has one, else no validation and one line saying
    so, though the test split is there (before: the test split, silently); the test split only
    where --val_split names it, with a line; a split named that the dataset lacks: refused
    before anything is written."""
    from stnh_tf.training import streams

    held, full = datasets
    lines = []
    result = training.train(_cfg(full, tmp_path / "none"), printer=lines.append)
    assert "val_h_bar_mace" not in result["history"]
    assert _said(lines) == [NO_VAL_LINE.format(full)]
    assert streams.validation_plan(_cfg(held, "x")) == ("val", None)
    assert streams.validation_plan(_cfg(full, "x", val_split="test")) == (
        "test", TEST_LINE.format(full))
    assert streams.validation_plan(_cfg(full, "x", val_samples=0)) == (None, None)
    with pytest.raises(ValueError, match="has no complete 'tset' split for --val_split"):
        training.train(_cfg(full, tmp_path / "typo", val_split="tset"), printer=QUIET)
    assert not (tmp_path / "typo").exists()


@pytest.mark.parametrize("split", ["val", "test"])  # (5 s each on 2 shared cores)
@pytest.mark.slow
def test_a_run_validates_on_the_split_it_says(datasets, tmp_path, narrow, split):
    """On the held-out dataset by default: its val pairs, no line; on --val_split=test: the test
    pairs, and the line says so. The logged MACE is the evaluation of the final model on that
    split's pairs."""
    from stnh_tf.evaluation import mace as evaluation

    held, full = datasets
    d, kw = (held, {}) if split == "val" else (full, {"val_split": "test"})
    lines = []
    result = training.train(_cfg(d, tmp_path / split, **kw), printer=lines.append)
    assert _said(lines) == ([] if split == "val" else [TEST_LINE.format(full)])
    evaluated = evaluation.evaluate([str(tmp_path / split)], d, split, max_samples=4)
    assert evaluated["count"] == 4
    assert result["history"]["val_h_bar_mace"][-1] == pytest.approx(
        evaluated["model"]["mace"], rel=1e-3)


def test_a_run_saved_with_the_former_default_resumes(tmp_path):
    """A run saved when ``val_split`` defaulted to ``test``: on image folders (which never read
    it) it resumes under the new default; on TFRecords it resumes with --val_split=test, and
    without it is refused naming the field (its log would mix two validation sets)."""
    base = dict(train_steps=4, warmup_steps=1, checkpoint_every=2, val_split="test")
    for source in ({"image_dir": "photos", "val_image_dir": "test_photos"},
                   {"data_dir": "records"}):
        folder = tmp_path / next(iter(source))
        run_dir.prepare_model_dir(train_config.TrainConfig(model_dir=str(folder), **base,
                                                           **source))
        now = {k: v for k, v in base.items() if k != "val_split"}
        cfg = train_config.TrainConfig(model_dir=str(folder), **now, **source)
        if "image_dir" in source:
            run_dir.prepare_model_dir(cfg)
        else:
            with pytest.raises(ValueError, match="'val_split': \\('test', 'val'\\)"):
                run_dir.prepare_model_dir(cfg)
            run_dir.prepare_model_dir(train_config.TrainConfig(model_dir=str(folder), **base,
                                                               **source))


def test_the_holdout_doctests():
    import doctest

    result = doctest.testmod(holdout, optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0 and result.failed == 0
