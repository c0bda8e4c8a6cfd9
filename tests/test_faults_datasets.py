"""A hostile review of how datasets are written and re-made (issue 79's fourth round): each test
fails on the code before it.

Data loss: a ``--overwrite`` that failed (every photograph skipped) or was cut short marked the
complete split incomplete before any work and replaced its shards one by one: the old split was
gone, or its intact shards unreadable; files named like shards in a folder with no
``metadata.json`` were deleted. Silently wrong: two runs writing ``train`` and ``val`` at once
both passed the hold-out check (photographs in both); the splits of one stage-k dataset could
come from different stage-(k-1) models; ``stage1.check_made`` took photometric or held-out pairs
for the paper's. Crashes: a corrupted input shard and a section without ``shards``
(tracebacks). ``make_stage_dataset`` cut short could not be resumed by the same command."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from stnh_tf.data import metadata, pairs, stage1, stage_k
from stnh_tf.data import tfrecords as data
from stnh_tf.data.tfrecords import METADATA_FILE, ShardError

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WEIGHTS = os.path.join(ROOT, "stnh_tf", "weights")
QUIET = lambda *a, **k: None  # noqa: E731


def _photos(folder, n=4, seed=0):
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for i in range(n):
        img = cv2.GaussianBlur((rng.random((240, 320)) * 255).astype(np.uint8), (7, 7), 2)
        cv2.imwrite(str(folder / f"img{i:02d}.png"), img)
    return str(folder)


def _digests(folder, split):
    return {p: hashlib.sha256(open(os.path.join(folder, p), "rb").read()).hexdigest()
            for p in sorted(os.listdir(folder)) if p.startswith(f"{split}-")}


@pytest.fixture()
def complete(tmp_path):
    out = tmp_path / "ds"
    stage1.make_dataset("bundled", str(out), "train", seed=0, max_images=3, samples_per_image=1,
                        num_shards=2, log=QUIET)
    return out, _digests(out, "train"), data.split_info(str(out), "train")


def test_an_overwrite_with_every_photograph_skipped_keeps_the_complete_split(complete, tmp_path):
    out, before, section = complete
    bad = tmp_path / "bad"
    bad.mkdir()
    for name in ("a.png", "b.jpg"):
        (bad / name).write_bytes(b"not an image")
    with pytest.raises(ValueError, match="nothing written, the earlier complete split is kept"):
        stage1.make_dataset("folder", str(out), "train", image_dir=str(bad), num_shards=1,
                            overwrite=True, log=QUIET)
    assert _digests(out, "train") == before  # (the 2 shards were emptied, the section lost)
    assert data.split_info(str(out), "train") == section
    assert not [p for p in os.listdir(out) if ".tmp" in p]


def test_an_overwrite_cut_short_keeps_the_complete_split_readable(complete, monkeypatch):
    out, before, section = complete
    real, calls = pairs.generate_item_samples, []

    def interrupted(item, **kw):
        calls.append(item.index)
        if len(calls) == 2:
            raise KeyboardInterrupt  # (Ctrl-C; a kill -9 leaves the same files, less the temps)
        return real(item, **kw)

    monkeypatch.setattr(pairs, "generate_item_samples", interrupted)
    with pytest.raises(KeyboardInterrupt):
        stage1.make_dataset("bundled", str(out), "train", seed=5, max_images=3,
                            samples_per_image=1, num_shards=3, overwrite=True, log=QUIET)
    assert data.split_info(str(out), "train") == section  # (was: status "incomplete")
    assert _digests(out, "train") == before
    assert len(data.load_arrays(str(out), "train")["h_ba"]) == 3
    monkeypatch.setattr(pairs, "generate_item_samples", real)
    stage1.make_dataset("bundled", str(out), "train", seed=5, max_images=3, samples_per_image=1,
                        num_shards=3, overwrite=True, log=QUIET)
    made = data.split_info(str(out), "train")
    assert (made["seed"], made["num_shards"]) == (5, 3)
    assert sorted(_digests(out, "train")) == [f"train-0000{k}-of-00003.tfrecord"
                                              for k in range(3)]  # the 2 old shards removed


def test_files_named_like_shards_without_metadata_are_not_written_over(tmp_path):
    out = tmp_path / "foreign"
    out.mkdir()
    mine = {f"train-0000{k}-of-00004.tfrecord": f"user data {k}" for k in range(4)}
    for name, text in mine.items():
        (out / name).write_text(text)
    with pytest.raises(ValueError, match="named like the 'train' split's shards"):
        stage1.make_dataset("bundled", str(out), "train", max_images=2, num_shards=2, log=QUIET)
    assert {p.name: p.read_text() for p in out.glob("train-*")} == mine
    assert not (out / METADATA_FILE).exists()


def test_train_and_val_written_at_once_cannot_share_photographs(tmp_path, monkeypatch):
    """The hold-out check ran before any lock and only against a complete split: runs writing
    train (--val_fraction=0.2) and val (0.5) at once both passed. The writer now records the
    flags in the incomplete section and checks again under the metadata's lock at the start and
    before the swap."""
    photos = _photos(tmp_path / "photos", 6)
    out = str(tmp_path / "ho")
    os.makedirs(out)
    val_marker = {"status": "incomplete", "started_pid": 1, "source": "folder",
                  "image_dir": photos, "val_fraction": 0.5}
    metadata.update_metadata(out, "val", val_marker, {"stage": 1})  # a val run under way
    with pytest.raises(ValueError, match=r"val split being written .* --val_fraction=0.5"):
        stage1.make_dataset("folder", out, "train", image_dir=photos, val_fraction=0.2,
                            samples_per_image=1, num_shards=1, log=QUIET)
    out2 = str(tmp_path / "ho2")
    real = pairs.generate_item_samples

    def a_val_run_starts_meanwhile(item, **kw):
        if item.index == 0:
            metadata.update_metadata(out2, "val", val_marker)
        return real(item, **kw)

    monkeypatch.setattr(pairs, "generate_item_samples", a_val_run_starts_meanwhile)
    with pytest.raises(ValueError, match="--val_fraction=0.5"):
        stage1.make_dataset("folder", out2, "train", image_dir=photos, val_fraction=0.2,
                            samples_per_image=1, num_shards=1, log=QUIET)
    assert not [p for p in os.listdir(out2) if p.endswith(".tfrecord") or ".tmp" in p]
    monkeypatch.setattr(pairs, "generate_item_samples", real)
    section = stage1.make_dataset("folder", str(tmp_path / "ho3"), "train", image_dir=photos,
                                  val_fraction=0.5, samples_per_image=1, num_shards=1, log=QUIET)
    assert section["status"] == "complete"  # (the same fraction: no refusal)


def test_check_made_refuses_photometric_and_held_out_pairs(tmp_path):
    photos = _photos(tmp_path / "photos", 4)
    plain = dict(source="folder", image_dir=photos, samples_per_image=1, seed=0, max_images=0)
    for name, extra, differs in (("ph", {"photometric": True}, "photometric"),
                                 ("vf", {"val_fraction": 0.5}, "val_fraction")):
        d = str(tmp_path / name)
        stage1.make_dataset(split="train", output_dir=d, num_shards=1, log=QUIET, **plain,
                            **extra)
        with pytest.raises(ValueError, match=f"other flags .*'{differs}'"):
            stage1.check_made(d, "train", "folder", photos, 1, 0, 0)
    d = str(tmp_path / "paper")
    stage1.make_dataset(split="train", output_dir=d, num_shards=1, log=QUIET, **plain)
    stage1.check_made(d, "train", "folder", photos, 1, 0, 0)  # the paper's protocol: accepted


@pytest.fixture(scope="module")
def stage1_data(tmp_path_factory):
    d = str(tmp_path_factory.mktemp("stage1"))
    stage1.make_dataset("bundled", d, "train", seed=0, num_shards=2, max_images=2,
                        samples_per_image=1, log=QUIET)
    stage1.make_dataset("bundled", d, "test", seed=1, num_shards=1, max_images=2,
                        samples_per_image=1, log=QUIET)
    return d


def test_the_splits_of_a_stage_k_dataset_come_from_one_model(stage1_data, tmp_path):
    out = str(tmp_path / "s2")
    model_a = os.path.join(WEIGHTS, "stage1.keras")
    model_b = os.path.join(WEIGHTS, "paper_recipe", "stage1.keras")
    section = stage_k.make_stage_dataset(2, stage1_data, out, "test", model_dir=model_a,
                                         log=QUIET)
    assert section["model_sha256"] == hashlib.sha256(open(model_a, "rb").read()).hexdigest()
    assert sum(section["degenerate_predictions"].values()) == 2  # (written with the section)
    with pytest.raises(ValueError, match="every split of one stage-k dataset comes from one"):
        stage_k.check_stage_arguments(2, stage1_data, out, ["train"], model_dir=model_b)
    link = str(tmp_path / "same_model.keras")
    os.symlink(model_a, link)
    source = stage_k.made_from(stage1_data, link)
    assert stage_k.check_one_source(out, ["train", "test"], source) == ["test"]  # kept
    assert stage_k.check_one_source(out, ["train"], source) == []
    assert stage_k.check_one_source(out, ["test"], stage_k.made_from(stage1_data,
                                                                     model_b)) == []
    stage_k.check_made(out, "test", stage1_data, model_a)  # what a reproduction re-run checks
    with pytest.raises(ValueError, match="the 'test' pairs made from .* move it aside"):
        stage_k.check_made(out, "test", stage1_data, model_b)
    import shutil

    moved = str(tmp_path / "moved_input")  # a folder moved is the same input (its digest)
    shutil.copytree(stage1_data, moved)
    stage_k.check_made(out, "test", moved, link)
    assert stage_k.check_one_source(out, ["test"], stage_k.made_from(moved, model_a)) == ["test"]


def test_a_corrupted_input_shard_is_named(stage1_data, tmp_path):
    import shutil

    src = str(tmp_path / "in")
    shutil.copytree(stage1_data, src)
    shard = os.path.join(src, "train-00000-of-00002.tfrecord")
    raw = bytearray(open(shard, "rb").read())
    raw[500:600] = bytes(b ^ 0xFF for b in raw[500:600])  # the same size: passes the size check
    open(shard, "wb").write(bytes(raw))
    with pytest.raises(ShardError, match="train-00000-of-00002.tfrecord.* corrupted"):
        stage_k.make_stage_dataset(2, src, str(tmp_path / "out"), "train",
                                   predict=lambda a, b: np.tile(np.eye(3), (len(a), 1, 1)),
                                   log=QUIET)


def test_a_section_without_its_shards_is_refused_in_one_line(tmp_path):
    d = tmp_path / "badmeta"
    d.mkdir()
    (d / METADATA_FILE).write_text(json.dumps({
        "format": "stnh_tf.dataset", "format_version": 1, "stage": 1,
        "splits": {"train": {"status": "complete", "num_samples": 9},
                   "val": {"status": "empty", "num_samples": 0, "shards": []}}}))
    with pytest.raises(ValueError, match="does not list its shards"):
        data.shard_paths(str(d), "train")
    with pytest.raises(ValueError, match="is empty: every item of its generation was skipped"):
        data.split_info(str(d), "val")


@pytest.mark.slow
def test_make_stage_dataset_cut_short_resumes_with_the_same_command(stage1_data, tmp_path):
    """A run killed while making ``test`` left ``train`` complete; the same command refused
    ("pass --overwrite", which would make train again). It keeps train now and makes test."""
    out = str(tmp_path / "s2")
    model = os.path.join(WEIGHTS, "stage1.keras")
    base = [sys.executable, "-m", "data_prep.make_stage_dataset", "--stage=2",
            f"--input_dir={stage1_data}", f"--model_dir={model}", f"--output_dir={out}",
            "--num_workers=1"]
    proc = subprocess.run(base + ["--splits=train"], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    before = _digests(out, "train")
    proc = subprocess.run(base, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "train: complete in" in proc.stderr and "kept" in proc.stderr
    assert _digests(out, "train") == before
    assert data.split_info(out, "test")["num_samples"] == 2


def _dies_on_the_second_item(item):
    if item.index == 1:
        os._exit(3)  # (as a decoder crashing in native code)
    return []


def test_a_worker_that_dies_is_said_in_one_line(tmp_path):
    """A worker process dying (a decoder crash) ended make_dataset in a BrokenProcessPool
    traceback; it is a ``ChildProcessError`` (an ``OSError``: the binaries' one-line errors)
    naming the items and the way to find the one, and no temporary shard is left."""
    from stnh_tf.data import writer

    items = [writer.WorkItem(i, f"photo{i}.png") for i in range(4)]
    with pytest.raises(ChildProcessError, match=r"photo\d.png \.\.\. photo\d.png .*num_workers=1"):
        writer.write_sharded(str(tmp_path), "train", items, _dies_on_the_second_item,
                             num_shards=1, num_workers=2, chunk_size=1, log=QUIET)
    assert not [p for p in os.listdir(tmp_path) if ".tmp" in p or p.endswith(".tfrecord")]


def test_a_stage_k_folder_is_made_again_from_a_new_model_split_after_split(stage1_data,
                                                                          tmp_path):
    """The final read of this round: with the one-source rule, making train again from a new
    model was refused because test (still the old model's) was 'left out'; the command names
    every split it writes (``writing``), which may then be made again one after another."""
    out = str(tmp_path / "s2")
    model_a = os.path.join(WEIGHTS, "stage1.keras")
    model_b = os.path.join(WEIGHTS, "paper_recipe", "stage1.keras")
    for split in ("train", "test"):
        stage_k.make_stage_dataset(2, stage1_data, out, split, model_dir=model_a, log=QUIET)
    for split in ("train", "test"):
        stage_k.make_stage_dataset(2, stage1_data, out, split, model_dir=model_b, log=QUIET,
                                   overwrite=True, writing=["train", "test"])
    source = stage_k.made_from(stage1_data, model_b)
    assert stage_k.check_one_source(out, ["train", "test"], source) == ["train", "test"]


def test_an_incomplete_splits_old_shards_are_removed_by_the_next_run(tmp_path):
    """A run cut short kept, in its incomplete section, the shards it was to replace
    (``replacing``); the next run removes them (the start marker dropped the list before)."""
    out = tmp_path / "ds"
    stage1.make_dataset("bundled", str(out), "train", max_images=3, samples_per_image=1,
                        num_shards=3, log=QUIET)
    old = sorted(p.name for p in out.glob("train-*.tfrecord"))
    section = data.split_info(str(out), "train")
    metadata.update_metadata(str(out), "train", {"status": "incomplete", "started_pid": 1,
                                                 "replacing": [s["file"] for s in
                                                               section["shards"]]})
    stage1.make_dataset("bundled", str(out), "train", max_images=3, samples_per_image=1,
                        num_shards=1, log=QUIET)
    assert len(old) == 3 and sorted(p.name for p in out.glob("train-*.tfrecord")) == [
        "train-00000-of-00001.tfrecord"]


def test_a_users_file_named_like_a_shard_beside_a_listed_split_is_not_written_over(complete):
    """Files named like the split's shards that its metadata.json does not list were refused
    only where the split had no section: beside a complete split of 2 shards, a user's
    ``train-00000-of-00001.tfrecord`` was replaced without a word by ``--overwrite
    --num_shards=1``. It is refused now, the user's file and the split as they were."""
    out, before, section = complete
    user = out / "train-00000-of-00001.tfrecord"
    user.write_bytes(b"USER DATA")
    with pytest.raises(ValueError, match=r"named like the 'train' split's shards .*"
                                         r"train-00000-of-00001\.tfrecord"):
        stage1.make_dataset("bundled", str(out), "train", seed=0, max_images=3,
                            samples_per_image=1, num_shards=1, overwrite=True, log=QUIET)
    assert user.read_bytes() == b"USER DATA"
    assert {k: v for k, v in _digests(out, "train").items() if k != user.name} == before
    assert data.split_info(str(out), "train") == section


def test_a_run_cut_short_in_its_swap_is_finished_by_the_next(complete, monkeypatch):
    """A run cut short while renaming its shards into place leaves shards of its own layout
    that no complete section lists: its marker names them (``writing``), so the next run takes
    them for the split's own (not a user's) and removes those its layout lacks."""
    from stnh_tf.data import writer

    out, _, _ = complete
    real = os.replace

    def killed(src, dst):  # the first new shard renamed into place, then the process stops
        real(src, dst)
        if ".tfrecord.tmp-" in os.fspath(src):
            raise KeyboardInterrupt

    monkeypatch.setattr(writer.os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        stage1.make_dataset("bundled", str(out), "train", seed=3, max_images=3,
                            samples_per_image=1, num_shards=3, overwrite=True, log=QUIET)
    monkeypatch.setattr(writer.os, "replace", real)
    assert (out / "train-00000-of-00003.tfrecord").exists()
    marker = metadata.read_metadata_file(str(out))["splits"]["train"]
    assert marker["status"] == "incomplete"
    assert "train-00000-of-00003.tfrecord" in marker["writing"]
    stage1.make_dataset("bundled", str(out), "train", seed=3, max_images=3, samples_per_image=1,
                        num_shards=1, log=QUIET)
    assert sorted(p.name for p in out.glob("train-*.tfrecord")) == [
        "train-00000-of-00001.tfrecord"]
    assert data.split_info(str(out), "train")["status"] == "complete"
