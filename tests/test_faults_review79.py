"""A hostile read of the inference surface a researcher uses (issue 79's review, 2026-12-07),
kept as tests: an ``--overwrite`` export whose output lies on another file system (a link, a
mounted volume) deleted the old export and then failed to move the new one in; an export
removed a user's backup beside the output that was named like the old staging folders; two
``predict`` runs writing to one folder could give one pair's results the other's name;
thresholds that make no sense were accepted; ``predict`` wrote mirrored positions for image_b's
corners beyond image_a's horizon. Each compares the user's files byte for byte or the values
with an independent computation.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os

import numpy as np
import pytest

from conftest import constant_stage
from stnh_tf.inference import HomographyEstimator, export, export_folder
from stnh_tf.inference.options import EstimateOptions


def _files(folder):
    """Every file below ``folder``: relative path -> bytes."""
    folder = str(folder)
    return {os.path.relpath(os.path.join(d, f), folder): open(os.path.join(d, f), "rb").read()
            for d, _, names in os.walk(folder) for f in names}


def _fake_archive(tag, seen=None):
    """A stand-in for the TensorFlow write (the file rules only): ``saved_model.pb`` holding
    ``tag`` and a ``variables`` folder; the folder written to is appended to ``seen``."""
    def write(estimator, path):
        if seen is not None:
            seen.append(path)
        with open(os.path.join(path, "saved_model.pb"), "wb") as f:
            f.write(tag)
        os.makedirs(os.path.join(path, "variables"))
        with open(os.path.join(path, "variables", "variables.index"), "wb") as f:
            f.write(tag * 3)
    return write


@pytest.fixture(scope="module")
def estimator():
    return HomographyEstimator([constant_stage(np.eye(3), "review79_id")])


def test_the_staging_folder_lies_inside_the_output_also_through_a_link(estimator, tmp_path,
                                                                          monkeypatch):
    """The staging folder was made beside the output's name: where the output is a link to (or
    a mount of) another file system, the new export could not be moved in (EXDEV). It is made
    inside the output now, on the output's own file system; the link stays a link and its
    target gets the new export."""
    target, link = tmp_path / "volume" / "export", tmp_path / "export"
    target.mkdir(parents=True)
    link.symlink_to(target)
    seen = []
    monkeypatch.setattr(export, "_write_archive", _fake_archive(b"first", seen))
    export.export_saved_model(estimator, link)
    monkeypatch.setattr(export, "_write_archive", _fake_archive(b"second", seen))
    export.export_saved_model(estimator, link, overwrite=True)
    assert [os.path.dirname(os.path.realpath(p)) for p in seen] == [str(target.resolve())] * 2
    assert link.is_symlink() and (target / "saved_model.pb").read_bytes() == b"second"
    assert sorted(os.listdir(tmp_path)) == ["export", "volume"]
    assert sorted(os.listdir(target)) == sorted(
        ["saved_model.pb", "variables", "README.md", "signature.json", export_folder.LOCK_FILE])


def test_a_move_that_fails_puts_the_old_export_back(estimator, tmp_path, monkeypatch):
    """The old export's entries were deleted before the new ones were moved in: a move that
    failed (EXDEV across file systems, a full disk's metadata) left neither. They are moved
    aside first and put back: the folder is byte for byte as before, the error names the
    output, and no staging folder stays."""
    out = tmp_path / "out"
    monkeypatch.setattr(export, "_write_archive", _fake_archive(b"old"))
    export.export_saved_model(estimator, out)
    (out / "client.py").write_text("a user's file")
    before = _files(out)
    real_replace = os.replace

    def cross_device(src, dst):
        if os.path.basename(os.path.dirname(src)).startswith(export_folder.STAGING_PREFIX) \
                and os.path.basename(src) == "variables":
            raise OSError(errno.EXDEV, "Invalid cross-device link", src)
        return real_replace(src, dst)

    monkeypatch.setattr(export, "_write_archive", _fake_archive(b"new"))
    monkeypatch.setattr(export_folder.os, "replace", cross_device)
    with pytest.raises(OSError, match=f"cannot move the new SavedModel into {out} .*"
                                      "cross-device.*the old export there is kept"):
        export.export_saved_model(estimator, out, overwrite=True)
    monkeypatch.setattr(export_folder.os, "replace", real_replace)
    assert _files(out) == before
    assert not [n for n in os.listdir(out) if n.startswith(export_folder.STAGING_PREFIX)]


def test_a_fresh_export_killed_midway_does_not_block_the_next(estimator, tmp_path, monkeypatch):
    """What a killed first export leaves in a new output (its lock and staging folder) counts
    as empty: the next export, without ``overwrite``, writes and removes that folder."""
    out = tmp_path / "out"
    out.mkdir()
    stale = out / (export_folder.STAGING_PREFIX + "abcd1234")
    stale.mkdir()
    (stale / "saved_model.pb").write_bytes(b"partial")
    (stale / export_folder.STAGING_MARKER).write_text('{"output": "%s"}' % out)
    monkeypatch.setattr(export, "_write_archive", _fake_archive(b"new"))
    export.export_saved_model(estimator, out)
    assert (out / "saved_model.pb").read_bytes() == b"new" and not stale.exists()


def test_two_predict_runs_into_one_folder_never_share_a_name(estimator, tmp_path, monkeypatch):
    """Two runs on different pairs with the same base names (dir1/a, b and dir2/a, b) into one
    ``--output_dir``: each chose its name before writing, so both took ``a__b`` and one pair's
    results were lost (the PNG and the JSON could even come from different pairs). The name is
    chosen and the files written under the folder's lock file: here the first run waits, its name
    chosen, for the second to choose one (up to 1 s); with the lock the second cannot, and the
    two pairs get ``a__b`` and ``a__b-2``, each JSON naming its own images."""
    import threading

    import cv2

    from stnh_tf.inference import image_files
    from stnh_tf.inference.estimator import HomographyEstimator as Loader

    rng = np.random.default_rng(0)
    for d in ("dir1", "dir2"):
        (tmp_path / d).mkdir()
        image = cv2.GaussianBlur(rng.integers(0, 256, (240, 320), np.uint8), (0, 0), 2)
        for name in ("a", "b"):
            cv2.imwrite(str(tmp_path / d / f"{name}.png"), image)
    monkeypatch.setattr(Loader, "load", classmethod(lambda cls, model=None: estimator))
    chosen = {d: threading.Event() for d in ("dir1", "dir2")}
    real_stem = image_files.output_stem

    def stem(output_dir, inputs):
        name = real_stem(output_dir, inputs)
        d = os.path.basename(os.path.dirname(inputs[0]))
        chosen[d].set()
        if d == "dir1":
            chosen["dir2"].wait(1.0)  # old code: the second run chooses meanwhile
        return name

    monkeypatch.setattr(image_files, "output_stem", stem)
    results = {}

    def run(d):
        results[d] = image_files.align_image_files(
            str(tmp_path / d / "a.png"), str(tmp_path / d / "b.png"), None,
            str(tmp_path / "out"), warn=lambda _: None, note=lambda _: None)

    (tmp_path / "out").mkdir()
    first = threading.Thread(target=run, args=("dir1",))
    first.start()
    assert chosen["dir1"].wait(60)
    second = threading.Thread(target=run, args=("dir2",))
    second.start()
    first.join(60), second.join(60)
    names = {d: os.path.basename(r["overlay_png"]) for d, r in results.items()}
    assert names == {"dir1": "a__b_overlay.png", "dir2": "a__b-2_overlay.png"}
    for d, r in results.items():
        stem_ = names[d][:-len("_overlay.png")]
        written = json.loads((tmp_path / "out" / f"{stem_}_homography.json").read_text())
        assert written["input_paths"] == [os.path.realpath(tmp_path / d / n)
                                          for n in ("a.png", "b.png")]


@pytest.mark.parametrize("optimized", [True, False])
def test_the_border_beyond_the_horizon_is_clipped_not_mirrored(estimator, optimized):
    """A homography that maps part of image_b beyond image_a's horizon (homogeneous coordinate
    below 0; issue 79's strongly projective pairs): ``predict`` wrote those corners at the
    mirrored places plain division gives (-1156, 0), drew the border through them and tinted
    the mirrored image into the overlay. Now the corners are null in the JSON, and the border
    drawn is the part in front: filled, it covers the pixels of image_a that image_b's pixels
    land on in front of camera a (NumPy's inverse mapping, the reference; a wedge of 30,780
    pixels), apart from the wedge's edges (measured: 117 pixels differ, all within 1 px of an
    edge, on both OpenCV paths; the mirrored border filled: 40,087)."""
    import cv2

    from stnh_tf.inference import image_files, overlays

    tilted = np.array([[0.5, 0, 100], [0, 0.5, 60], [-0.004, 0, 1.0]])  # horizon at x_b = 250
    previous = cv2.useOptimized()
    cv2.setUseOptimized(optimized)
    try:
        polygon = overlays.border_polygon(tilted, (320, 240))
        rng = np.random.default_rng(0)
        a = rng.integers(0, 256, (240, 320, 3), np.uint8)
        _, quad = overlays.overlay(a, a.copy(), tilted)
        filled = cv2.fillPoly(np.zeros((240, 320), np.uint8),
                              [np.round(polygon).astype(np.int32).reshape(-1, 1, 2)], 1) > 0
    finally:
        cv2.setUseOptimized(previous)
    assert np.isfinite(polygon).all() and np.abs(polygon).max() <= overlays.FAR * 1.01
    ys, xs = np.mgrid[:240, :320]
    b_from_a = np.linalg.inv(tilted)
    hom = np.stack([xs, ys, np.ones_like(xs)], -1).reshape(-1, 3).astype(float) @ b_from_a.T
    xb, yb = hom[:, 0] / hom[:, 2], hom[:, 1] / hom[:, 2]
    covered = ((hom[:, 2] > 0) & (xb >= 0) & (xb <= 319) & (yb >= 0) & (yb <= 239)).reshape(
        240, 320)
    edge = cv2.dilate(cv2.Canny(covered.astype(np.uint8) * 255, 1, 1), np.ones((3, 3))) > 0
    assert 0.3 * covered.size < covered.sum() < 0.5 * covered.size
    assert not (filled != covered)[~edge].any()
    assert np.isnan(quad[1:3]).all() and np.allclose(quad[[0, 3]], [[100, 60], [100, 179.5]])
    made = estimator.estimate_images_with_info(a[..., 0], a[..., 0],
                                               EstimateOptions.network_only())
    estimate = dataclasses.replace(made, homography=tilted[None])
    doc = image_files._estimate_json(estimate, (240, 320), quad)
    assert doc["image_b_border_in_a"] == [[100.0, 60.0], None, None, [100.0, 179.5]]
    w = 1 - 0.004 * 159.5
    assert doc["image_b_center_in_a"] == pytest.approx([179.75 / w, 119.75 / w])
    wide = image_files._estimate_json(estimate, (240, 640), quad)  # its centre at x = 319.5
    assert wide["image_b_center_in_a"] is None


@pytest.mark.parametrize("changes, message", [
    ({"corner_std_tile": 8.5}, "corner_std_tile must be a whole number"),
    ({"refine_iterations": 2.5}, "refine_iterations must be a whole number"),
    ({"min_overlap": 2.0}, r"min_overlap is a fraction of patch_b's pixels, in \[0, 1\]"),
])
def test_thresholds_that_make_no_sense_are_refused_naming_the_field(changes, message):
    """Accepted before: a fractional size or count failed later with a TypeError; an overlap
    fraction above 1 made every NCC undefined (every estimate flagged). Refused when the value
    is made, naming the field; whole numbers of NumPy's types and a float where a real number
    is meant stay accepted. (The ECC pre-filter, whose even sizes made OpenCV fail on every
    pair, and the search's sizes are no longer fields.)"""
    from stnh_tf.inference.options import Thresholds

    with pytest.raises(ValueError, match=message):
        Thresholds(**changes)
    kept = Thresholds(corner_std_tile=np.int64(32), min_overlap=1, coarse_corner_shift=150.5,
                      verified_ncc=1.01)
    assert kept.corner_std_tile == 32 and kept.coarse_corner_shift == 150.5


def test_the_thresholds_flag_takes_each_field_by_its_declared_type():
    """``--thresholds`` read a value by its default's type: ``coarse_corner_shift`` (default
    128, a whole number, but a real threshold) refused 150.5, while the whole-number fields'
    check was Thresholds' own. Each field is now read by its declared type."""
    from experiments.flags_common import thresholds_from_flag
    from stnh_tf.inference.options import Thresholds

    got = thresholds_from_flag(["coarse_corner_shift=150.5", "corner_std_tile=4"], Thresholds())
    assert (got.coarse_corner_shift, got.corner_std_tile) == (150.5, 4)
    with pytest.raises(ValueError, match="corner_std_tile takes a whole number; received '2.5'"):
        thresholds_from_flag(["corner_std_tile=2.5"], Thresholds())
    with pytest.raises(ValueError, match="min_overlap is a fraction"):
        thresholds_from_flag(["min_overlap=2"], Thresholds())


def test_gate_stages_takes_booleans_and_refuses_other_numbers():
    """``gate_stages=5`` and ``-1`` were taken as True, NumPy's ``True`` refused."""
    for value, want in ((True, True), (np.True_, True), (np.False_, False), (0, False)):
        assert EstimateOptions(gate_stages=value).gate_stages is want
    for value in (5, -1, 0.5, 1.0):
        with pytest.raises(ValueError, match="gate_stages must be a bool"):
            EstimateOptions(gate_stages=value)


def test_a_border_far_larger_than_image_a_is_still_drawn():
    """A 400x zoom into image_b (its border mapped 127,600 px wide, every corner in front): the
    first clipping cut the whole border away and drew nothing; clipped against the FAR box as
    well, the border is kept where it lies within reach and fills image_a (all of it covered,
    as NumPy's inverse mapping says)."""
    import cv2

    from stnh_tf.inference import overlays

    polygon = overlays.border_polygon(np.diag([400.0, 400.0, 1.0]), (320, 240))
    assert len(polygon) == 4 and np.abs(polygon).max() <= overlays.FAR
    filled = cv2.fillPoly(np.zeros((240, 320), np.uint8),
                          [np.round(polygon).astype(np.int32).reshape(-1, 1, 2)], 1)
    assert filled.all()


def _swap_that_cannot_undo(estimator, out, monkeypatch, match):
    """Export an old SavedModel to ``out``, then export over it with ``overwrite`` while both
    the move in and the move back fail (EXDEV); returns the old export's files (hidden ones
    aside) and the ``pytest.raises`` info of the error, which matches ``match``."""
    monkeypatch.setattr(export, "_write_archive", _fake_archive(b"old"))
    export.export_saved_model(estimator, out)
    before = {k: v for k, v in _files(out).items() if not k.startswith(".")}
    real_replace = os.replace

    def both_fail(src, dst):
        parent = os.path.basename(os.path.dirname(src))
        if (parent.startswith(export_folder.STAGING_PREFIX) and os.path.basename(src) ==
                "variables") or parent == export_folder.ASIDE:
            raise OSError(errno.EXDEV, "Invalid cross-device link", src)
        return real_replace(src, dst)

    monkeypatch.setattr(export, "_write_archive", _fake_archive(b"new"))
    monkeypatch.setattr(export_folder.os, "replace", both_fail)
    with pytest.raises(OSError, match=match) as info:
        export.export_saved_model(estimator, out, overwrite=True)
    monkeypatch.setattr(export_folder.os, "replace", real_replace)
    return before, info


def test_an_old_export_that_cannot_be_put_back_is_kept_and_named(estimator, tmp_path,
                                                                 monkeypatch):
    """Where the move in fails and so does the move back, the staging folder holding the old
    export aside was removed with it; it is kept now and the error names it: the old export's
    files are there byte for byte."""
    before, info = _swap_that_cannot_undo(
        estimator, tmp_path / "out", monkeypatch,
        "nor the old export back .*the old export's entries are in (.*); move them back by hand")
    aside = str(info.value).split("entries are in ")[1].split(";")[0]
    assert {k: v for k, v in _files(aside).items()} == before


def test_an_old_export_left_aside_is_put_back_by_the_next_export(estimator, tmp_path,
                                                                 monkeypatch):
    """After a swap whose move back failed too (above), the output held only the lock and the
    staging folder with the old export aside: the next export, even without ``overwrite``,
    took the output for empty, removed that folder with the old export and wrote its own. The
    old export is put back first now, and that export is refused as into any output holding
    one; the old export's files are in the output byte for byte."""
    out = tmp_path / "out"
    before, _ = _swap_that_cannot_undo(estimator, out, monkeypatch, "nor the old export back")
    assert not (out / "saved_model.pb").exists()  # the old export is aside, in staging
    with pytest.raises(FileExistsError, match="holds a SavedModel|was never verified"):
        export.export_saved_model(estimator, out)
    assert {k: v for k, v in _files(out).items() if not k.startswith(".")} == before
    assert not [n for n in os.listdir(out) if n.startswith(export_folder.STAGING_PREFIX)]
