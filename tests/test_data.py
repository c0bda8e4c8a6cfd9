"""Data preparation: protocol, TFRecord round trip, determinism, bad input, readers, generators.

References are written here with OpenCV/NumPy (conftest's ``to_bar``, ``cv2_warp``,
``inside_mask``), independently of stnh_tf. Sources are the bundled photographs or images made in
``tmp_path`` (nothing from outside the package).
"""

import functools
import json
import os
import re
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest
from PIL import Image

from conftest import cv2_warp, inside_mask, photo_folder, to_bar
from stnh_tf.data import stage1, writer
from stnh_tf.data import tfrecords as data
from stnh_tf.data import features, image_checks, pair_datasets, pairs, sources
from stnh_tf.data import bundled_photos

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CORNERS = np.array([[0, 0], [128, 0], [128, 128], [0, 128]], np.float64)


def _ref_gray(path):
    """Independent reference of the loader for an 8-bit colour/gray file."""
    img = cv2.imread(path, cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY)
    return img


def _dlt(src, dst):
    """float64 homography with dst ~ H @ src from four points (getPerspectiveTransform's system)."""
    a, b = [], []
    for (x, y), (u, v) in zip(src, dst):
        a += [[x, y, 1, 0, 0, 0, -u * x, -u * y], [0, 0, 0, x, y, 1, -v * x, -v * y]]
        b += [u, v]
    return np.append(np.linalg.solve(np.array(a), np.array(b)), 1.0).reshape(3, 3)


def _resize(gray):
    h, w = gray.shape
    interp = cv2.INTER_AREA if (w >= 320 and h >= 240) else cv2.INTER_LINEAR
    return cv2.resize(gray, (320, 240), interpolation=interp)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """3 bundled photographs x 3 samples, written in-process, 2 shards."""
    out = str(tmp_path_factory.mktemp("ds"))
    stage1.make_dataset("bundled", out, "train", max_images=3, seed=7, num_shards=2,
                        num_workers=1, log=lambda m: None)
    return out


@pytest.fixture(scope="module")
def arrays(dataset):
    return data.load_arrays(dataset, "train")


# ------------------------------------------------------------------------------------------------
# The protocol against a literal, independent implementation
# ------------------------------------------------------------------------------------------------
def test_protocol_matches_literal_reference():
    image_id, path = bundled_photos.bundled_image_files()[2]
    image_a = _resize(_ref_gray(path))
    np.testing.assert_array_equal(sources.load_gray_320x240(path), image_a)
    seed, index = 5, 11
    samples = pairs.make_image_samples(image_a, seed, index, image_id)
    rng = np.random.default_rng([seed, index])
    assert len(samples) == 3
    for k, s in enumerate(samples):
        x0, y0 = int(rng.integers(32, 160, endpoint=True)), int(rng.integers(32, 80, endpoint=True))
        offsets = rng.uniform(-32, 32, size=(4, 2))
        h_img = _dlt(CORNERS + [x0, y0], CORNERS + [x0, y0] + offsets)
        image_b = cv2.warpPerspective(image_a, h_img, (320, 240),
                                      flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
        t = np.array([[1, 0, x0], [0, 1, y0], [0, 0, 1]], np.float64)
        h_patch = np.linalg.inv(t) @ h_img @ t
        h_patch /= h_patch[2, 2]
        assert s["square_xy"].tolist() == [x0, y0]
        assert s["index"] == index * 3 + k and s["image_id"] == image_id
        np.testing.assert_allclose(s["h_ba"], h_patch, rtol=1e-9, atol=1e-9)
        np.testing.assert_array_equal(s["patch_a"], image_a[y0:y0 + 128, x0:x0 + 128])
        np.testing.assert_array_equal(s["context_a"], image_a[y0 - 32:y0 + 160, x0 - 32:x0 + 160])
        diff_b = np.abs(s["patch_b"].astype(int) - image_b[y0:y0 + 128, x0:x0 + 128])
        assert diff_b.max() <= 1 and (diff_b > 0).mean() < 0.01
        ref_t = cv2_warp(image_a[y0:y0 + 128, x0:x0 + 128], h_patch)
        diff_t = np.abs(s["patch_a_t"].astype(np.float32) - np.rint(ref_t))
        assert diff_t.max() <= 1 and (diff_t > 0).mean() < 0.01
        np.testing.assert_allclose(s["h_bar"], to_bar(h_patch).ravel()[:8], atol=1e-5)
        np.testing.assert_array_equal(s["h_prev"], np.eye(3))


# ------------------------------------------------------------------------------------------------
# TFRecords: round trip, geometry on read-back data, metadata
# ------------------------------------------------------------------------------------------------
def test_round_trip_every_field(dataset, arrays):
    files = bundled_photos.bundled_image_files()[:3]
    expected = [s for i, (image_id, p) in enumerate(files)
                for s in pairs.make_image_samples(sources.load_gray_320x240(p), 7, i, image_id)]
    assert len(arrays["index"]) == len(expected) == 9
    for j, s in enumerate(expected):
        for name in ("patch_a", "patch_b", "patch_a_t"):
            np.testing.assert_array_equal(np.rint(arrays[name][j, ..., 0] * 255), s[name])
        np.testing.assert_array_equal(arrays["context_a"][j], s["context_a"])
        np.testing.assert_array_equal(arrays["h_bar"][j], s["h_bar"])
        np.testing.assert_array_equal(arrays["h_ba"][j], s["h_ba"].astype(np.float32))
        np.testing.assert_array_equal(arrays["h_prev"][j], np.eye(3))
        assert arrays["h_mask"][j] == 1.0
        np.testing.assert_array_equal(arrays["square_xy"][j], s["square_xy"])
        assert arrays["image_id"][j] == s["image_id"] and arrays["index"][j] == s["index"]
    assert arrays["patch_a"].dtype == np.float32 and arrays["patch_a"].shape == (9, 128, 128, 1)
    assert arrays["h_ba"].dtype == np.float64 and arrays["h_ba"].shape == (9, 3, 3)


def test_raw_records_parse_with_tensorflow_and_numpy(dataset, arrays):
    import tensorflow as tf

    path = data.shard_paths(dataset, "train")[0]
    rec = next(iter(tf.data.TFRecordDataset(path))).numpy()
    ex = tf.train.Example.FromString(rec).features.feature  # the official protobuf class
    np.testing.assert_array_equal(np.frombuffer(ex["patch_b"].bytes_list.value[0], np.uint8),
                                  np.rint(arrays["patch_b"][0].ravel() * 255))
    np.testing.assert_array_equal(ex["h_bar"].float_list.value, arrays["h_bar"][0])
    assert list(ex["square_xy"].int64_list.value) == arrays["square_xy"][0].tolist()
    np_dec = features.decode_example(rec)
    raw = next(iter(data.load_raw(dataset, "train")))
    for name in features.FEATURE_NAMES:
        value = raw[name].numpy()
        value = value.decode() if name == "image_id" else value
        np.testing.assert_array_equal(np.asarray(np_dec[name]).reshape(np.shape(value)), value)


def test_serialize_validates_and_keeps_negative_ints():
    s = {n: np.zeros(f.shape, f.numpy_dtype if f.kind != "string" else object)
         for n, f in features.FIELD_BY_NAME.items()}
    s.update(image_id="dir/ümlaut.png", index=-5, square_xy=np.array([-1, 2 ** 40]),
             h_ba=np.arange(9.0).reshape(3, 3), h_mask=0.0)
    back = features.decode_example(features.serialize_example(s))
    assert back["image_id"] == "dir/ümlaut.png" and back["index"] == -5
    assert back["square_xy"].tolist() == [-1, 2 ** 40]
    np.testing.assert_array_equal(back["h_ba"], np.arange(9.0))
    with pytest.raises(ValueError, match="patch_b"):
        features.serialize_example({**s, "patch_b": np.zeros((64, 64), np.uint8)})
    with pytest.raises(ValueError, match="h_bar"):
        features.serialize_example({k: v for k, v in s.items() if k != "h_bar"})


def test_geometry_of_read_back_samples(arrays):
    n = len(arrays["index"])
    for j in range(n):
        h = arrays["h_ba"][j]
        pa = np.rint(arrays["patch_a"][j, ..., 0] * 255)
        pb = np.rint(arrays["patch_b"][j, ..., 0] * 255)
        pat = np.rint(arrays["patch_a_t"][j, ..., 0] * 255)
        warped = cv2_warp(pa, h)  # stored (float32) H reproduces patch_a_t
        assert np.abs(warped - pat).max() <= 1.5
        inside = inside_mask(h)
        assert inside.mean() > 0.3
        assert np.abs(pat - pb)[inside].mean() < 0.5  # patch_a_t == patch_b on the overlap
        assert np.abs(pat)[~inside_mask(h, 128, 128) & (warped == 0)].max(initial=0) == 0
        q = h @ np.c_[CORNERS, np.ones(4)].T
        offsets = (q[:2] / q[2]).T - CORNERS  # where patch_b's corners lie in patch_a
        assert np.abs(offsets).max() <= 32 + 1e-3
        np.testing.assert_allclose(arrays["h_bar"][j], to_bar(h).ravel()[:8], atol=1e-5)
        x0, y0 = arrays["square_xy"][j]
        assert 32 <= x0 <= 160 and 32 <= y0 <= 80
        np.testing.assert_array_equal(arrays["context_a"][j, 32:160, 32:160], pa)


def test_metadata_records_protocol_counts_and_shards(dataset):
    meta = data.read_metadata(dataset)
    assert meta["stage"] == 1 and meta["feature_spec"]["format"] == features.FORMAT_VERSION
    info = meta["splits"]["train"]
    assert info["status"] == "complete" and info["seed"] == 7 and info["source"] == "bundled"
    p = info["protocol"]
    assert (p["image_width"], p["image_height"], p["patch_size"], p["border"],
            p["max_perturbation"], p["samples_per_image"], p["context_size"]) == \
        (320, 240, 128, 32, 32.0, 3, 192)
    assert info["num_samples"] == 9 and info["num_items_used"] == 3 and info["skipped"] == []
    names = sorted(os.listdir(dataset))
    assert [s["file"] for s in info["shards"]] == ["train-00000-of-00002.tfrecord",
                                                   "train-00001-of-00002.tfrecord"]
    assert all(s["file"] in names for s in info["shards"])
    assert not [n for n in names if ".tmp" in n]
    assert sum(s["num_samples"] for s in info["shards"]) == 9
    assert 86_000 < info["bytes_per_sample"] < 87_000


def test_determinism_across_worker_counts(tmp_path):
    shards = {}
    for w in (1, 2):
        out = str(tmp_path / f"w{w}")
        stage1.make_dataset("bundled", out, "train", max_images=4, seed=3, num_shards=3,
                            num_workers=w, chunk_size=1, log=lambda m: None)
        shards[w] = {n: open(os.path.join(out, n), "rb").read()
                     for n in sorted(os.listdir(out)) if n.endswith(".tfrecord")}
    assert list(shards[1]) == [f"train-0000{k}-of-00003.tfrecord" for k in range(3)]
    assert shards[1] == shards[2]
    other = str(tmp_path / "seed4")
    stage1.make_dataset("bundled", other, "train", max_images=4, seed=4, num_shards=3,
                        num_workers=1, log=lambda m: None)
    assert open(os.path.join(other, "train-00000-of-00003.tfrecord"), "rb").read() != \
        shards[1]["train-00000-of-00003.tfrecord"]


def test_complete_split_is_not_regenerated_without_overwrite(tmp_path):
    out = str(tmp_path / "d")
    quiet = lambda *a, **k: None  # noqa: E731
    stage1.make_dataset("bundled", out, "train", max_images=2, seed=7, num_shards=1, log=quiet)
    before = data.load_arrays(out, "train")["patch_b"]
    with pytest.raises(FileExistsError, match="complete 'train' split .*--overwrite"):
        stage1.make_dataset("bundled", out, "train", max_images=2, seed=8, num_shards=1, log=quiet)
    np.testing.assert_array_equal(data.load_arrays(out, "train")["patch_b"], before)  # untouched
    stage1.make_dataset("bundled", out, "train", max_images=2, seed=8, num_shards=1, log=quiet,
                        overwrite=True)
    after = data.load_arrays(out, "train")["patch_b"]
    assert after.shape == before.shape and not np.array_equal(after, before)


@pytest.mark.slow  # (a binary end to end, 6-15 s; make test-all)
def test_cli_smoke_two_splits_share_metadata(tmp_path):
    out = str(tmp_path / "cli")
    for split, seed in (("train", 0), ("test", 1)):
        proc = subprocess.run(
            [sys.executable, "-m", "data_prep.make_dataset", "--source=bundled",
             f"--output_dir={out}", f"--split={split}", f"--seed={seed}", "--max_images=2",
             "--num_shards=2", "--num_workers=2"], cwd=REPO, capture_output=True, text=True,
            timeout=120)
        assert proc.returncode == 0, proc.stderr[-2000:]
    meta = data.read_metadata(out)
    assert sorted(meta["splits"]) == ["test", "train"]
    assert meta["splits"]["train"]["seed"] == 0 and meta["splits"]["test"]["seed"] == 1
    assert meta["splits"]["test"]["num_samples"] == 6
    assert "data_prep.make_dataset" in meta["splits"]["test"]["command"]


# ------------------------------------------------------------------------------------------------
# Bad input
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def messy_folder(tmp_path_factory):
    """A folder with good, convertible and broken files (made here, from a bundled photo)."""
    root = tmp_path_factory.mktemp("messy")
    (root / "sub" / "deeper").mkdir(parents=True)
    rgb = cv2.cvtColor(cv2.imread(bundled_photos.bundled_image_files()[0][1]), cv2.COLOR_BGR2RGB)
    rgb = cv2.resize(rgb, (400, 300), interpolation=cv2.INTER_AREA)
    pil = Image.fromarray(rgb)
    pil.save(root / "good.jpg", quality=95)
    gray8 = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    g16 = (gray8.astype(np.uint16) * 257 + np.arange(300)[:, None].astype(np.uint16) % 200)
    cv2.imwrite(str(root / "sub" / "gray16.png"), g16)
    alpha = np.tile(np.linspace(0, 255, 400).astype(np.uint8), (300, 1))
    Image.fromarray(np.dstack([rgb, alpha]), "RGBA").save(root / "sub" / "rgba.png")
    pil.convert("P", palette=Image.Palette.ADAPTIVE, colors=64).save(root / "palette.png")
    pil.convert("CMYK").save(root / "sub" / "deeper" / "cmyk.jpg", quality=95)
    Image.fromarray(gray8[:80, :100]).save(root / "small.bmp")
    Image.fromarray(gray8).save(root / "gray.pgm")
    Image.fromarray(rgb).save(root / "color.tif")
    jpg = (root / "good.jpg").read_bytes()
    (root / "truncated.jpg").write_bytes(jpg[: len(jpg) // 2])
    (root / "empty.png").write_bytes(b"")
    (root / "notanimage.png").write_text("this is text, not a PNG\n" * 20)
    (root / "corrupt.tif").write_bytes(np.random.default_rng(0).bytes(5000))
    (root / "README.txt").write_text("ignored: not an image file name")
    return root, {"rgb": rgb, "gray8": gray8, "g16": g16, "alpha": alpha, "pil": pil}


def test_conversions_of_unusual_images(messy_folder):
    root, src = messy_folder
    g16 = src["g16"]
    np.testing.assert_array_equal(sources.load_gray_320x240(str(root / "sub" / "gray16.png")),
                                  _resize(np.rint(g16 / 257.0).astype(np.uint8)))
    luma = (0.299 * src["rgb"][..., 0] + 0.587 * src["rgb"][..., 1] + 0.114 * src["rgb"][..., 2])
    want = _resize(np.clip(np.rint(luma * src["alpha"] / 255.0), 0, 255).astype(np.uint8))
    got = sources.load_gray_320x240(str(root / "sub" / "rgba.png"))
    assert np.abs(got.astype(int) - want).max() <= 1
    pal = np.asarray(src["pil"].convert("P", palette=Image.Palette.ADAPTIVE, colors=64)
                     .convert("RGB"))
    want = _resize(cv2.cvtColor(pal, cv2.COLOR_RGB2GRAY))
    got = sources.load_gray_320x240(str(root / "palette.png"))
    assert np.abs(got.astype(int) - want).max() <= 1
    cmyk_ref = np.asarray(Image.open(root / "sub" / "deeper" / "cmyk.jpg").convert("L"))
    got = sources.load_gray_320x240(str(root / "sub" / "deeper" / "cmyk.jpg"))
    assert np.abs(got.astype(float) - _resize(cmyk_ref)).mean() < 3  # not inverted, not skipped
    small = sources.load_gray_320x240(str(root / "small.bmp"))  # enlarged, not skipped
    np.testing.assert_array_equal(small, cv2.resize(src["gray8"][:80, :100], (320, 240),
                                                    interpolation=cv2.INTER_LINEAR))
    for name in ("gray.pgm", "color.tif"):
        np.testing.assert_array_equal(sources.load_gray_320x240(str(root / name)),
                                      _resize(_ref_gray(str(root / name))))
    for name, reason in (("truncated.jpg", "corrupt or truncated"), ("empty.png", "empty file"),
                         ("notanimage.png", "not a decodable image"),
                         ("corrupt.tif", "not a decodable image")):
        with pytest.raises(sources.ImageDecodeError, match=reason):
            sources.load_gray_320x240(str(root / name))


def test_bad_files_are_skipped_with_reasons(messy_folder, tmp_path, monkeypatch):
    root, _ = messy_folder
    (root / "locked").mkdir(exist_ok=True)
    (root / "locked" / "hidden.jpg").write_bytes((root / "good.jpg").read_bytes())
    real_scandir = os.scandir

    def scandir(path="."):  # root can read any directory, so simulate an unreadable one
        if os.path.basename(os.fspath(path)) == "locked":
            raise PermissionError(13, "Permission denied", os.fspath(path))
        return real_scandir(path)

    monkeypatch.setattr(os, "scandir", scandir)
    out = str(tmp_path / "out")
    info = stage1.make_dataset("folder", out, "train", image_dir=str(root), num_workers=1,
                               num_shards=2, log=lambda m: None)
    skipped = {s["item_id"]: s["reason"] for s in info["skipped"]}
    assert set(skipped) == {"truncated.jpg", "empty.png", "notanimage.png", "corrupt.tif",
                            str(root / "locked")}
    assert "empty file" in skipped["empty.png"] and "truncated" in skipped["truncated.jpg"]
    assert "unreadable directory" in skipped[str(root / "locked")]
    used = set(data.load_arrays(out, "train")["image_id"])
    assert used == {"color.tif", "good.jpg", "gray.pgm", "palette.png", "small.bmp",
                    "sub/deeper/cmyk.jpg", "sub/gray16.png", "sub/rgba.png"}
    assert info["num_samples"] == 8 * 3 and info["num_items_skipped"] == 4
    assert info["num_non_image_files_ignored"] == 1
    assert data.read_metadata(out)["splits"]["train"]["skipped"] == info["skipped"]


def test_images_too_small_for_a_patch_are_skipped_by_name(tmp_path):
    """One rule with estimate_images (sources.check_image_size): an image under 20 x 15 px,
    whose 128 x 128 patches would cover fewer than 8 of its pixels on a side (a 1 x 1 image made
    flat pairs), is refused when read, and skipped with its reason by make_dataset and by the
    generated pairs; 20 x 15 px is used."""
    from stnh_tf.data import batches, folder_counts

    root = tmp_path / "small"
    root.mkdir()
    rng = np.random.default_rng(0)
    for name, (w, h) in {"dot.png": (1, 1), "narrow.png": (19, 240), "low.png": (320, 14),
                         "least.png": (20, 15), "photo.png": (320, 240)}.items():
        cv2.imwrite(str(root / name), (rng.random((h, w)) * 255).astype(np.uint8))
    with pytest.raises(image_checks.ImageTooSmallError, match="image is 1 x 1 px: too small"):
        sources.load_gray_320x240(str(root / "dot.png"))
    with pytest.raises(ValueError, match="image is 19 x 15 px: too small"):
        sources.as_gray_320x240(np.zeros((15, 19), np.uint8))
    least = cv2.imread(str(root / "least.png"), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(sources.load_gray_320x240(str(root / "least.png")),
                                  cv2.resize(least, (320, 240), interpolation=cv2.INTER_LINEAR))
    out = str(tmp_path / "out")
    info = stage1.make_dataset("folder", out, "train", image_dir=str(root), num_workers=1,
                               num_shards=1, samples_per_image=1, log=lambda m: None)
    skipped = {s["item_id"]: s["reason"] for s in info["skipped"]}
    assert set(skipped) == {"dot.png", "narrow.png", "low.png"}
    assert {folder_counts.skip_kind(r) for r in skipped.values()} == {"too small"}
    assert set(data.load_arrays(out, "train")["image_id"]) == {"least.png", "photo.png"}
    pair_batches = batches.PairBatches(str(root), 1, samples_per_image=1)
    assert sorted(e[1] for e in pair_batches.entries) == ["least.png", "photo.png"]
    assert sorted(i for i, _ in pair_batches.skipped) == ["dot.png", "low.png", "narrow.png"]


def test_empty_source_and_unwritable_output_fail_before_work(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("no images here")
    out = tmp_path / "out"
    with pytest.raises(sources.SourceError, match="no image files found"):
        stage1.make_dataset("folder", str(out), "train", image_dir=str(empty), log=print)
    assert not (out / "metadata.json").exists()
    with pytest.raises(sources.SourceError, match="does not exist"):
        stage1.make_dataset("folder", str(out), "train", image_dir=str(tmp_path / "nope"))
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    with pytest.raises(OSError, match="not writable"):
        stage1.make_dataset("bundled", str(blocker / "sub"), "train")


# ------------------------------------------------------------------------------------------------
# Atomicity, re-runs, metadata merge
# ------------------------------------------------------------------------------------------------
def _fail_on_third(item):
    if item.index == 2:
        raise KeyboardInterrupt("simulated kill")
    return [{**pairs.make_pair(np.full((240, 320), 100, np.uint8),
                               pairs.draw_params(pairs.image_rng(0, item.index))[0]),
             "h_prev": np.eye(3), "h_mask": 1.0, "image_id": item.item_id, "index": item.index}]


def test_interrupted_run_never_looks_finished_and_rerun_replaces(tmp_path, dataset):
    out = str(tmp_path / "ds")
    items = [writer.WorkItem(i, f"img{i}") for i in range(4)]
    with pytest.raises(KeyboardInterrupt):
        writer.write_sharded(out, "train", items, _fail_on_third, num_shards=4,
                             top_metadata={"stage": 1}, log=lambda m: None)
    assert not [n for n in os.listdir(out) if ".tmp" in n]
    assert data.read_metadata(out)["splits"]["train"]["status"] == "incomplete"
    assert not data.has_split(out, "train")
    with pytest.raises(ValueError, match="did not finish"):
        data.load_split(out, "train", 2)
    ok = functools.partial(pairs.generate_item_samples, seed=0,
                           protocol=pairs.Protocol(samples_per_image=1))
    files = [writer.WorkItem(i, f, p)
             for i, (f, p) in enumerate(bundled_photos.bundled_image_files()[:4])]
    writer.write_sharded(out, "train", files, ok, num_shards=2, top_metadata={"stage": 1},
                         log=lambda m: None)
    writer.write_sharded(out, "test", files[:1], ok, num_shards=1, top_metadata={"stage": 1},
                         log=lambda m: None)
    meta = data.read_metadata(out)
    assert meta["splits"]["train"]["status"] == "complete"
    assert meta["splits"]["train"]["num_samples"] == 4
    assert meta["splits"]["test"]["num_samples"] == 1
    tfrecords = sorted(n for n in os.listdir(out) if n.endswith(".tfrecord"))
    assert tfrecords == ["test-00000-of-00001.tfrecord", "train-00000-of-00002.tfrecord",
                         "train-00001-of-00002.tfrecord"]  # the old 4-shard layout is gone
    with pytest.raises(ValueError, match="stage"):
        writer.write_sharded(out, "val", files, ok, num_shards=1, top_metadata={"stage": 2})


def test_corrupted_or_truncated_shard_error_names_the_file(tmp_path, dataset):
    out = str(tmp_path / "copy")
    shutil.copytree(dataset, out)
    shard = os.path.join(out, "train-00001-of-00002.tfrecord")
    blob = bytearray(open(shard, "rb").read())
    blob[len(blob) // 2] ^= 0xFF  # same size, bad CRC
    open(shard, "wb").write(bytes(blob))
    with pytest.raises(data.ShardError, match="train-00001-of-00002.tfrecord"):
        data.load_arrays(out, "train")
    with pytest.raises(data.ShardError, match="train-00001-of-00002.tfrecord"):
        data.verify_split(out, "train")
    open(shard, "wb").write(bytes(blob[:-1000]))  # truncated
    with pytest.raises(data.ShardError, match="train-00001-of-00002.tfrecord"):
        data.load_split(out, "train", 4)
    with pytest.raises(data.ShardError, match="train-00001-of-00002.tfrecord"):
        data.load_arrays(out, "train", verify="none")
    with pytest.raises(FileNotFoundError, match="metadata.json"):
        data.read_metadata(str(tmp_path))


# ------------------------------------------------------------------------------------------------
# Readers and generators
# ------------------------------------------------------------------------------------------------
def test_load_split_structure_and_seeded_order(dataset, arrays):
    ds = data.load_split(dataset, "train", 4, shuffle=False, repeat=False)
    batches = list(ds)
    assert len(batches) == 2  # 9 samples, drop_remainder
    x, y, w = batches[0]
    assert x["patch_a"].shape == (4, 128, 128, 1) and x["patch_a"].dtype.name == "float32"
    assert y["h_bar"].shape == (4, 8) and y["patch_a_warp"].shape == (4, 128, 128, 1)
    assert w["h_bar"].shape == (4,) and w["patch_a_warp"].shape == (4,)
    # images 0, 1 -> shard 0 (samples 0-5), image 2 -> shard 1 (samples 6-8); interleaved one
    # record at a time
    order = [0, 6, 1, 7]
    np.testing.assert_array_equal(x["patch_b"].numpy(), arrays["patch_b"][order])
    np.testing.assert_array_equal(y["patch_a_warp"].numpy(), arrays["patch_a_t"][order])
    np.testing.assert_array_equal(y["h_bar"].numpy(), arrays["h_bar"][order])
    np.testing.assert_array_equal(w["h_bar"].numpy(), np.ones(4))

    def first(seed, n=3):
        return [b[1]["h_bar"].numpy() for b in data.load_split(dataset, "train", 4, seed=seed)
                .take(n)]

    a, b, c = first(1), first(1), first(2)
    for u, v in zip(a, b):
        np.testing.assert_array_equal(u, v)
    assert any(not np.array_equal(u, v) for u, v in zip(a, c))
    # A resumed stream starts where the uninterrupted one is after that many batches.
    (skipped,) = [b[1]["h_bar"].numpy() for b in data.load_split(dataset, "train", 4, seed=1,
                                                                   skip_batches=2).take(1)]
    np.testing.assert_array_equal(skipped, a[2])


def test_pair_sequence_matches_tfrecords(arrays):
    seq = pair_datasets.PairSequence("bundled", 3, seed=7, shuffle=False, max_images=3)
    assert len(seq) == 3
    x, y, w = seq[1]
    assert set(x) == {"patch_a", "patch_b"} and set(y) == {"h_bar", "patch_a_warp"}
    assert set(w) == {"h_bar", "patch_a_warp"}
    assert x["patch_a"].shape == (3, 128, 128, 1) and x["patch_a"].dtype == np.float32
    np.testing.assert_array_equal(x["patch_a"], arrays["patch_a"][3:6])
    np.testing.assert_array_equal(x["patch_b"], arrays["patch_b"][3:6])
    np.testing.assert_array_equal(y["patch_a_warp"], arrays["patch_a_t"][3:6])
    np.testing.assert_array_equal(y["h_bar"], arrays["h_bar"][3:6])
    np.testing.assert_array_equal(w["h_bar"], np.ones(3, np.float32))
    shuffled = pair_datasets.PairSequence("bundled", 3, seed=7, shuffle=True, max_images=3)
    again = pair_datasets.PairSequence("bundled", 3, seed=7, shuffle=True, max_images=3)
    np.testing.assert_array_equal(shuffled[2][0]["patch_b"], again[2][0]["patch_b"])
    got = np.concatenate([shuffled[i][1]["h_bar"] for i in range(3)])
    assert sorted(map(tuple, got)) == sorted(map(tuple, arrays["h_bar"]))
    with pytest.raises(IndexError):
        seq[3]


def test_pair_generator_imports_no_tensorflow():
    code = (
        "import sys, types\n"
        "k = types.ModuleType('keras'); k.utils = types.SimpleNamespace()\n"
        "class PyDataset:\n"
        "    def __init__(self, workers=1, use_multiprocessing=False, max_queue_size=10): pass\n"
        "k.utils.PyDataset = PyDataset; sys.modules['keras'] = k\n"
        "from stnh_tf.data import pair_datasets, tfrecords\n"
        "x, y, w = pair_datasets.PairSequence('bundled', 2, max_images=1)[0]\n"
        "assert x['patch_a'].shape == (2, 128, 128, 1)\n"
        "from stnh_tf.data import stage1, writer\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('tensorflow', 'jax')))\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == "[]"


def test_hbar_histogram_figure(dataset, tmp_path):
    """Fig. 1's statistics are those of H_bar recomputed here from each sample's pixel H_ba
    (conftest's ``to_bar``, the paper's M written out), entry by entry in the paper's order."""
    from experiments import plot_hbar_histogram as plot

    arrays = data.load_arrays(dataset, "train")
    ref = np.stack([to_bar(h.astype(np.float64)).ravel()[:8] for h in arrays["h_ba"]])
    h_bar = plot.read_h_bar(dataset, "train")
    assert h_bar.shape == (9, 8)
    # H_ba and H_bar are stored in float32: measured max difference 8e-8 (entries up to 1.3)
    np.testing.assert_allclose(h_bar, ref, rtol=0, atol=1e-6)
    out = str(tmp_path / "fig" / "hist.png")
    stats = plot.plot_histogram(h_bar, out, bins=10)
    assert cv2.imread(out).shape == (600, 1400, 3)  # 14 x 6 inches at 100 dpi, 2 x 4 panels
    assert stats["num_samples"] == 9
    names = ["h11", "h12", "h13", "h21", "h22", "h23", "h31", "h32"]
    assert list(stats["entries"]) == names
    for j, name in enumerate(names):
        got, col = stats["entries"][name], ref[:, j]
        for key, want in (("mean", col.mean()), ("std", col.std()), ("min", col.min()),
                          ("max", col.max())):
            assert got[key] == pytest.approx(want, abs=1e-6), (name, key)
    assert stats["entries"]["h11"]["std"] > 0.01 and stats["entries"]["h31"]["std"] > 1e-4
    json.dumps(stats)


def test_coco2014_fails_fast_without_network(tmp_path, monkeypatch):
    monkeypatch.setattr(stage1, "_network_reachable", lambda *a, **k: False)
    with pytest.raises(sources.SourceError, match="--source=folder"):
        stage1.make_dataset("coco2014", str(tmp_path / "out"), "train",
                            tfds_data_dir=str(tmp_path / "tfds"))
    assert not (tmp_path / "out" / "metadata.json").exists()


# ------------------------------------------------------------------------------------------------
# Nothing lost, nothing crashes: arguments, paths read from metadata, concurrent writers
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs, message", [
    ({"num_shards": -3}, "--num_shards must be >= 0; received -3"),
    ({"max_images": -2}, "--max_images must be >= 0; received -2"),
    ({"split": ".."}, "split must be a plain name"),
    ({"split": "../train"}, "split must be a plain name"),
    # its lock was the metadata's (.metadata.lock): the writer waited on itself for ever
    ({"split": "metadata"}, "split 'metadata' is reserved"),
    ({"split": "Metadata"}, "split 'Metadata' is reserved"),  # (one file where case is blind)
    ({"source": "folder", "image_dir": "MISSING"}, "does not exist"),
    ({"source": "folder", "image_dir": "EMPTY"}, "no image files found"),
])
def test_make_dataset_checks_everything_before_creating_the_output_folder(tmp_path, kwargs,
                                                                          message):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("no images")
    folders = {"MISSING": str(tmp_path / "missing"), "EMPTY": str(tmp_path / "empty")}
    kwargs = {"source": "bundled", "split": "train", "max_images": 1, **kwargs}
    if "image_dir" in kwargs:
        kwargs["image_dir"] = folders[kwargs["image_dir"]]
    out = tmp_path / "out"
    with pytest.raises(ValueError, match=re.escape(message)):  # SourceError is a ValueError
        stage1.make_dataset(output_dir=str(out), log=lambda m: None, **kwargs)
    assert not out.exists()


def test_crafted_shard_path_in_metadata_is_refused(tmp_path, dataset):
    """A metadata.json naming shards of another folder ('../' or absolute) must not make the
    readers score that folder's pairs."""
    other, out = tmp_path / "other", tmp_path / "copy"
    shutil.copytree(dataset, other)
    shutil.copytree(dataset, out)
    meta = json.loads((out / "metadata.json").read_text())
    for crafted in ("../other/train-00000-of-00002.tfrecord",
                    str(other / "train-00000-of-00002.tfrecord")):
        meta["splits"]["train"]["shards"][0]["file"] = crafted
        (out / "metadata.json").write_text(json.dumps(meta))
        with pytest.raises(ValueError, match="is not a path inside"):
            data.shard_paths(str(out), "train")
        with pytest.raises(ValueError, match="is not a path inside"):
            data.load_arrays(str(out), "train")


def _constant_sample(item):
    return [{**pairs.make_pair(np.full((240, 320), 100, np.uint8),
                               pairs.draw_params(pairs.image_rng(0, item.index))[0]),
             "h_prev": np.eye(3), "h_mask": 1.0, "image_id": item.item_id, "index": item.index}]


def test_concurrent_writers_of_one_split_do_not_corrupt_each_other(tmp_path):
    """A second make_dataset on a split being written is refused at once; it used to delete the
    first run's temporary shard, which then failed or wrote an unreadable split."""
    import threading

    out = str(tmp_path / "ds")
    inside_second_item, release = threading.Event(), threading.Event()

    def slow(item):
        if item.index == 1:  # the first shard's temporary file is open by now
            inside_second_item.set()
            assert release.wait(120)
        return _constant_sample(item)

    items = [writer.WorkItem(i, f"img{i}") for i in range(4)]
    result, errors = {}, []

    def first_run():
        try:
            result.update(writer.write_sharded(out, "train", items, slow, num_shards=2,
                                               chunk_size=1, top_metadata={"stage": 1},
                                               log=lambda m: None))
        except BaseException as e:  # noqa: BLE001 - reported below
            errors.append(e)

    thread = threading.Thread(target=first_run)
    thread.start()
    try:
        assert inside_second_item.wait(120)
        temporary = [n for n in os.listdir(out) if ".tfrecord.tmp-" in n]
        assert len(temporary) == 1
        with pytest.raises(FileExistsError, match="another process is writing split 'train'"):
            writer.write_sharded(out, "train", items, _constant_sample, num_shards=2,
                                 top_metadata={"stage": 1}, log=lambda m: None)
        assert os.path.exists(os.path.join(out, temporary[0]))  # not deleted by the second run
    finally:
        release.set()
        thread.join(120)
    assert not errors, errors
    assert result["status"] == "complete" and result["num_samples"] == 4
    assert len(data.load_arrays(out, "train", verify="full")["index"]) == 4
    # Another split of the same folder is written meanwhile without waiting for the lock.
    writer.write_sharded(out, "test", items[:1], _constant_sample, num_shards=1,
                         top_metadata={"stage": 1}, log=lambda m: None)


def test_symlinks_leading_out_of_the_image_folder_are_not_followed(tmp_path):
    folder, elsewhere = tmp_path / "images", tmp_path / "elsewhere"
    folder.mkdir()
    elsewhere.mkdir()
    photo = bundled_photos.bundled_image_files()[0][1]
    shutil.copy(photo, folder / "real.png")
    shutil.copy(photo, elsewhere / "secret.png")
    os.symlink(folder / "real.png", folder / "alias.png")  # inside, to a listed file: named
    os.symlink(elsewhere / "secret.png", folder / "outside.png")
    os.symlink(elsewhere, folder / "linked_dir")  # directories behind links are not entered
    listing = sources.scan_image_folder(str(folder))
    assert [os.path.basename(p) for p in listing.files] == ["real.png"]
    why = {os.path.basename(p): reason for p, reason in listing.unreadable}
    assert sorted(why) == ["alias.png", "linked_dir", "outside.png"]
    assert "outside the image folder" in why["outside.png"]
    assert why["alias.png"] == "the same file (a link) as real.png"
    assert why["linked_dir"].startswith("symbolic link to a folder")


@pytest.mark.slow
def test_evaluate_json_out_folder_is_made_before_the_evaluation(dataset, tmp_path):
    """--json_out into a missing folder used to fail after the evaluation, losing its result."""
    out = tmp_path / "missing" / "sub" / "result.json"
    proc = subprocess.run([sys.executable, "-m", "experiments.evaluate", f"--data_dir={dataset}",
                           "--split=train", "--baselines=identity", f"--json_out={out}"],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    record = json.loads(out.read_text())
    assert record["count"] == 9
    assert record["machine"]["numpy"] == np.__version__ and "git_commit" in record["machine"]
    proc = subprocess.run([sys.executable, "-m", "experiments.evaluate", f"--data_dir={dataset}",
                           "--split=train", "--baselines=identity", f"--json_out={tmp_path}"],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert "is a directory" in proc.stderr


def test_evaluate_refuses_bad_numbers_before_reading():
    from stnh_tf.evaluation import mace as evaluation

    with pytest.raises(ValueError, match="batch_size must be >= 1; received 0"):
        evaluation.evaluate([], "no_such_dataset", batch_size=0)
    with pytest.raises(ValueError, match="max_samples must be >= 1"):
        evaluation.evaluate([], "no_such_dataset", max_samples=-1)


# ------------------------------------------------------------------------------------------------
# Issue 62, item 5: --max_images wherever a binary reads a photograph folder; skipped files
# counted by reason (a link leading out of the folder named, not dropped)
# ------------------------------------------------------------------------------------------------
def test_max_images_keeps_the_first_n_of_the_sorted_listing(tmp_path):
    """The first N of the listing's order (path relative to the folder, folder after folder),
    the same whatever order the files were made in; the others counted, not listed."""
    one = photo_folder(tmp_path / "one", ["z.png", "b.jpg", "sub_a.png", "m.png"])
    (one / "sub").mkdir()
    shutil.copy(one / "m.png", one / "sub" / "a.png")
    two = photo_folder(tmp_path / "two", ["c.png", "a.png"])
    every = sorted(os.path.relpath(os.path.join(d, f), one).replace(os.sep, "/")
                   for d, _, fs in os.walk(one) for f in fs)
    listing = sources.scan_image_folders(str(one), max_images=3)
    assert [listing.image_id(p) for p in listing.files] == every[:3]
    assert listing.beyond_max_images == len(every) - 3
    both = sources.scan_image_folders([str(one), str(two)], max_images=len(every) + 1)
    assert [both.image_id(p) for p in both.files] == [f"0:{n}" for n in every] + ["1:a.png"]
    assert both.beyond_max_images == 1
    assert sources.scan_image_folders(str(one), max_images=0).files == \
        sources.scan_image_folder(str(one)).files  # 0: every image
    with pytest.raises(ValueError, match="max_images must be >= 0"):
        sources.scan_image_folders(str(one), max_images=-1)
    from stnh_tf.data import batches  # the generated training pairs take the same first N

    pb = batches.PairBatches(str(one), 1, samples_per_image=1, max_images=2, shuffle=False)
    assert [e[1] for e in pb.entries] == every[:2]


@pytest.fixture
def counted_folder(messy_folder, tmp_path):
    """messy_folder's files (8 photographs, a truncated JPEG, an empty PNG, two undecodable
    files, a text file) and a symbolic link to a photograph outside the folder."""
    root = tmp_path / "messy"
    shutil.copytree(messy_folder[0], root, ignore=shutil.ignore_patterns("locked"))
    elsewhere = photo_folder(tmp_path / "elsewhere", ["photo.png"])
    os.symlink(elsewhere / "photo.png", root / "link.png")
    return root


WANT_SKIPPED = {"corrupt or truncated": 1, "empty file": 1, "not an image": 2,
                "link outside the folder": 1}


def test_skipped_files_are_counted_by_reason(counted_folder, tmp_path):
    from stnh_tf.data import folder_counts

    images, counts = folder_counts.read_gray_folder(str(counted_folder))
    assert len(images) == counts.used == 8
    assert counts.skipped == WANT_SKIPPED and counts.ignored == 1
    line = counts.line()
    assert line.startswith("photographs: 8 used; skipped 5 (not an image: 2, corrupt or "
                           "truncated: 1, empty file: 1, link outside the folder: 1); "
                           "non-image files ignored: 1; symbolic links leading out")
    assert "not followed" in line and "cp -L" in line
    # the first 3 of the sorted listing: color.tif, corrupt.tif, empty.png
    _, first3 = folder_counts.read_gray_folder(str(counted_folder), max_images=3)
    assert (first3.used, first3.beyond_max_images) == (1, 9)
    assert first3.skipped == {"not an image": 1, "empty file": 1, "link outside the folder": 1}
    assert "left out by --max_images=3: 9" in first3.line()
    # make_dataset's split records the same reasons: the same counts
    info = stage1.make_dataset("folder", str(tmp_path / "out"), "train",
                               image_dir=str(counted_folder), num_workers=1, num_shards=1,
                               log=lambda m: None)
    assert folder_counts.split_counts(info) == counts


def test_a_folder_of_links_outside_it_says_why_and_writes_nothing(tmp_path):
    """make_camera_pairs on a folder of symbolic links said "no readable photograph" and dropped
    the reason; it now counts them and says why links out of a folder are not followed."""
    from stnh_tf.data import camera_pair_files

    real = photo_folder(tmp_path / "real", ["a.png", "b.png"])
    links = tmp_path / "links"
    links.mkdir()
    for name in ("a.png", "b.png"):
        os.symlink(real / name, links / name)
    out = tmp_path / "pairs"
    with pytest.raises(ValueError) as e:
        camera_pair_files.write_pairs(str(links), str(out), pairs_per_image=1)
    message = str(e.value)
    assert "skipped 2 (link outside the folder: 2)" in message and "not followed" in message
    assert f"first: a.png: symbolic link to a file outside the image folder ({real / 'a.png'})" \
        in message
    assert not out.exists()
    manifest = camera_pair_files.write_pairs(str(real), str(out), pairs_per_image=1,
                                             max_images=1)
    assert manifest["images"] == 1 and manifest["photographs"]["beyond_max_images"] == 1
    assert {p.image_id for p in camera_pair_files.load_pairs(str(out))[1]} == {"a.png"}


def test_make_camera_pairs_prints_the_counts_line(tmp_path):
    real = photo_folder(tmp_path / "real", ["a.png", "b.png"])
    (real / "0broken.jpg").write_bytes(b"not a jpeg")  # first of the sorted listing
    proc = subprocess.run([sys.executable, "-m", "experiments.make_camera_pairs",
                           f"--image_dir={real}", f"--output_dir={tmp_path / 'pairs'}",
                           "--pairs_per_image=1", "--max_images=2"],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines()[-1] == (
        "photographs: 1 used; skipped 1 (not an image: 1); left out by --max_images=2: 1")
    assert json.loads(proc.stdout)["images"] == 1


@pytest.mark.parametrize("name", ["stnh_tf.data.sources", "stnh_tf.data.folder_counts"])
def test_listing_and_counting_doctests(name):
    import doctest
    import importlib

    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0 and result.failed == 0
