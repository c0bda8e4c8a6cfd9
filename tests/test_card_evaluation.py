"""experiments.ship_weights --refresh_evaluation (stnh_tf.evaluation.card_evaluation): a card's
evaluation re-measured on its shipped files, each entry with the commit and machine of the run.

The stages output a constant H whatever their input (as in test_ship_weights), so the MACE after
each stage is a NumPy corner computation on the pairs ``data_prep.make_dataset`` writes with the
card's test-pair settings (seed 1, three a photograph) from a folder of photographs made here.
"""

import json
import os
import shutil

import cv2
import numpy as np
import pytest

from test_ship_weights import _constant_run, _mace_numpy
from stnh_tf.data import bundled_photos, stage1
from stnh_tf.data import tfrecords as data
from stnh_tf.evaluation import card_evaluation


def _photographs(folder, ids):
    os.makedirs(folder)
    for image_id, gray in bundled_photos.bundled_images():
        if image_id in ids:
            cv2.imwrite(os.path.join(folder, image_id.replace("/", "_")), gray)
    return str(folder)


def test_plan_by_card_layout():
    one = {"model": {"clip_to_context": False}, "identity": {"mace": 24.0}}
    assert card_evaluation.plan(one) == {"": card_evaluation.Evaluation(
        "hierarchy", compute_dtype=None, clip_to_context=False)}
    # written before --no_clip existed: no clip_to_context recorded, and it clipped
    assert card_evaluation.plan({"model": {}})[""].clip_to_context is True
    named = {"plain_coco_mini_test": {}, "training": {}, "implausibility_coco_mini_test": {}}
    # every named measurement, those the card lacks added; the training record kept
    assert card_evaluation.plan(named) == card_evaluation.NAMED
    assert card_evaluation.NAMED["plain_bundled_test"].source == "bundled"
    with pytest.raises(ValueError, match="cannot re-measure.*'hand_made'"):
        card_evaluation.plan({**named, "hand_made": {}})
    # a single result keeps its baselines (a refresh dropped them); one stage: no entries
    # without the clipping rule, which changes only a hierarchy (the refresh failed on them)
    with_baselines = {**one, "baselines": {"sift_ransac": {}, "identity": {}}}
    assert card_evaluation.plan(with_baselines)[""].baselines == ("identity", "sift_ransac")
    assert card_evaluation.plan(named, num_stages=1) == {
        k: e for k, e in card_evaluation.NAMED.items() if k != "plain_coco_mini_test_no_clip"}


@pytest.mark.slow
def test_refresh_measures_the_shipped_files_and_refuses_other_pairs(tmp_path, narrow,
                                                                     monkeypatch):
    # two of the named measurements: the test photographs' and the bundled ones' (the others
    # differ from them only in their settings, and take minutes with the search)
    monkeypatch.setattr(card_evaluation, "NAMED", {
        key: card_evaluation.NAMED[key] for key in ("plain_coco_mini_test", "plain_bundled_test")})
    h = np.array([[1.04, 0.02, -3.0], [-0.02, 0.97, 4.0], [1e-4, -1e-4, 1.0]])
    _constant_run(tmp_path / "s1", h, mixed=False)
    _constant_run(tmp_path / "s2", np.eye(3), mixed=False)
    weights = tmp_path / "weights"
    os.makedirs(weights)
    for k in (1, 2):  # as ship_weights lays them out, without its slow bundled check
        shutil.copy(tmp_path / f"s{k}" / "model.keras", weights / f"stage{k}.keras")
    card_path = weights / "model_card.json"
    card = {"stages": [{"file": "stage1.keras"}, {"file": "stage2.keras"}],
            "evaluation": {"plain_coco_mini_test": {"identity": {"mace": 1e9}},
                           "training": {"stage1": "kept as it is"}}}
    with open(card_path, "w") as f:
        json.dump(card, f)
    photos = _photographs(tmp_path / "photos", {"skimage/camera.png", "skimage/astronaut.png"})

    # The recorded identity (1e9) is not that of these pairs: refused, nothing written.
    before = card_path.read_bytes()
    with pytest.raises(card_evaluation.OtherPairs, match="nothing was written"):
        card_evaluation.refresh_card(str(weights), photos, log=lambda *_: None)
    assert card_path.read_bytes() == before

    del card["evaluation"]["plain_coco_mini_test"]["identity"]
    with open(card_path, "w") as f:
        json.dump(card, f)
    lines = []
    new = card_evaluation.refresh_card(str(weights), photos, log=lines.append)
    assert lines == ["plain_coco_mini_test: measured", "plain_bundled_test: measured"]
    assert new["evaluation"]["training"] == {"stage1": "kept as it is"}
    entry = new["evaluation"]["plain_coco_mini_test"]
    with open(card_path) as f:
        assert json.load(f) == new

    # The oracle: the pairs make_dataset writes with the card's settings, and NumPy corners.
    pairs = tmp_path / "pairs"
    settings = card_evaluation.TEST_PAIRS
    stage1.make_dataset(settings["source"], str(pairs), settings["split"], image_dir=photos,
                        seed=settings["seed"], samples_per_image=settings["samples_per_image"],
                        log=lambda *a, **k: None)
    h_ba = data.load_arrays(str(pairs), "test")["h_ba"].astype(np.float64)
    assert entry["count"] == len(h_ba) == 6
    assert entry["identity"]["mace"] == pytest.approx(_mace_numpy(np.eye(3), h_ba), rel=1e-9)
    for k in (1, 2):  # stage 2 is the identity: both stages leave the constant H
        assert entry["model"]["stages"][f"after_{k}_stages"]["mace"] == pytest.approx(
            _mace_numpy(h, h_ba), abs=1e-3)
    assert entry["model"]["model_dirs"] == ["stage1.keras", "stage2.keras"]
    assert entry["test_pairs"] == {**settings, "image_dir": photos, "photometric": False}
    bundled = new["evaluation"]["plain_bundled_test"]
    assert bundled["test_pairs"]["source"] == "bundled" and bundled["test_pairs"]["image_dir"] is None
    assert bundled["count"] == 3 * len(bundled_photos.bundled_images())
    assert entry["machine"]["cpu_count"] == os.cpu_count() and "git_commit" in entry["machine"]
    assert "data_dir" not in entry  # a temporary folder, gone

    # Measured again on the same photographs: the same numbers (the identity check passes).
    again = card_evaluation.refresh_card(str(weights), photos, log=lambda *_: None)
    assert again["evaluation"]["plain_coco_mini_test"]["model"]["mace"] == entry["model"]["mace"]


@pytest.mark.slow
def test_a_one_stage_card_refreshed_keeps_its_baselines_and_photometric_records(tmp_path,
                                                                                narrow,
                                                                                monkeypatch):
    """A card whose evaluation is one ``evaluate`` result with baselines lost them on a
    refresh; a one-stage card's result was written with ``model_dirs`` (a hierarchy's key);
    the photometric implausibility entry recorded
    ``photometric: false``. Now the baselines are measured again (the same MACE: SIFT + RANSAC
    is deterministic), one stage is recorded as ``model_dir`` (as ``evaluate`` records one
    model), and the entry says ``photometric: true``."""
    from stnh_tf.evaluation import mace

    h = np.array([[1.04, 0.02, -3.0], [-0.02, 0.97, 4.0], [1e-4, -1e-4, 1.0]])
    _constant_run(tmp_path / "s1", h, mixed=False)
    weights = tmp_path / "weights"
    os.makedirs(weights)
    shutil.copy(tmp_path / "s1" / "model.keras", weights / "stage1.keras")
    photos = _photographs(tmp_path / "photos", {"skimage/camera.png", "skimage/astronaut.png"})
    settings, pairs = card_evaluation.TEST_PAIRS, tmp_path / "pairs"
    stage1.make_dataset(settings["source"], str(pairs), settings["split"], image_dir=photos,
                        seed=settings["seed"], samples_per_image=settings["samples_per_image"],
                        log=lambda *a, **k: None)
    old = mace.evaluate([str(weights / "stage1.keras")], str(pairs), "test",
                        baselines=("sift_ransac",))
    card_path = weights / "model_card.json"
    card_path.write_text(json.dumps({"stages": [{"file": "stage1.keras"}], "evaluation": old}))
    new = card_evaluation.refresh_card(str(weights), photos, log=lambda *_: None)["evaluation"]
    assert sorted(new["baselines"]) == ["sift_ransac"]
    assert new["baselines"]["sift_ransac"]["mace"] == old["baselines"]["sift_ransac"]["mace"]
    assert new["model"]["model_dir"] == "stage1.keras" and "model_dirs" not in new["model"]
    monkeypatch.setattr(card_evaluation, "NAMED", {
        "implausibility_coco_mini_test_photometric":
            card_evaluation.NAMED["implausibility_coco_mini_test_photometric"]})
    card_path.write_text(json.dumps({"stages": [{"file": "stage1.keras"}], "evaluation": {}}))
    named = card_evaluation.refresh_card(str(weights), photos, log=lambda *_: None)
    entry = named["evaluation"]["implausibility_coco_mini_test_photometric"]
    assert entry["photometric"] is True and entry["test_pairs"]["photometric"] is True


@pytest.mark.slow
def test_the_implausibility_check_refuses_stage_k_pairs(tmp_path, narrow):
    """On stage-2 pairs (``h_prev`` not the identity) the implausibility check scored a model
    against the original pair's ``h_ba``, ignoring ``h_prev``, where ``evaluate`` composes it:
    the same model and pairs got two MACEs without a word. Refused now, as ``evaluate``'s
    baselines refuse them."""
    from stnh_tf.data import stage_k
    from stnh_tf.evaluation import mace

    _constant_run(tmp_path / "s1", np.eye(3), mixed=False)
    photos = _photographs(tmp_path / "photos", {"skimage/camera.png"})
    d1, d2 = tmp_path / "pairs1", tmp_path / "pairs2"
    stage1.make_dataset("folder", str(d1), "test", image_dir=photos, seed=1,
                        samples_per_image=3, num_shards=1, log=lambda *a, **k: None)
    shift = np.array([[1.0, 0.0, 3.0], [0.0, 1.0, -2.0], [0.0, 0.0, 1.0]])
    stage_k.make_stage_dataset(2, str(d1), str(d2), "test", num_shards=1,
                               predict=lambda a, b: np.broadcast_to(shift, (len(a), 3, 3)).copy(),
                               log=lambda *a, **k: None)
    with pytest.raises(ValueError, match="stage-1 pairs.*h_prev != identity"):
        mace.implausibility_check(str(tmp_path / "s1"), str(d2), "test")
    assert mace.implausibility_check(str(tmp_path / "s1"), str(d1), "test")["ordinary"][
        "count"] == 3  # (stage-1 pairs: measured as before)
