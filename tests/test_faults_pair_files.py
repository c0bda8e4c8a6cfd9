"""A hostile read of the files that the camera-pair benchmark writes (issue 79's sets), kept as
tests: ``make_camera_pairs --overwrite`` that found no readable photograph replaced a complete
set's manifest by an incomplete stub; pair images already in a folder without a manifest were
overwritten silently; a smaller set written over a larger one left the larger one's images
beside it, read by name as unlabeled pairs; ``--json_out=-`` wrote a file named ``-``; an
unwritable ``--json_out`` was found only after the whole set was written. Each compares the
user's files byte for byte before and after.
"""

from __future__ import annotations

import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from stnh_tf.data import camera_pair_files as files
from stnh_tf.data import unlabeled_pairs

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _files(folder):
    """Every file below ``folder``: relative path -> bytes."""
    folder = str(folder)
    return {os.path.relpath(os.path.join(d, f), folder): open(os.path.join(d, f), "rb").read()
            for d, _, names in os.walk(folder) for f in names}


@pytest.fixture
def photos(pair_photos):
    return pair_photos


def test_overwrite_from_unreadable_photographs_keeps_the_set(photos, tmp_path):
    """Photographs that are listed but none of which decodes were found after the complete
    manifest had been replaced by the incomplete one: the error came, and the old set (its
    ground truth, its checksums) could no longer be loaded. The manifest is now replaced only
    once a photograph decodes: the set is left byte for byte and still loads."""
    out, broken = tmp_path / "pairs", tmp_path / "broken"
    files.write_pairs(photos, out, pairs_per_image=2, seed=0)
    broken.mkdir()
    (broken / "truncated.png").write_bytes((photos / "camera.png").read_bytes()[:60])
    before = _files(out)
    with pytest.raises(ValueError, match="no readable photograph"):
        files.write_pairs(broken, out, pairs_per_image=2, seed=1, overwrite=True)
    assert _files(out) == before
    manifest, pairs = files.load_pairs(out)
    assert manifest["seed"] == 0 and len(pairs) == 4


def test_pair_images_without_a_manifest_are_not_overwritten(photos, tmp_path):
    """A folder of pair images without ``pairs.json`` (unlabeled pairs laid out as the sets
    are, or a set whose manifest was deleted) had its images overwritten without
    ``overwrite``. Now refused in one line naming the folder and an image, nothing written;
    with ``overwrite`` they are replaced."""
    out = tmp_path / "mine"
    out.mkdir()
    cv2.imwrite(str(out / "00000_a.png"), np.full((240, 320), 7, np.uint8))
    cv2.imwrite(str(out / "00000_b.png"), np.full((240, 320), 9, np.uint8))
    before = _files(out)
    with pytest.raises(ValueError) as refused:
        files.write_pairs(photos, out, pairs_per_image=2)
    message = str(refused.value)
    assert str(out) in message and "00000_a.png" in message and "\n" not in message
    assert _files(out) == before
    files.write_pairs(photos, out, pairs_per_image=2, overwrite=True)
    assert len(files.load_pairs(out)[1]) == 4 and _files(out) != before


def test_a_smaller_set_over_a_larger_leaves_none_of_its_images(photos, tmp_path):
    """``overwrite`` with fewer pairs left the larger set's images past the new count in the
    folder: ``load_pairs`` ignored them, but unlabeled pairs are read by name, so a
    semi-supervised run read the old seed's pairs with the new ones. The images the new
    manifest does not list are removed once it is written; the folder then holds exactly the
    new set (the same files as a set made in an empty folder)."""
    out, fresh = tmp_path / "pairs", tmp_path / "fresh"
    files.write_pairs(photos, out, pairs_per_image=3, seed=0)
    assert len(unlabeled_pairs.list_pairs(str(out))[0]) == 6
    kept = {"notes.png": b"mine", "00000_c.png": b"mine too", "0000_a.png": b"four digits"}
    for name, data in kept.items():
        (out / name).write_bytes(data)
    files.write_pairs(photos, out, pairs_per_image=1, seed=5, overwrite=True)
    files.write_pairs(photos, fresh, pairs_per_image=1, seed=5)
    assert _files(out) == {**_files(fresh), **kept}  # files not named as pairs are left
    assert len(files.load_pairs(out)[1]) == 2
    assert files.PAIR_FILE.fullmatch("100000_b.png")  # from pair 100,000 on


def test_a_set_among_its_photographs_is_refused(photos):
    """``write_pairs`` called as a library function (``make_camera_pairs`` checked its flags
    apart before) would write, and now delete, pair images among the photographs it reads:
    refused before anything is written."""
    before = _files(photos)
    for out in (photos, photos / "pairs"):
        with pytest.raises(ValueError, match="image_dir"):
            files.write_pairs(photos, out, pairs_per_image=1)
    assert _files(photos) == before


def test_json_out_dash_is_standard_output_only(tmp_path, monkeypatch, capsys):
    """``--json_out=-`` of the binaries that print their JSON through ``common.emit_json``
    (make_camera_pairs, the benchmarks) wrote a file named ``-`` in the working folder, where
    the others print to standard output only."""
    import json

    from experiments import common

    monkeypatch.chdir(tmp_path)
    common.emit_json({"a": 1}, "-")
    assert json.loads(capsys.readouterr().out) == {"a": 1}
    assert os.listdir(tmp_path) == []
    common.emit_json({"a": 2}, "out.json")
    assert json.loads((tmp_path / "out.json").read_text())["a"] == 2


def test_make_camera_pairs_checks_json_out_before_the_set(photos, tmp_path):
    """An unwritable ``--json_out`` (a folder there) ended make_camera_pairs in a traceback
    after the whole set was written. It is now a one-line error before any pair."""
    out, blocker = tmp_path / "pairs", tmp_path / "taken"
    blocker.mkdir()
    env = dict(os.environ, TF_CPP_MIN_LOG_LEVEL="2", PYTHONPATH=ROOT)
    proc = subprocess.run([sys.executable, "-m", "experiments.make_camera_pairs",
                           f"--image_dir={photos}", f"--output_dir={out}",
                           "--pairs_per_image=1", f"--json_out={blocker}"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr
    assert "--json_out" in proc.stderr and f"{str(blocker)!r} is a directory" in proc.stderr
    assert not out.exists()


def test_make_camera_pairs_rerun_replaces_its_own_json_out(photos, tmp_path):
    """The summary ``--json_out`` carried the set manifest's ``format``, so a re-run with the same
    ``--json_out`` (``--overwrite``) was refused as if it would replace the set's record. The
    summary has no ``format`` now: the re-run replaces it, and the set's own manifest is still
    a record no ``--json_out`` replaces."""
    import json

    from stnh_tf import paths

    out, summary = tmp_path / "pairs", tmp_path / "summary.json"
    env = dict(os.environ, TF_CPP_MIN_LOG_LEVEL="2", PYTHONPATH=ROOT)
    for seed in (0, 1):
        proc = subprocess.run([sys.executable, "-m", "experiments.make_camera_pairs",
                               f"--image_dir={photos}", f"--output_dir={out}", "--overwrite",
                               "--pairs_per_image=1", f"--seed={seed}", f"--json_out={summary}"],
                              cwd=ROOT, capture_output=True, text=True, timeout=300, env=env)
        assert proc.returncode == 0, proc.stderr[-2000:]
        assert json.loads(summary.read_text())["seed"] == seed
    assert paths.project_record(str(summary)) is None
    assert paths.project_record(str(out / files.MANIFEST)) is not None
