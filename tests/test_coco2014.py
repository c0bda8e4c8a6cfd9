"""``--source=coco2014`` (tensorflow-datasets ``coco/2014``) tested offline, against a prepared fake
builder: the split map, the undecoded JPEG bytes (``SkipDecoding``) made into the same pairs as
the folder source makes from the same files, the file names, ``max_images``, and the errors when
tensorflow-datasets is missing or COCO 2014 is not prepared."""

import sys
import types

import cv2
import numpy as np
import pytest
import skimage.data
import tensorflow as tf
import tensorflow_datasets as tfds

from stnh_tf.data import sources, stage1
from stnh_tf.data import tfrecords as data

NAMES = ["COCO_train2014_000000000009.jpg", "COCO_train2014_000000000025.jpg",
         "COCO_val2014_000000000042.jpg"]


@pytest.fixture(scope="module")
def jpegs(tmp_path_factory):
    """Three photographs as the JPEG files COCO ships (folder) and their bytes (tfds)."""
    folder = tmp_path_factory.mktemp("coco_folder")
    photos = [skimage.data.astronaut(), skimage.data.coffee(), skimage.data.chelsea()]
    out = {}
    for name, rgb in zip(NAMES, photos):
        ok, encoded = cv2.imencode(".jpg", cv2.resize(rgb[..., ::-1], (400, 300)))
        assert ok
        (folder / name).write_bytes(encoded.tobytes())
        out[name] = encoded.tobytes()
    return folder, out


class FakeCocoBuilder:
    """What stage1.coco2014_items uses of a prepared ``tfds.builder("coco/2014")``."""

    def __init__(self, jpegs, data_dir):
        self.jpegs, self.data_dir, self.requests = jpegs, data_dir, []
        counts = {"train+validation": len(jpegs), "test": 1}
        self.info = types.SimpleNamespace(splits={
            k: types.SimpleNamespace(num_examples=n) for k, n in counts.items()})

    def is_prepared(self):
        return True

    def as_dataset(self, split, shuffle_files, decoders):
        self.requests.append((split, shuffle_files, type(decoders["image"]).__name__))
        names = list(self.jpegs) if split == "train+validation" else NAMES[:1]
        return tf.data.Dataset.from_tensor_slices({
            "image": [self.jpegs[n] for n in names],
            "image/filename": [n.encode() for n in names]})


@pytest.fixture
def fake_tfds(jpegs, monkeypatch, tmp_path):
    made = []

    def builder(name, data_dir=None):
        assert name == "coco/2014"
        made.append(FakeCocoBuilder(jpegs[1], data_dir or str(tmp_path / "tfds")))
        return made[-1]

    monkeypatch.setattr(tfds, "builder", builder)
    return made


@pytest.mark.parametrize("max_images", [0, 2])
def test_coco2014_pairs_equal_the_folder_sources(jpegs, fake_tfds, tmp_path, max_images):
    folder, _ = jpegs
    kw = dict(seed=3, samples_per_image=2, num_shards=1, max_images=max_images,
              log=lambda *a, **k: None)
    stage1.make_dataset("coco2014", str(tmp_path / "tfds_out"), "train",
                        tfds_data_dir=str(tmp_path / "tfds"), **kw)
    stage1.make_dataset("folder", str(tmp_path / "folder_out"), "train", image_dir=str(folder),
                        **kw)
    # the split map: the stage-1 "train" split is COCO's train + validation, undecoded bytes
    assert fake_tfds[0].requests == [("train+validation", False, "SkipDecoding")]
    a = data.load_arrays(str(tmp_path / "tfds_out"), "train")
    b = data.load_arrays(str(tmp_path / "folder_out"), "train")
    n = 2 * (max_images or len(NAMES))
    assert len(a["patch_a"]) == len(b["patch_a"]) == n
    for key in ("patch_a", "patch_b", "h_ba", "context_a"):
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    split = data.read_metadata(str(tmp_path / "tfds_out"))["splits"]["train"]
    assert (split["source"], split["tfds_name"]) == ("coco2014", "coco/2014")
    assert split["tfds_split"] == "train+validation" and split["num_files_listed"] == len(NAMES)


def test_coco2014_test_split_and_file_names(jpegs, fake_tfds, tmp_path):
    seen = []
    items, n, info = stage1.coco2014_items("test", data_dir=str(tmp_path / "tfds"),
                                           log=seen.append)
    items = list(items)
    assert n == 1 and [it.item_id for it in items] == NAMES[:1]
    assert items[0].payload == jpegs[1][NAMES[0]]
    assert info["tfds_split"] == "test" and fake_tfds[0].requests[0][0] == "test"


def test_coco2014_without_tensorflow_datasets_says_what_to_do(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "tensorflow_datasets", None)  # import fails
    with pytest.raises(sources.SourceError, match="needs tensorflow-datasets.*--source=folder"):
        stage1.make_dataset("coco2014", str(tmp_path / "out"), "train")
    assert not (tmp_path / "out" / "metadata.json").exists()


def test_coco2014_not_prepared_offline_says_how_to_prepare(monkeypatch, tmp_path):
    monkeypatch.setattr(stage1, "_network_reachable", lambda *a, **k: False)
    with pytest.raises(sources.SourceError) as error:
        stage1.make_dataset("coco2014", str(tmp_path / "out"), "train",
                            tfds_data_dir=str(tmp_path / "tfds"))
    message = str(error.value)
    assert "not prepared" in message and str(tmp_path / "tfds") in message
    assert "--source=folder --image_dir" in message and "train2014 + val2014" in message
