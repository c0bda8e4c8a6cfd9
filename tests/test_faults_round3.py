"""Issue 80's minor faults, kept as tests: a 16-bit PNG of low range read as black (item 5), a
small PNG that decodes to a huge image (6), an export that failed its own check on a degenerate
stage prediction (7), an export killed during its check taken for a good one (8), ``evaluate``
silent about a model of another stage than its data (10) and a negative ``--seed`` refused
without naming the flag (11). References are made here: pixels with NumPy, files byte for byte,
homographies from the matrices the test builds.
"""

from __future__ import annotations

import ast
import glob
import json
import logging
import os
import struct
import subprocess
import sys
import zlib

import cv2
import numpy as np
import pytest
import skimage.data

from conftest import binary_flags, constant_stage
from stnh_tf.data import folder_counts, image_checks, sources, stage1, stage_k
from stnh_tf.inference import export, image_files
from stnh_tf.inference.estimator import HomographyEstimator
from stnh_tf.paths import atomic_write_json
from stnh_tf.training import run_dir
from stnh_tf.training.config import TrainConfig

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
QUIET = lambda *a, **k: None  # noqa: E731


def _binary(module, *args):
    env = dict(os.environ, TF_CPP_MIN_LOG_LEVEL="2", PYTHONPATH=ROOT)
    return subprocess.run([sys.executable, "-m", module, *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=300, env=env)


# ------------------------------------------------------------------------------------------------
# Item 5: a 16-bit image is scaled by the bit depth its values use
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bits", [8, 10, 12, 16])
def test_a_16_bit_png_is_scaled_by_the_bit_depth_its_values_use(bits, tmp_path):
    """A 16-bit PNG holding 0..255 (a low-range export) was scaled by 255/65535, read as black
    and reported as "the central patch is flat". A 16-bit image is now scaled by 255 / (2^b - 1),
    b the fewest bits (at least 8) that hold its largest value: 0..255 reads as the 8-bit image,
    12-bit data by 255/4095, full-range data by 255/65535 as before. Both the gray image
    estimated on and the colours of predict's overlay."""
    camera = skimage.data.camera()
    full = 2 ** bits - 1
    stored = np.rint(camera.astype(np.float64) * full / 255).astype(np.uint16)
    stored[0, 0] = full  # the largest value the depth holds
    path = str(tmp_path / f"camera{bits}.png")
    assert cv2.imwrite(path, stored)
    want = np.rint(stored.astype(np.float64) * 255 / full).astype(np.uint8)
    assert np.abs(want.astype(int) - camera)[1:].max() <= 1 and want.std() > 40  # not flat
    np.testing.assert_array_equal(sources.read_gray(path), want)
    image = image_files.read_image(path, "image_a")
    np.testing.assert_array_equal(image.gray, want)
    np.testing.assert_array_equal(image.colour, np.repeat(want[..., None], 3, axis=2))


# ------------------------------------------------------------------------------------------------
# Item 6: decoded pixels are capped, from the file's header, before decoding
# ------------------------------------------------------------------------------------------------
BOMB_SIDE = 12_000


def _png_chunk(kind, data):
    return (struct.pack(">I", len(data)) + kind + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))


@pytest.fixture(scope="module")
def bomb_png(tmp_path_factory):
    """A valid 8-bit gray PNG of 12,000 x 12,000 black pixels (144 megapixels) in ~140 KB, made
    here byte by byte (PNG signature, IHDR, one zlib-compressed IDAT of filter-0 rows, IEND)."""
    compressor, rows = zlib.compressobj(9), bytes(100 * (BOMB_SIDE + 1))
    idat = b"".join(compressor.compress(rows) for _ in range(BOMB_SIDE // 100))
    idat += compressor.flush()
    data = (b"\x89PNG\r\n\x1a\n"
            + _png_chunk(b"IHDR", struct.pack(">IIBBBBB", BOMB_SIDE, BOMB_SIDE, 8, 0, 0, 0, 0))
            + _png_chunk(b"IDAT", idat) + _png_chunk(b"IEND", b""))
    path = tmp_path_factory.mktemp("bomb") / "bomb.png"
    path.write_bytes(data)
    return str(path)


def test_a_small_png_that_decodes_huge_is_refused_before_decoding(bomb_png, monkeypatch):
    """A 250 KB PNG of 16,000 x 16,000 pixels made predict use 4.3 GB. The header's size is read
    first and a file over the cap (``sources.MAX_IMAGE_PIXELS``) refused in one line naming its
    size and predict's flag, without decoding it (OpenCV's decoder is never called)."""
    assert os.path.getsize(bomb_png) < 300_000
    assert BOMB_SIDE ** 2 > sources.MAX_IMAGE_PIXELS
    decoded = []
    monkeypatch.setattr(cv2, "imdecode", lambda *a, **k: decoded.append(a) or None)
    with pytest.raises(image_files.AlignmentError) as e:
        image_files.read_image(bomb_png, "image_a")
    message = str(e.value)
    assert "\n" not in message and "image_a" in message and bomb_png in message
    assert f"{BOMB_SIDE:,} x {BOMB_SIDE:,}" in message and "--max_image_pixels" in message
    assert decoded == []


def test_a_photograph_folder_skips_a_decompression_bomb_and_counts_it(bomb_png, tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "bomb.png").write_bytes(open(bomb_png, "rb").read())
    assert cv2.imwrite(str(folder / "camera.png"), skimage.data.camera())
    images, counts = folder_counts.read_gray_folder(str(folder))
    assert len(images) == 1 and counts.skipped == {"too large": 1}
    assert "too large: 1" in counts.line()


def test_the_cap_is_raised_by_predicts_flag(tmp_path):
    """``--max_image_pixels`` (default ``sources.MAX_IMAGE_PIXELS``) reaches the reader: a
    200 x 150 image is refused under a cap of 29,999 pixels and read at 30,000."""
    path = str(tmp_path / "small.png")
    cv2.imwrite(path, cv2.resize(skimage.data.camera(), (200, 150)))
    with pytest.raises(image_files.AlignmentError, match="200 x 150"):
        image_files.read_image(path, "image_b", max_pixels=29_999)
    assert image_files.read_image(path, "image_b", max_pixels=30_000).size == (200, 150)
    found = binary_flags(["experiments.predict"])["experiments.predict"]
    assert found["max_image_pixels"] == sources.MAX_IMAGE_PIXELS


# ------------------------------------------------------------------------------------------------
# Items 7 and 8: the export computes what estimate does, and is marked verified only after
# ------------------------------------------------------------------------------------------------
BEHIND = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-0.01, 0.0, 1.0]])
"""A stage prediction that maps patch corners behind the camera (w < 0 at x = 128): singular
by the degenerate-prediction rule (:func:`stnh_tf.hierarchy.rejection_reason`)."""
RANK_TWO = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
"""A stage prediction of determinant 0."""
SHIFT = np.array([[1.0, 0.0, 5.0], [0.0, 1.0, -3.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("stages, want", [
    ([BEHIND], np.eye(3)),
    pytest.param([SHIFT, RANK_TWO], SHIFT, marks=pytest.mark.slow)],  # (5 s: make test's time)
    ids=["one singular stage", "hierarchy, second stage singular"])
def test_the_export_skips_a_degenerate_stage_prediction_as_estimate_does(stages, want,
                                                                          tmp_path):
    """An under-trained model's export failed its own check: the SavedModel kept a singular
    stage prediction that ``estimate`` replaces by the estimate before it. The exported graph
    now applies the same rule: on every pair it returns the estimate before the degenerate
    stage (the identity; the first stage's shift), and the check passes."""
    est = HomographyEstimator([constant_stage(h, f"s{k}") for k, h in enumerate(stages)])
    report = export.export_and_verify(est, tmp_path / "export", check_pairs=3)
    assert report["ok"], report
    patch_a, patch_b = export.verification_pairs(3)
    saved = export.run_saved_model(tmp_path / "export", patch_a, patch_b)
    np.testing.assert_allclose(saved, np.broadcast_to(want, (3, 3, 3)), atol=1e-4)


def _export_records(caplog):
    """The log records of :mod:`stnh_tf.inference.export` (TensorFlow logs its own)."""
    return [r for r in caplog.records if r.name == export.__name__]


class Killed(BaseException):
    """What ``kill -9`` does to the check, as far as the files are concerned: it stops there."""


def test_an_export_killed_during_its_check_is_not_taken_for_a_verified_one(tmp_path,
                                                                           monkeypatch, caplog):
    """A kill during the check left a complete but unchecked SavedModel, and the re-run only
    asked for --overwrite. The check runs in the staging folder now (a kill there moves nothing
    in), and the folder is marked verified (``export.VERIFIED_FILE``, written atomically after
    the check passed, naming the SavedModel's digest) only after the swap: a kill between the
    two leaves the export unmarked, the re-run says it was never verified, loading it warns,
    and a finished export is marked."""
    est = HomographyEstimator([constant_stage(SHIFT)])
    out = tmp_path / "export"

    def killed(*args, **kwargs):
        raise Killed()

    monkeypatch.setattr(export, "verify_export", killed)
    with pytest.raises(Killed):
        export.export_and_verify(est, out, check_pairs=2)
    monkeypatch.undo()
    assert not (out / "saved_model.pb").exists()  # killed in its check: nothing moved in
    monkeypatch.setattr(export.paths, "atomic_write_json", killed)  # killed before the marker
    with pytest.raises(Killed):
        export.export_and_verify(est, out, check_pairs=2)
    monkeypatch.undo()
    assert (out / "saved_model.pb").is_file() and not (out / export.VERIFIED_FILE).exists()
    with pytest.raises(FileExistsError) as e:
        export.export_and_verify(est, out, check_pairs=2)
    assert "never verified" in str(e.value) and "--overwrite" in str(e.value)
    with caplog.at_level(logging.WARNING, logger=export.__name__):
        export.load_serving_signature(out)
    assert any("never verified" in r.getMessage() for r in _export_records(caplog)), caplog.text
    caplog.clear()

    report = export.export_and_verify(est, out, overwrite=True, check_pairs=2)
    assert report["ok"]
    marker = json.loads((out / export.VERIFIED_FILE).read_text())
    assert marker["report"]["ok"] and marker["saved_model_sha256"] == export.saved_model_digest(out)
    with caplog.at_level(logging.WARNING, logger=export.__name__):
        export.load_serving_signature(out)
    assert not _export_records(caplog), caplog.text
    with pytest.raises(FileExistsError) as e:  # verified: only --overwrite is asked for
        export.export_and_verify(est, out, check_pairs=2)
    assert "never verified" not in str(e.value)


def test_a_failed_check_keeps_the_earlier_verified_export(tmp_path):
    """``--overwrite`` with a check that fails (``--tolerance=0``, a reviewer's run) swapped the
    new SavedModel in before checking it: the earlier, verified export was gone. The check runs
    before the swap now: the earlier export stays as it was, marked verified; into an empty
    output the failing export still goes, unmarked, for inspection."""
    first = HomographyEstimator([constant_stage(SHIFT)])
    second = HomographyEstimator([constant_stage(SHIFT @ SHIFT)])
    out = tmp_path / "export"
    assert export.export_and_verify(first, out, check_pairs=2)["ok"]
    digest = export.saved_model_digest(out)
    failing = {"max_abs_diff": 1.0, "max_abs_diff_estimate": 1.0, "ok": False}
    real = export.verify_export
    export.verify_export = lambda *a, **k: {**real(*a, **k), **failing}
    try:
        report = export.export_and_verify(second, out, overwrite=True, check_pairs=2)
        alone = export.export_and_verify(second, tmp_path / "new", check_pairs=2)
    finally:
        export.verify_export = real
    assert not report["ok"] and report["kept_earlier_export"] and report["documents"] == []
    assert export.saved_model_digest(out) == digest and export.verified_problem(out) is None
    patch_a, patch_b = export.verification_pairs(2)
    np.testing.assert_allclose(export.run_saved_model(out, patch_a, patch_b),
                               np.broadcast_to(SHIFT, (2, 3, 3)), atol=1e-4)
    assert not [n for n in os.listdir(out) if n.startswith(".stnh_tf_export_staging")]
    assert not alone["ok"] and not alone["kept_earlier_export"]
    assert (tmp_path / "new" / "saved_model.pb").is_file()
    assert "never verified" in export.verified_problem(tmp_path / "new")


def test_the_export_refuses_another_keras_backend_first(tmp_path, monkeypatch):
    """Under ``KERAS_BACKEND=jax`` the export failed deep in its trace and said "cannot write
    the SavedModel": refused first now, in one line naming the backend, nothing created."""
    import keras

    monkeypatch.setattr(keras.backend, "backend", lambda: "jax")
    est = HomographyEstimator([constant_stage(SHIFT)])
    for write in (export.export_saved_model, export.export_and_verify):
        with pytest.raises(ValueError, match="KERAS_BACKEND=tensorflow"):
            write(est, tmp_path / "export")
    assert not (tmp_path / "export").exists()


# ------------------------------------------------------------------------------------------------
# Item 10: evaluate says when the model's stage and the data's differ
# ------------------------------------------------------------------------------------------------
def _run_folder(folder, stage, h_pix):
    """A training run's folder as the loop leaves it: ``model.keras`` (a constant stage) and
    ``config.json`` (``TrainConfig`` with ``stage``)."""
    os.makedirs(folder)
    constant_stage(h_pix).save(os.path.join(folder, run_dir.FINAL_MODEL))
    config = TrainConfig(model_dir=str(folder), data_dir="data", stage=stage).to_json()
    atomic_write_json(os.path.join(folder, run_dir.CONFIG_FILE),
                      {**run_dir.CONFIG_MARKER, **config})
    return str(folder)


def test_evaluate_notes_a_model_of_another_stage_than_its_data(tmp_path):
    """``evaluate`` of a stage-1 model on stage-2 data gave no note that the stages differ. The
    model's stage (its run's ``config.json``) and the data's (``metadata.json``) are compared:
    a note in the JSON and under the table names both; none where they agree; a hierarchy's
    k-th model is compared with stage k."""
    from stnh_tf.evaluation import mace, summaries

    data1, data2 = str(tmp_path / "data1"), str(tmp_path / "data2")
    stage1.make_dataset("bundled", data1, "test", seed=1, max_images=1, samples_per_image=2,
                        num_workers=1, log=QUIET)
    stage_k.make_stage_dataset(2, data1, data2, "test", log=QUIET,
                               predict=lambda a, b: np.broadcast_to(np.eye(3), (len(a), 3, 3)))
    model = _run_folder(tmp_path / "run1", 1, SHIFT)
    result = mace.evaluate([model], data2, "test")
    assert len(result["notes"]) == 1
    note = result["notes"][0]
    for fragment in ("stage 1", "stage-2", model, data2, "config.json", "metadata.json"):
        assert fragment in note, (fragment, note)
    assert note in summaries.evaluation_table(result)
    assert mace.evaluate([model], data1, "test").get("notes", []) == []
    # a hierarchy of two stage-1 runs: its second stage is not a stage-2 model
    notes = mace.stage_notes([model, model], 1, data1)
    assert len(notes) == 1 and "stage 2 of the hierarchy" in notes[0] and "stage 1" in notes[0]


# ------------------------------------------------------------------------------------------------
# Item 11: a negative --seed is refused naming the flag
# ------------------------------------------------------------------------------------------------
BINARY_FOLDERS = ("experiments", "data_prep", "semi_supervised")


def _seed_definitions():
    """``{binary file: how it defines --seed}`` for every binary that has the flag: the name of
    the call (``DEFINE_integer``, ``define_seed``, ...) and whether it passes ``lower_bound``
    (``experiments/flags_common.py``, where ``define_seed`` is defined, left out)."""
    found = {}
    for folder in BINARY_FOLDERS:
        for path in sorted(glob.glob(os.path.join(ROOT, folder, "*.py"))):
            if path.endswith(os.path.join("experiments", "flags_common.py")):
                continue
            for node in ast.walk(ast.parse(open(path, encoding="utf-8").read())):
                if not isinstance(node, ast.Call):
                    continue
                name = getattr(node.func, "attr", getattr(node.func, "id", ""))
                first = node.args[0] if node.args else None
                if name.startswith("DEFINE") and isinstance(first, ast.Constant) \
                        and first.value == "seed":
                    found[os.path.relpath(path, ROOT)] = (
                        name, any(k.arg == "lower_bound" for k in node.keywords))
                elif name == "define_seed":
                    found[os.path.relpath(path, ROOT)] = (name, True)
    return found


def test_every_binarys_seed_flag_refuses_a_negative_value_at_parsing():
    """Each binary's ``--seed`` is defined by ``flags_common.define_seed`` (an integer >= 0,
    refused by absl naming the flag), not a bare ``DEFINE_integer`` that lets -1 reach NumPy."""
    found = _seed_definitions()
    assert len(found) >= 10 and "experiments/make_camera_pairs.py" in found
    bare = {path: how for path, how in found.items() if how != ("define_seed", True)}
    assert bare == {}


@pytest.mark.parametrize("module, args", [
    ("experiments.make_camera_pairs", ["--image_dir={photos}"]),
    ("experiments.demo", []),
])
def test_a_negative_seed_is_refused_naming_the_flag(module, args, tmp_path):
    """``make_camera_pairs --seed=-1`` said "expected non-negative integer" (NumPy's words) and
    ``demo --seed=-1`` ended in a traceback; both now refuse it at parsing, naming ``--seed``,
    before anything is written."""
    out = tmp_path / "out"
    args = [a.format(photos=tmp_path) for a in args]
    proc = _binary(module, f"--output_dir={out}", "--seed=-1", *args)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert "--seed=-1" in proc.stderr and "non-negative" in proc.stderr, proc.stderr[-2000:]
    assert not out.exists()


_EXR_OF_40_BY_30 = """
import sys, cv2, numpy as np
image = np.random.default_rng(0).random((30, 40)).astype(np.float32)
sys.stdout.buffer.write(cv2.imencode(".exr", image)[1].tobytes())
"""


def test_an_exr_is_held_to_the_pixel_cap(monkeypatch, tmp_path):
    """OpenCV decodes OpenEXR where ``OPENCV_IO_ENABLE_OPENEXR`` is set, and Pillow reads no EXR
    header, so the cap did not hold for it (a review's find, left open last round). Its
    ``dataWindow`` is read now: OpenCV's own EXR of 40 x 30 px (written in a subprocess with the
    variable set) reports that size, and the same file declaring 12,000 x 12,000 px is refused
    before decoding."""
    env = dict(os.environ, OPENCV_IO_ENABLE_OPENEXR="1")
    data = subprocess.run([sys.executable, "-c", _EXR_OF_40_BY_30], env=env, check=True,
                          capture_output=True, timeout=120).stdout
    assert image_checks.header_size(data) == (40, 30)
    at = data.index(b"dataWindow\0box2i\0") + len(b"dataWindow\0box2i\0") + 4
    assert struct.unpack_from("<4i", data, at) == (0, 0, 39, 29)
    big = data[:at] + struct.pack("<4i", 0, 0, 11999, 11999) + data[at + 16:]
    decoded = []
    monkeypatch.setattr(cv2, "imdecode", lambda *a, **k: decoded.append(a) or None)
    path = tmp_path / "big.exr"
    path.write_bytes(big)
    with pytest.raises(image_files.AlignmentError, match="12,000 x 12,000"):
        image_files.read_image(str(path), "image_a")
    assert decoded == []
    assert image_checks.header_size(big[:at + 8]) is None  # cut short: the decoder's to judge


@pytest.mark.parametrize("header", [
    b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 12000 +X 12000\n",  # Radiance HDR
    b"Pf\n12000 12000\n-1.0\n"])  # PFM
def test_an_opencv_only_format_is_held_to_the_pixel_cap(header, monkeypatch, tmp_path):
    """Pillow reads no header of Radiance HDR or PFM, so the cap was not checked and OpenCV
    decoded them whatever their size (a 9 MB HDR declaring 144 megapixels: 1.7 GB; a review's
    find). Their headers are read now: refused before decoding. OpenCV's own small HDR and PFM
    files report their true size and decode as before."""
    decoded = []
    monkeypatch.setattr(cv2, "imdecode", lambda *a, **k: decoded.append(a) or None)
    path = tmp_path / "big.img"
    path.write_bytes(header + bytes(1000))
    with pytest.raises(image_files.AlignmentError, match="12,000 x 12,000"):
        image_files.read_image(str(path), "image_a")
    assert decoded == []
    monkeypatch.undo()
    image = np.random.default_rng(0).random((30, 40, 3)).astype(np.float32)
    for ext in (".hdr", ".pfm"):
        data = cv2.imencode(ext, image)[1].tobytes()
        assert image_checks.header_size(data) == (40, 30)
        assert sources.decode_gray(data).shape == (30, 40)
