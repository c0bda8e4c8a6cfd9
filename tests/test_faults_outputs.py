"""Issue 80's faults of outputs and inputs, kept as tests: a binary that deleted what it did not
write (item 1), wrote its result over the dataset it read (2), built data from the model of
another stage (3), read its own earlier output back as photographs (4), or wrote a dataset into
a training run's folder (9). Each drives the binary as a user does (``python -m``) and compares
the user's files byte for byte before and after; the verdict is a one-line error naming the
flags, with nothing written.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest
import skimage.data

from stnh_tf.data import stage1, stage_k
from test_device_photographs import photograph_sets
from stnh_tf.paths import atomic_write_json

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
QUIET = lambda *a, **k: None  # noqa: E731


def _files(folder):
    """Every file below ``folder`` (links followed): relative path -> bytes."""
    folder = str(folder)
    return {os.path.relpath(os.path.join(d, f), folder): open(os.path.join(d, f), "rb").read()
            for d, _, names in os.walk(folder, followlinks=True) for f in names}


def _binary(module, *args):
    env = dict(os.environ, TF_CPP_MIN_LOG_LEVEL="2", PYTHONPATH=ROOT)
    return subprocess.run([sys.executable, "-m", module, *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=300, env=env)


def _refused(proc, binary, *fragments):
    """The binary ended with rc 1 and one line ``<binary>: ...`` holding ``fragments``."""
    assert proc.returncode == 1, (proc.returncode, proc.stderr[-2000:])
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith(f"{binary}: ") and all(f in last for f in fragments), last
    assert "Traceback" not in proc.stderr


def _photo_folder(folder, n=4):
    os.makedirs(folder)
    for i, image in enumerate([skimage.data.camera(), skimage.data.coins(), skimage.data.moon(),
                               skimage.data.astronaut()][:n]):
        cv2.imwrite(os.path.join(folder, f"{i}.png"), image)
    return str(folder)


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    """Bundled photographs, 4 images x 3 pairs for train and test (stage-1 data)."""
    d = str(tmp_path_factory.mktemp("tiny_data"))
    stage1.make_dataset("bundled", d, "train", seed=0, num_shards=1, max_images=4, log=QUIET)
    stage1.make_dataset("bundled", d, "test", seed=1, num_shards=1, max_images=4, log=QUIET)
    return d


@pytest.fixture(scope="module")
def stage1_run(tiny_data, tmp_path_factory):
    """A stage-1 training run's folder as ``train_stage`` leaves it: its ``config.json`` (with the
    marker) and a ``model.keras`` (a narrow, untrained stage)."""
    import keras

    from conftest import narrow_network
    from stnh_tf.modeling import models
    from stnh_tf.training import run_dir
    from stnh_tf.training.config import TrainConfig

    folder = str(tmp_path_factory.mktemp("stage1_run"))
    cfg = TrainConfig(model_dir=folder, data_dir=tiny_data, stage=1, train_steps=4)
    atomic_write_json(os.path.join(folder, run_dir.CONFIG_FILE),
                      {**cfg.to_json(), **run_dir.CONFIG_MARKER})
    keras.utils.set_random_seed(0)
    with narrow_network():
        models.build_stn_homography().save(os.path.join(folder, run_dir.FINAL_MODEL))
    return folder


# ------------------------------------------------------------------------------------------------
# Item 1: device_photographs clears only its own files, never through a link
# ------------------------------------------------------------------------------------------------
def test_device_photographs_never_deletes_through_a_link_in_its_output(tmp_path):
    """Item 1: with ``OUT/part-1/photos_extra`` (a copy it made) replaced by a link to the real
    ``--extra_dir``, the second run removed the source photographs through the link (rc 0).
    Now nothing is followed out of ``--output_dir``: the run ends with one line naming the link,
    and every source photograph is still there, byte for byte."""
    coco, extra = photograph_sets(tmp_path, (2, 1, 2))
    (tmp_path / "whl").mkdir()
    out = tmp_path / "dev"
    flags = [f"--coco_dir={coco}", f"--extra_dir={extra}", f"--output_dir={out}",
             f"--wheels_dir={tmp_path / 'whl'}", "--call_mib=1024"]
    first = _binary("experiments.device_photographs", *flags)
    assert first.returncode == 0, first.stderr[-2000:]
    copy = out / "part-1" / "photos_extra"
    assert sorted(os.listdir(copy / "set1")) == ["p0.jpg", "p1.jpg"]
    sources_before = _files(extra)
    shutil.rmtree(copy)
    os.symlink(extra, copy)
    second = _binary("experiments.device_photographs", *flags)
    assert _files(extra) == sources_before
    _refused(second, "device_photographs", str(copy), "symbolic link")
    assert os.path.islink(copy)


# ------------------------------------------------------------------------------------------------
# Item 2: an output that is (or lies in) the dataset a binary reads
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("binary, args, fragments", [
    ("evaluate", ["--baselines=identity", "--data_dir={d}", "--json_out={d}/metadata.json"],
     ["--json_out", "is inside --data_dir"]),
    ("plot_hbar_histogram", ["--data_dir={d}", "--output={d}/metadata.png"],
     ["--output", "is inside --data_dir"]),
])
def test_an_output_inside_the_dataset_read_is_refused(tiny_data, tmp_path, binary, args,
                                                      fragments):
    """Item 2: ``evaluate --json_out=D/metadata.json`` wrote its result over the dataset it read
    (rc 0), as ``plot_hbar_histogram --output=D/metadata.png`` did with its ``.json`` beside the
    PNG. An output inside an input folder is refused before any work; D is unchanged."""
    d = tmp_path / "data"
    shutil.copytree(tiny_data, d)
    before = _files(d)
    proc = _binary(f"experiments.{binary}", *(a.format(d=d) for a in args))
    _refused(proc, binary, *fragments)
    assert _files(d) == before


def test_an_output_reached_through_a_link_to_the_input_is_refused(tiny_data, tmp_path):
    """Item 2, through a link: ``--json_out=L/metadata.json`` with ``L`` a link to the dataset
    is the dataset's file."""
    d, link = tmp_path / "data", tmp_path / "link"
    shutil.copytree(tiny_data, d)
    os.symlink(d, link)
    before = _files(d)
    proc = _binary("experiments.evaluate", "--baselines=identity", f"--data_dir={d}",
                   f"--json_out={link}/metadata.json")
    _refused(proc, "evaluate", "--json_out", "--data_dir")
    assert _files(d) == before


# ------------------------------------------------------------------------------------------------
# Item 3: make_stage_dataset with the model of another stage
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def stage2_data(tiny_data, tmp_path_factory):
    """Stage-2 data from tiny_data (the identity as the stage-1 prediction)."""
    d = str(tmp_path_factory.mktemp("stage2_data"))

    def identity(patch_a, patch_b):
        return np.broadcast_to(np.eye(3), (len(patch_a), 3, 3))

    for split in ("train", "test"):
        stage_k.make_stage_dataset(2, tiny_data, d, split, predict=identity, log=QUIET)
    return d


@pytest.mark.parametrize("form", ["run folder", pytest.param("chunked stage file", marks=(
    pytest.mark.slow))])  # ~8 s each on a loaded 2-core machine: the second only in make test-all
def test_stage_data_from_the_model_of_another_stage_is_refused(stage2_data, stage1_run, tmp_path,
                                                               form):
    """Item 3: ``make_stage_dataset --stage=3 --model_dir=R`` with R a stage-1 run built stage-3
    data from the wrong stage's model (rc 0). The model's stage, from its run's ``config.json``
    or the record beside a chunked run's ``stage<k>.keras``, must be k-1: refused, naming both
    stages and the record, before the model loads; no output folder is made."""
    model, record = stage1_run, os.path.join(stage1_run, "config.json")
    if form == "chunked stage file":  # paper_schedule/stage<k>.keras and its record
        model, record = str(tmp_path / "stage1.keras"), str(tmp_path / "stage1.json")
        shutil.copyfile(os.path.join(stage1_run, "model.keras"), model)
        atomic_write_json(record, {"format": "stnh_tf.chunked_stage", "stage": 1,
                                   "config": json.load(open(os.path.join(stage1_run,
                                                                         "config.json")))})
    out = tmp_path / "stage3"
    proc = _binary("data_prep.make_stage_dataset", "--stage=3", f"--input_dir={stage2_data}",
                   f"--model_dir={model}", f"--output_dir={out}", "--num_workers=1")
    _refused(proc, "make_stage_dataset", "stage-1", "stage-2", record)
    assert not out.exists()


# ------------------------------------------------------------------------------------------------
# Item 4: an output folder inside the photographs read, or holding them
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("output, images, fragment", [
    ("photos", "photos", "is --image_dir"),
    ("photos/pairs", "photos", "is inside --image_dir"),
    ("work", "work/photos", "holds --image_dir"),
])
def test_camera_pairs_never_written_among_the_photographs_they_are_made_from(
        tmp_path, output, images, fragment):
    """Item 4: ``make_camera_pairs --output_dir=F --image_dir=F`` wrote its pairs among the
    photographs, and a second run (``--overwrite``) read them as 12 photographs from 4. An output
    folder that is, lies inside or holds the image folder is refused; the photographs' folder is
    unchanged."""
    photos = _photo_folder(tmp_path / images)
    before = _files(tmp_path)
    proc = _binary("experiments.make_camera_pairs", f"--output_dir={tmp_path / output}",
                   f"--image_dir={photos}", "--pairs_per_image=1")
    _refused(proc, "make_camera_pairs", "--output_dir", fragment)
    assert _files(tmp_path) == before


def test_make_dataset_never_writes_among_its_photographs(tmp_path):
    """Item 4, make_dataset: TFRecords in a folder inside ``--image_dir`` are refused."""
    photos = _photo_folder(tmp_path / "photos")
    before = _files(tmp_path)
    proc = _binary("data_prep.make_dataset", "--source=folder", f"--image_dir={photos}",
                   f"--output_dir={photos}/data", "--num_workers=1")
    _refused(proc, "make_dataset", "--output_dir", "is inside --image_dir")
    assert _files(tmp_path) == before


# ------------------------------------------------------------------------------------------------
# Item 9: a dataset written into a training run's folder
# ------------------------------------------------------------------------------------------------
def test_make_dataset_refuses_a_training_runs_folder(tiny_data, tmp_path):
    """Item 9: ``make_dataset --output_dir=<a training run folder>`` wrote TFRecords and a
    ``metadata.json`` among the run's files. A folder that holds a run is refused by name; the
    run's files are unchanged."""
    from stnh_tf.training import run_dir
    from stnh_tf.training.config import TrainConfig

    run = tmp_path / "run"
    run.mkdir()
    cfg = TrainConfig(model_dir=str(run), data_dir=tiny_data, stage=1, train_steps=4)
    atomic_write_json(run / run_dir.CONFIG_FILE, {**cfg.to_json(), **run_dir.CONFIG_MARKER})
    before = _files(run)
    proc = _binary("data_prep.make_dataset", "--source=bundled", f"--output_dir={run}",
                   "--max_images=4", "--num_workers=1")
    _refused(proc, "make_dataset", "--output_dir", "training run")
    assert _files(run) == before


def test_export_refuses_to_overwrite_the_model_it_exports(tmp_path):
    """``export --model=R --output=R --overwrite``: the folder the model is read from is refused
    as the output before the model is loaded, in one line naming both flags (the output rule of
    every binary; before, the export's own check refused it after loading, as "not a
    SavedModel"), the folder byte for byte as it was."""
    from stnh_tf.inference import model_files

    run = tmp_path / "run"
    shutil.copytree(os.path.dirname(model_files.resolve_model_paths(None)[0]), run)
    before = _files(run)
    proc = _binary("experiments.export", f"--model={run}", f"--output={run}", "--overwrite")
    _refused(proc, "export", "--output", "--model")
    assert _files(run) == before


def test_make_camera_pairs_refuses_json_out_inside_its_set(tmp_path):
    """``make_camera_pairs --json_out=D/pairs.json`` wrote its summary over the set's manifest
    (the set could no longer be read); a --json_out inside --output_dir is refused before
    anything is written."""
    photos = _photo_folder(tmp_path / "photos", 2)
    out = tmp_path / "set"
    proc = _binary("experiments.make_camera_pairs", f"--image_dir={photos}",
                   f"--output_dir={out}", f"--json_out={out / 'pairs.json'}")
    _refused(proc, "make_camera_pairs", "--json_out", "--output_dir")
    assert not out.exists()
