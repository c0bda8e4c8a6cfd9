"""experiments.device_photographs: the photographs split into parts that each fit one device
call."""

import json
import os
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest

from experiments import device_photographs as dp

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_parts_keep_the_order_and_fill_each_call_up_to_its_budget():
    files = [("a", 4), ("b", 4), ("c", 3), ("d", 9), ("e", 1)]
    got = dp.parts(files, budget=10, first_extra=2)
    assert [p["files"] for p in got] == [["a", "b"], ["c"], ["d", "e"]]
    assert [p["bytes"] for p in got] == [10, 3, 10]
    assert sum(len(p["files"]) for p in got) == len(files)


def test_parts_refuse_a_file_or_wheels_larger_than_a_call():
    with pytest.raises(ValueError, match="big.jpg"):
        dp.parts([("small.jpg", 2), ("big.jpg", 11)], budget=10, first_extra=0)
    with pytest.raises(ValueError, match="no room"):
        dp.parts([("a.jpg", 1)], budget=10, first_extra=10)


def photograph_sets(root, counts=(3, 2, 2)):
    """``root/coco_mini/{train,test}`` and ``root/photos_extra/set1`` with ``counts`` random
    400 x 300 JPEGs ``p<k>.jpg`` each; returns the folders ``(coco_mini, photos_extra)``."""
    rng = np.random.default_rng(0)
    coco, extra = root / "coco_mini", root / "photos_extra"
    for folder, count in zip((coco / "train", coco / "test", extra / "set1"), counts):
        folder.mkdir(parents=True)
        for k in range(count):
            cv2.imwrite(str(folder / f"p{k}.jpg"), rng.integers(0, 256, (300, 400, 3), np.uint8))
    return coco, extra


def test_parts_copied_over_one_folder_rebuild_every_photograph(tmp_path):
    coco, extra = photograph_sets(tmp_path)
    (extra / "README.md").write_text("not a photograph")
    (tmp_path / "whl").mkdir()
    out = tmp_path / "dev"
    proc = subprocess.run(
        [sys.executable, "-m", "experiments.device_photographs", f"--coco_dir={coco}",
         f"--extra_dir={extra}", f"--output_dir={out}", f"--wheels_dir={tmp_path / 'whl'}",
         "--call_mib=1024"],  # the repository's own size does not decide the test
        cwd=REPO, capture_output=True, text=True, check=True)
    report = json.loads(proc.stdout)
    assert report["coco_mini"] == {"train": 3, "test": 2} and report["photographs"] == 7
    assert report["calls"][0]["carry"][1] == os.path.relpath(tmp_path / "whl", REPO)
    assert all(call["mib"] <= 1024 for call in report["calls"])
    merged = {}
    for part in sorted(os.listdir(out)):
        for d, _, fs in os.walk(out / part):
            for f in fs:
                rel = os.path.relpath(os.path.join(d, f), out / part)
                assert rel not in merged  # every file in exactly one part
                merged[rel] = os.path.join(d, f)
    assert sorted(merged) == sorted(
        [f"coco_mini/train/p{k}.jpg" for k in range(3)]
        + [f"coco_mini/test/p{k}.jpg" for k in range(2)]
        + [f"photos_extra/set1/p{k}.jpg" for k in range(2)])
    for rel in merged:  # byte for byte (a gray re-encoding of coco_mini had other sizes)
        original = (coco / rel.split("/", 1)[1] if rel.startswith("coco_mini/")
                    else extra / rel.split("/", 1)[1])
        with open(merged[rel], "rb") as a, open(original, "rb") as b:
            assert a.read() == b.read(), rel
    # the chunks' check of the photographs (names and sizes) sees the same set there
    from stnh_tf.training import ledger

    whole = tmp_path / "whole"
    for rel, path in merged.items():
        os.makedirs(whole / os.path.dirname(rel), exist_ok=True)
        shutil.copyfile(path, whole / rel)
    assert ledger.listing_digest([str(whole / "coco_mini" / "train")]) == \
        ledger.listing_digest([str(coco / "train")])


def _git_repo(root, files):
    """A git repository at ``root`` holding ``files`` (relative path -> bytes), committed."""
    for rel, data in files.items():
        os.makedirs(os.path.dirname(root / rel) or root, exist_ok=True)
        (root / rel).write_bytes(data)
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false"]
    subprocess.run(["git", "init", "-q", str(root)], check=True)
    subprocess.run(git + ["add", "-A"], cwd=root, check=True)
    subprocess.run(git + ["commit", "-qm", "files"], cwd=root, check=True)


MIB = 2 ** 20
ASIDE = {"semi_supervised/run.keras": b"a" * 3 * MIB,
         "stnh_tf/weights/stage1.keras": b"b" * 2 * MIB,
         "stnh_tf/weights/paper/stage1.keras": b"c" * MIB}
KEPT = {"semi_supervised/run.json": b"{}", "paper_schedule/stage1.keras": b"d" * 50,
        "stnh_tf/weights/model_card.json": b"{}"}


def test_set_aside_removes_the_unread_models_and_restore_brings_them_back(tmp_path):
    _git_repo(tmp_path, {**ASIDE, **KEPT})
    assert dp.aside_files(str(tmp_path)) == sorted(ASIDE)
    assert dp.set_aside(str(tmp_path)) == 6 * MIB
    assert not any((tmp_path / rel).exists() for rel in ASIDE)
    assert all((tmp_path / rel).read_bytes() == data for rel, data in KEPT.items())
    assert dp.set_aside(str(tmp_path)) == 0  # already aside: nothing more, no error
    assert dp.restore(str(tmp_path)) == sorted(ASIDE)
    assert all((tmp_path / rel).read_bytes() == data for rel, data in ASIDE.items())
    assert subprocess.run(["git", "status", "--porcelain"], cwd=tmp_path, capture_output=True,
                          text=True, check=True).stdout == ""
    (tmp_path / "stnh_tf/weights/stage1.keras").write_bytes(b"retrained")
    with pytest.raises(RuntimeError, match="stnh_tf/weights/stage1.keras"):
        dp.set_aside(str(tmp_path))
    assert all((tmp_path / rel).exists() for rel in ASIDE)  # nothing removed


def test_set_aside_gives_the_calls_the_models_room(tmp_path):
    """The binary in a repository of its own: with --set_aside the tree it reports is smaller by
    the models set aside; a failed planning checks them out again."""
    repo = tmp_path / "repo"
    script = open(os.path.join(REPO, "experiments", "device_photographs.py"), "rb").read()
    ledger = json.dumps([{"stage": 2, "done": False}]).encode()
    _git_repo(repo, {**ASIDE, **KEPT, "experiments/device_photographs.py": script,
                     "paper_schedule/ledger.json": ledger})
    photos = tmp_path / "photos"
    for folder in ("coco/train", "coco/test", "extra/set1"):
        (photos / folder).mkdir(parents=True)
        cv2.imwrite(str(photos / folder / "p.jpg"), np.full((240, 320), 7, np.uint8))
    (tmp_path / "whl").mkdir()
    run = [sys.executable, str(repo / "experiments" / "device_photographs.py"),
           f"--coco_dir={photos / 'coco'}", f"--extra_dir={photos / 'extra'}",
           f"--output_dir={tmp_path / 'dev'}", f"--wheels_dir={tmp_path / 'whl'}"]
    env = dict(os.environ, PYTHONPATH=REPO)
    plain = json.loads(subprocess.run(run, env=env, capture_output=True, text=True,
                                      check=True).stdout)
    aside = json.loads(subprocess.run(run + ["--set_aside"], env=env, capture_output=True,
                                      text=True, check=True).stdout)
    assert not any((repo / rel).exists() for rel in ASIDE)
    assert plain["tracked_mib"] - aside["tracked_mib"] == pytest.approx(6.0, abs=0.11)
    assert aside["set_aside"]["mib"] == 6.0 and "set_aside" not in plain
    assert aside["calls"][-1]["command"].startswith("STAGE=2 ")
    back = json.loads(subprocess.run(run[:2] + ["--restore"], env=env, capture_output=True,
                                     text=True, check=True).stdout)
    assert back["restored"] == sorted(ASIDE)
    proc = subprocess.run(run[:2] + ["--set_aside", f"--coco_dir={tmp_path / 'none'}"], env=env,
                          capture_output=True, text=True)
    assert proc.returncode != 0 and "none" in proc.stderr
    assert all((repo / rel).read_bytes() == data for rel, data in ASIDE.items())


def test_the_next_chunk_goes_through_the_stages_then_the_other_parts(tmp_path, monkeypatch):
    """next_chunk: the stage the hierarchy's ledger rows are at (rows of another part left out),
    then, once stage 3 is done, each part of SCHEDULE_PARTS in order until its model exists."""
    folder = tmp_path / "paper_schedule"
    folder.mkdir()
    monkeypatch.setattr(dp, "REPO", str(tmp_path))

    def at(*rows):
        (folder / "ledger.json").write_text(json.dumps(list(rows)))
        return dp.next_chunk()

    assert at({"stage": 2, "done": False}) == "STAGE=2"
    assert at({"stage": 2, "done": True}) == "STAGE=3"
    done3 = {"stage": 3, "done": True}
    assert at(done3) == "PART=sequence2"
    # a part's row (stage 1 of its own run) does not move the hierarchy back to stage 1
    assert at(done3, {"stage": 1, "part": "sequence2", "done": False}) == "PART=sequence2"
    (folder / "sequence2.keras").write_bytes(b"finished")
    assert at(done3) == "PART=stage1_l2-10_l1-1"
    (folder / "stage1_l2-10_l1-1.keras").write_bytes(b"finished")
    assert at(done3) is None
