"""The weights shipped in stnh_tf/weights load without a network and reproduce the numbers their
model card records on the seeded bundled test pairs (a regression guard for the files)."""

import json
import os

import numpy as np
import pytest

from data_prep import stage1
from stnh_tf import data, geometry, inference, model_files

WEIGHTS = model_files.default_weights_dir()
CARD = os.path.join(WEIGHTS, "model_card.json")
pytestmark = pytest.mark.skipif(not os.path.exists(CARD), reason="no weights shipped in stnh_tf/weights")


@pytest.fixture(scope="module")
def card_and_pairs(tmp_path_factory):
    with open(CARD) as f:
        card = json.load(f)
    check = card["bundled_check"]
    d = str(tmp_path_factory.mktemp("bundled"))
    stage1.make_dataset(check["source"], d, check["split"], seed=check["seed"],
                        samples_per_image=check["samples_per_image"], num_shards=1, log=lambda *a, **k: None)
    return card, data.load_arrays(d, check["split"])


def test_default_load_is_the_shipped_hierarchy(card_and_pairs):
    card, _ = card_and_pairs
    est = inference.HomographyEstimator.load()
    assert est.num_stages == len(card["stages"])
    for s in card["stages"]:
        assert os.path.getsize(os.path.join(WEIGHTS, s["file"])) < 20 * 2 ** 20


def test_shipped_weights_reproduce_their_recorded_mace(card_and_pairs):
    card, arrays = card_and_pairs
    check = card["bundled_check"]
    assert check["count"] == len(arrays["h_ba"])
    identity = float(geometry.mean_corner_error(np.broadcast_to(np.eye(3), arrays["h_ba"].shape), arrays["h_ba"]))
    assert identity == pytest.approx(check["identity_mace"], rel=1e-6)
    # The card records the precision its numbers were computed in (None: as the models were saved).
    dtype = check.get("compute_dtype")
    stages = [inference.HomographyEstimator.load(os.path.join(WEIGHTS, s["file"]),
                                                 compute_dtype=dtype).stages[0]
              for s in card["stages"]]
    for k in range(1, len(stages) + 1):
        h = inference.HomographyEstimator(stages[:k]).estimate(arrays["patch_a"], arrays["patch_b"])
        assert h.shape == (len(arrays["h_ba"]), 3, 3)
        mace = float(geometry.mean_corner_error(h, arrays["h_ba"]))
        assert mace == pytest.approx(check[f"estimate_mace_{k}_stages"], rel=1e-3, abs=1e-3)
        assert mace < identity
