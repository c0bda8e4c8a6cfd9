"""experiments.device_photographs: the photographs split into parts that each fit one device
call."""

import json
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from experiments import device_photographs as dp
from stnh_tf.data import sources

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


def test_parts_copied_over_one_folder_rebuild_every_photograph(tmp_path):
    rng = np.random.default_rng(0)
    coco, extra = tmp_path / "coco_mini", tmp_path / "photos_extra"
    for folder, count in ((coco / "train", 3), (coco / "test", 2), (extra / "set1", 2)):
        folder.mkdir(parents=True)
        for k in range(count):
            cv2.imwrite(str(folder / f"p{k}.jpg"), rng.integers(0, 256, (300, 400, 3), np.uint8))
    (extra / "README.md").write_text("not a photograph")
    (tmp_path / "whl").mkdir()
    out = tmp_path / "dev"
    proc = subprocess.run(
        [sys.executable, "-m", "experiments.device_photographs", f"--coco_dir={coco}",
         f"--extra_dir={extra}", f"--output_dir={out}", f"--wheels_dir={tmp_path / 'whl'}"],
        cwd=REPO, capture_output=True, text=True, check=True)
    report = json.loads(proc.stdout)
    assert report["coco_mini"] == {"train": 3, "test": 2} and report["photographs"] == 7
    assert report["calls"][0]["carry"][1] == os.path.relpath(tmp_path / "whl", REPO)
    assert all(call["mib"] <= 64 for call in report["calls"])
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
    for k in range(3):  # coco_mini: the gray 320x240 the training reads, pixel for pixel
        np.testing.assert_array_equal(
            sources.load_gray_320x240(merged[f"coco_mini/train/p{k}.jpg"]),
            sources.load_gray_320x240(str(coco / "train" / f"p{k}.jpg")))
    for k in range(2):  # photos_extra: byte for byte
        with open(merged[f"photos_extra/set1/p{k}.jpg"], "rb") as a, \
                open(extra / "set1" / f"p{k}.jpg", "rb") as b:
            assert a.read() == b.read()
