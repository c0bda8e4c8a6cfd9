"""A hostile read of training on one's own photographs (2026-12-07), kept as tests: a test split
made from a folder inside the train split's (``photos/test`` beside ``photos``) shared every one
of its photographs with training; a link to a listed photograph, and hidden folders (thumbnails,
a trash), put copies of photographs in the listing, one of them possibly in the val split; a
linked folder was dropped without a word; a file name that is not UTF-8 stopped a hold-out;
WebP and GIF photographs were "non-image files"; flags of generated pairs were accepted with
``--data_dir``, recorded and ignored.
"""

from __future__ import annotations

import json
import os
import shutil

import cv2
import numpy as np
import pytest

from conftest import photo_folder
from stnh_tf.data import bundled_photos, folder_counts, holdout, sources, stage1
from stnh_tf.data import tfrecords as data


@pytest.mark.parametrize("first", ["train", "test"])
def test_a_split_from_a_folder_inside_anothers_is_said_when_made_and_evaluated(tmp_path,
                                                                              first):
    """``--split=train --image_dir=photos`` and ``--split=test --image_dir=photos/test`` into
    one dataset: the train listing takes ``photos/test`` too, so every test photograph was
    trained on, without a word, and ``evaluate`` reported MACE on training photographs. (The
    project's own checks make a test split of the training folder with another seed on purpose,
    so it is said, not refused.) make_dataset says it in one line, whichever split comes
    second, and ``evaluate``'s notes say it of the test split; folders side by side say
    nothing."""
    from stnh_tf.evaluation import mace

    photos = photo_folder(tmp_path / "photos", ["a.png", "b.png"])
    photo_folder(photos / "test", ["t.png"])
    folders = {"train": photos, "test": photos / "test"}
    out, apart_out = tmp_path / "data", tmp_path / "apart"
    second = "test" if first == "train" else "train"
    for split in (first, second):
        lines = []
        stage1.make_dataset("folder", str(out), split, image_dir=str(folders[split]),
                            samples_per_image=1, num_workers=1, log=lines.append)
        said = [line for line in lines if "made from the same photographs" in str(line)]
        assert len(said) == (split == second), lines
    assert said[0].startswith(f"note: the {second} split of {out} is made from the same "
                              "photographs (or photograph folders, one inside the other) as its "
                              f"{first} split")
    notes = mace.evaluate([], str(out), "test", baselines=("identity",))["notes"]
    assert notes == [holdout.sharing_line(str(out), "test", ["train"])]
    elsewhere = photo_folder(tmp_path / "b", ["c.png"])
    for split, folder in (("train", photos / "test"), ("test", elsewhere)):
        stage1.make_dataset("folder", str(apart_out), split, image_dir=str(folder),
                            samples_per_image=1, num_workers=1, log=lambda *_: None)
    assert mace.evaluate([], str(apart_out), "test", baselines=("identity",))["notes"] == []


def test_links_hidden_and_linked_folders_are_named_not_listed(tmp_path):
    """A link to a listed photograph counted it twice (and the hold-out, keyed by path, could
    put one copy in val); hidden folders (``.thumbnails``) were entered and hidden files used;
    a linked folder was left out without being named. Now the photograph itself is listed once
    and each of the others is named with its reason and counted in the run's line."""
    folder = photo_folder(tmp_path / "photos", ["a.png", "b.png", ".hidden.png"])
    photo_folder(folder / ".thumbnails", ["a.png"])
    other = photo_folder(tmp_path / "album", ["x.png", "y.png"])
    os.symlink(folder / "b.png", folder / "0_link_to_b.png")
    os.symlink(other, folder / "album2020")
    listing = sources.scan_image_folder(str(folder))
    assert [listing.image_id(p) for p in listing.files] == ["a.png", "b.png"]
    why = {os.path.relpath(p, folder): r for p, r in listing.unreadable}
    assert why == {"0_link_to_b.png": "the same file (a link) as b.png",
                   ".hidden.png": sources.HIDDEN, ".thumbnails": sources.HIDDEN,
                   "album2020": f"symbolic link to a folder ({other}): not entered"}
    line = folder_counts.FolderCounts.of(len(listing.files), [r for _, r in listing.unreadable],
                                         listing).line()
    assert line == ("photographs: 2 used; skipped 4 (hidden: 2, linked folder: 1, "
                    "listed already: 1)")


def test_a_name_that_is_not_utf8_is_used_with_its_bytes_escaped(tmp_path):
    """``caf\\xe9.png`` (Latin-1, as old archives write names): with ``--val_fraction`` the hold-out
    stopped the whole run on ``str.encode``; without it the photograph was skipped. Its id now
    escapes the byte, and it is held out or kept like any other."""
    folder = photo_folder(tmp_path / "photos", ["a.png"])
    name = os.fsdecode(b"caf\xe9.png")
    shutil.copy(folder / "a.png", os.path.join(str(folder), name))
    listing = sources.scan_image_folder(str(folder))
    ids = [listing.image_id(p) for p in listing.files]
    assert ids == ["a.png", "caf\\xe9.png"]
    out, written = tmp_path / "data", {}
    for split in ("train", "val"):  # the hold-out of 0.5 divides the two photographs
        stage1.make_dataset("folder", str(out), split, image_dir=str(folder),
                            samples_per_image=1, val_fraction=0.5, num_workers=1,
                            log=lambda *_: None)
        stored = data.load_arrays(str(out), split)["image_id"]
        written[split] = {x.decode() if isinstance(x, bytes) else str(x) for x in stored}
    assert written == {split: {i for i in ids if holdout.held_out(i, 0.5) == (split == "val")}
                       for split in ("train", "val")}


def test_webp_and_gif_photographs_are_used(tmp_path):
    """WebP and GIF files were counted as non-image files (with ``.DS_Store``), although the
    reader decodes them: now listed and decoded, the same pixels as the PNG they were made from
    (WebP lossless, GIF of a gray image)."""
    from PIL import Image

    gray = cv2.cvtColor(cv2.imread(bundled_photos.bundled_image_files()[0][1]),
                        cv2.COLOR_BGR2GRAY)
    folder = tmp_path / "photos"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.webp"), gray, [cv2.IMWRITE_WEBP_QUALITY, 101])
    Image.fromarray(gray).save(folder / "b.GIF")
    (folder / ".DS_Store").write_bytes(b"\0\0")
    listing = sources.scan_image_folder(str(folder))
    assert [listing.image_id(p) for p in listing.files] == ["a.webp", "b.GIF"]
    assert listing.ignored == 1
    for path in listing.files:
        np.testing.assert_array_equal(sources.read_gray(path), gray)


def test_flags_of_generated_pairs_are_refused_with_tfrecords():
    """``--data_dir`` with ``--samples_per_image=100 --fresh_pairs --val_image_dir=...``
    trained on the TFRecords, validated on their val split and wrote the three into
    ``config.json`` as if they had applied. Each is refused naming it; at their defaults, or
    with ``--image_dir``, they stay accepted, and so do the speed fields ``workers`` and
    ``in_memory`` (they change no result; ``experiments.semi_supervised --workers`` sets
    ``workers`` on its TFRecords rows too)."""
    from stnh_tf.training.config import TrainConfig

    changes = {"samples_per_image": 100, "fresh_pairs": True, "val_image_dir": "/v",
               "val_seed": 7}
    problems = TrainConfig(model_dir="/m", data_dir="/d", **changes).problems()
    for name in changes:
        assert sum(p.startswith(f"{name} applies to pairs generated from image_dir")
                   for p in problems) == 1, (name, problems)
    assert len(problems) == len(changes)
    assert not TrainConfig(model_dir="/m", data_dir="/d").problems()
    assert not TrainConfig(model_dir="/m", data_dir="/d", workers=4, in_memory=True).problems()
    generated = TrainConfig(model_dir="/m", image_dir="/i", **dict(changes, workers=2))
    assert not [p for p in generated.problems() if "applies to pairs" in p]


def test_a_run_resumed_on_other_training_data_is_refused(tmp_path):
    """A run stopped at step 2 on one dataset resumed on another (``--data_dir`` is free to
    change, so that a run can move between machines): it trained on, and its ``config.json``
    named the second dataset only; ``--overwrite`` with the first one's path then resumed the
    wrong run. ``config.json`` now records what identifies the data wherever it lies (the train
    split's shards, seed and protocol; a photograph folder's listing), and a resumption on
    other data is refused as other flags are (``--overwrite`` starts over); the same dataset
    moved elsewhere, and a run saved before the record, resume."""
    from stnh_tf.training import run_dir
    from stnh_tf.training.config import TrainConfig

    data = {}
    for seed in (0, 1):
        data[seed] = tmp_path / f"ds{seed}"
        stage1.make_dataset("bundled", str(data[seed]), "train", samples_per_image=1, seed=seed,
                            max_images=2, num_shards=1, num_workers=1, log=lambda *_: None)
    moved = tmp_path / "elsewhere" / "ds0"
    shutil.copytree(data[0], moved)
    run = str(tmp_path / "run")

    def cfg(folder):
        return TrainConfig(model_dir=run, data_dir=str(folder), train_steps=4)

    assert run_dir.prepare_model_dir(cfg(data[0]))
    doc = run_dir.read_run_config(os.path.join(run, "config.json"), digests=True)
    assert set(doc[run_dir.DATA_DIGESTS]) == {"data_dir"} and doc[run_dir.DATA_DIGESTS]["data_dir"]
    assert "data_sha256" not in run_dir.read_run_config(os.path.join(run, "config.json"))
    with pytest.raises(ValueError, match=r"different configuration .*'data_dir \(its data\)'"):
        run_dir.prepare_model_dir(cfg(data[1]))
    assert not run_dir.prepare_model_dir(cfg(moved))  # the same data elsewhere: resumed
    assert run_dir.prepare_model_dir(cfg(data[1]), overwrite=True)  # over: a new run
    config = os.path.join(run, "config.json")
    old = {k: v for k, v in json.loads(open(config).read()).items()
           if k != run_dir.DATA_DIGESTS}
    with open(config, "w") as f:  # a run saved before the record: resumed
        json.dump(old, f)
    assert not run_dir.prepare_model_dir(cfg(data[0]))  # (it cannot tell the data apart)
    # Same names, seed, sizes and counts, other photographs (records are of one size): the
    # shards' first and last bytes tell them apart.
    photos = [p for _, p in bundled_photos.bundled_image_files()]
    for name, picks in (("A", photos[:2]), ("B", photos[5:7])):
        folder = tmp_path / f"photos{name}"
        folder.mkdir()
        for k, path in enumerate(picks):
            shutil.copy(path, folder / f"img{k}.png")
        data[name] = tmp_path / f"ds{name}"
        stage1.make_dataset("folder", str(data[name]), "train", image_dir=str(folder),
                            samples_per_image=1, num_shards=1, num_workers=1,
                            log=lambda *_: None)
    assert run_dir.prepare_model_dir(cfg(data["A"]), overwrite=True)
    with pytest.raises(ValueError, match=r"'data_dir \(its data\)'"):
        run_dir.prepare_model_dir(cfg(data["B"]))
    # A source of unlabeled pairs dropped on resumption: other data too.
    mixed = TrainConfig(model_dir=run, data_dir=str(data["A"]), train_steps=4,
                        unlabeled_pairs_dir=str(tmp_path / "photosB"))
    assert run_dir.prepare_model_dir(mixed, overwrite=True)
    with pytest.raises(ValueError, match=r"'unlabeled_pairs_dir \(its data\)': \('sha256:"):
        run_dir.prepare_model_dir(cfg(data["A"]))


def test_a_folder_of_hidden_files_says_what_was_left_out(tmp_path):
    """A folder holding only macOS's ``._`` files: "no image files found ... (2 unreadable
    directories)" counted the hidden files as directories; the message now says what was left
    out, by kind."""
    folder = photo_folder(tmp_path / "photos", ["._IMG_1.jpg", "._IMG_2.jpg"])
    with pytest.raises(sources.SourceError, match=r"no image files found in .*photos "
                                                  r"\(left out: hidden 2\)"):
        stage1.make_dataset("folder", str(tmp_path / "data"), "train", image_dir=str(folder),
                            num_workers=1, log=lambda *_: None)


# ------------------------------------------------------------------------------------------------
# A review of the offline dataset path (2026-12-07)
# ------------------------------------------------------------------------------------------------
def test_two_splits_of_the_bundled_photographs_are_said_to_share_them(tmp_path):
    """``--source=bundled`` takes the same few photographs for every split (the quickstart's
    train and test): the check that says a split shares photographs with another looked at
    folders only, so a test split of the training photographs went unsaid, and ``evaluate``
    reported MACE on them without a note. Said now, when made and evaluated."""
    from stnh_tf.evaluation import mace

    out, said = tmp_path / "data", []
    for split, seed in (("train", 0), ("test", 1)):
        stage1.make_dataset("bundled", str(out), split, seed=seed, max_images=2,
                            samples_per_image=1, num_workers=1, log=said.append)
    line = holdout.sharing_line(str(out), "test", ["train"])
    assert [str(x) for x in said].count(line) == 1
    assert line in mace.evaluate([], str(out), "test", baselines=("identity",))["notes"]


def test_more_shards_than_photographs_are_refused_and_an_empty_share_never_hangs(tmp_path):
    """``--num_shards`` above the photographs wrote empty shards (shards hold whole
    photographs), and a data-parallel process whose shards were all empty repeated them for
    ever: its training hung without a word. make_dataset refuses such a count (nothing
    written); a split with empty shards (a photograph left out as unreadable) is shared by
    rows instead, every share getting its batches."""
    with pytest.raises(ValueError, match="--num_shards=4 is more than the 2 photographs"):
        stage1.make_dataset("bundled", str(tmp_path / "refused"), "train", max_images=2,
                            samples_per_image=3, num_shards=4, num_workers=1,
                            log=lambda *_: None)
    assert not (tmp_path / "refused").exists() or not os.listdir(tmp_path / "refused")
    out = tmp_path / "data"
    stage1.make_dataset("bundled", str(out), "train", max_images=2, samples_per_image=3,
                        num_shards=2, num_workers=1, log=lambda *_: None)
    meta_path = out / "metadata.json"
    meta = json.loads(meta_path.read_text())
    shards = meta["splits"]["train"]["shards"]
    empty = []
    for k in (1, 3):  # shards 0 and 2 hold the photographs, 1 and 3 none: share 1's are empty
        (out / f"empty{k}.tfrecord").write_bytes(b"")
        empty.append({**shards[0], "file": f"empty{k}.tfrecord", "num_bytes": 0,
                      "num_samples": 0})
    meta["splits"]["train"]["shards"] = [shards[0], empty[0], shards[1], empty[1]]
    meta_path.write_text(json.dumps(meta))
    for k in range(2):
        batches = list(data.load_split(str(out), "train", 2, shuffle=False, repeat=False,
                                       share=(k, 2)))
        assert len(batches) == 3 and all(len(b[0]["patch_a"]) == 1 for b in batches)


def test_unlabeled_pairs_on_several_processes_are_refused(tmp_path):
    """``--unlabeled_pairs_dir`` added all its rows of every batch to each process's share (the
    global batch larger than asked, the same real pairs on every process), or failed naming a
    batch size nobody gave: refused in one line with several processes."""
    from stnh_tf.training.config import TrainConfig

    cfg = TrainConfig(data_dir=str(tmp_path), model_dir=str(tmp_path / "m"),
                      unlabeled_pairs_dir=str(tmp_path / "pairs"), num_processes=2,
                      strategy="data_parallel", coordinator_address="localhost:1234",
                      batch_size=8)
    assert any("unlabeled_pairs_dir trains on one process only" in p for p in cfg.problems())


def test_video_frames_numbered_without_zeros_are_paired_in_frame_order(tmp_path):
    """Frames named ``frame_1.png`` ... ``frame_12.png`` (ffmpeg's ``%d``) were paired in string
    order: frame 1 with frame 10, 12 with 2, and 9 never with 10. Digit runs compare as numbers
    now; zero-padded names keep their order."""
    from stnh_tf.data import unlabeled_pairs

    for sub, names in (("video", [f"frame_{i}.png" for i in range(1, 13)]),
                       ("padded", [f"f{i:04d}.png" for i in range(1, 4)])):
        photo_folder(tmp_path / "pairs" / sub, names)
    found = unlabeled_pairs.list_pairs(str(tmp_path / "pairs"))[0]
    ids = [p.pair_id for p in found]
    assert ids == (["0:padded/f0001.png>f0002.png", "0:padded/f0002.png>f0003.png"]
                   + [f"0:video/frame_{i}.png>frame_{i + 1}.png" for i in range(1, 12)])


def test_a_share_dropping_the_unlabeled_never_hangs(tmp_path):
    """With ``drop_unlabeled`` a data-parallel process whose shards hold no labeled record (the
    label draw of a small split) repeated them for ever, filtering out every record: shared by
    rows now, every share gets batches of labeled records only."""
    from stnh_tf.data import labels

    out = tmp_path / "data"
    stage1.make_dataset("bundled", str(out), "train", max_images=4, samples_per_image=2,
                        num_shards=2, num_workers=1, log=lambda *_: None)
    index = data.read_index(str(out), "train")[0]  # stored order: shard 0's, then shard 1's
    assert len(index) == 8
    fraction = 0.4
    seed = next(s for s in range(1000) if (lambda m: m[:4].any() and not m[4:].any())(
        labels.labeled(s, index, fraction)))  # the second shard holds no labeled record
    for k in range(2):  # (before: share 1's first batch never came)
        ds = data.load_split(str(out), "train", 2, shuffle=False, seed=seed,
                             label_fraction=fraction, drop_unlabeled=True, share=(k, 2))
        batches = list(ds.take(2))
        assert len(batches) == 2 and all((b[2]["h_bar"].numpy() > 0).all() for b in batches)
