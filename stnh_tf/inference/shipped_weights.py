"""Trained stage models copied into the package as its shipped weights, with a model card
(library core of ``experiments.ship_weights``, whose docstring lists the files written).

:func:`ship` writes ``stage{k}.keras`` (weights and architecture only), the manifest
``default.json`` and ``model_card.json``; :func:`replace_stage` swaps one stage of weights already
shipped; :func:`bundled_check` is the card's check that
``tests/test_shipped_weights.py`` re-computes, and :func:`refresh_check` re-records it for
weights already shipped.
"""

from __future__ import annotations

import json
import os

from stnh_tf.paths import atomic_write_json, stage_record_path
from stnh_tf.provenance import machine_info


def ship(model_dirs, weights_dir=None, eval_json=None) -> dict:
    """Copy the trained stages ``model_dirs`` (in order) into ``weights_dir`` (default: the
    package's ``stnh_tf/weights``) with the manifest and the model card; returns the card."""
    from stnh_tf.inference import model_files

    weights_dir = weights_dir or model_files.default_weights_dir()
    os.makedirs(weights_dir, exist_ok=True)
    card = {"stages": []}
    names = []
    for k, d in enumerate(model_dirs, start=1):
        card["stages"].append(_copy_stage(d, weights_dir, f"stage{k}.keras"))
        names.append(os.path.join(weights_dir, card["stages"][-1]["file"]))
    model_files.write_manifest(os.path.join(weights_dir, "default.json"), names,
                               description=f"{len(names)}-stage hierarchy shipped with stnh-tf")
    if eval_json:
        with open(eval_json) as f:
            card["evaluation"] = json.load(f)
    return _write_rechecked(weights_dir, card)


def _copy_stage(model_dir, weights_dir, name) -> dict:
    """Save run ``model_dir``'s model as ``weights_dir/name``; returns its card entry (file,
    source, the run's config and result without the history). ``model_dir`` may also be a
    chunked run's finished ``stage<k>.keras`` (:mod:`stnh_tf.training.chunks`): its config and
    chunks then come from the ``stage<k>.json`` beside it."""
    from stnh_tf.modeling import runner

    runner.load_model(model_dir).save(os.path.join(weights_dir, name))  # no optimizer state
    entry = {"file": name, "source": os.path.abspath(model_dir)}
    record = stage_record_path(model_dir)
    if os.path.isfile(model_dir) and os.path.exists(record):
        with open(record) as f:
            doc = json.load(f)
        entry.update(config=doc["config"], chunks=doc["chunks"], final_step=doc["final_step"],
                     wall_s=doc["wall_s"], machines=doc["machines"])
    for extra in ("config.json", "result.json"):
        path = os.path.join(model_dir, extra)
        if os.path.exists(path):
            with open(path) as f:
                doc = json.load(f)
            entry[extra[:-5]] = ({key: v for key, v in doc.items() if key != "history"}
                                 if extra == "result.json" else doc)
    return entry


def replace_stage(stage: int, model_dir, weights_dir=None, eval_json=None,
                  init_from_previous: bool = False) -> dict:
    """Replace stage ``stage`` (1-based) of already shipped weights by the trained run
    ``model_dir``, keeping the other stages' files and card entries; returns the card.

    The card's entry for the stage is rebuilt from the run; with ``init_from_previous`` (the run
    was initialised from the stage it replaces) the replaced entry is kept in it as
    ``init_from_run``, so the card records the whole chain of runs. ``eval_json`` (if given)
    replaces the card's ``evaluation``; the bundled check is re-computed.

    Raises:
      FileNotFoundError: no model card in ``weights_dir``.
      ValueError: ``stage`` is not one of the shipped stages.
    """
    weights_dir, card = _shipped_card(weights_dir)
    if isinstance(stage, bool) or not 1 <= int(stage) <= len(card["stages"]):
        raise ValueError(f"stage must be one of 1..{len(card['stages'])} (the shipped stages); "
                         f"received {stage!r}.")
    stage = int(stage)
    previous = card["stages"][stage - 1]
    entry = _copy_stage(model_dir, weights_dir, previous["file"])  # the manifest's name stays
    if init_from_previous:
        entry["init_from_run"] = previous
    card["stages"][stage - 1] = entry
    if eval_json:
        with open(eval_json) as f:
            card["evaluation"] = json.load(f)
    return _write_rechecked(weights_dir, card)


BUNDLED_CHECK = {"source": "bundled", "split": "test", "seed": 0, "samples_per_image": 3,
                 "compute_dtype": "float32", "fill": "reflect", "tta": "dihedral", "search": "ecc"}


def bundled_pairs(photometric: bool = False) -> dict:
    """The seeded bundled test pairs of :data:`BUNDLED_CHECK` as arrays
    (:func:`stnh_tf.data.tfrecords.load_arrays`); ``photometric`` changes each patch_b in
    brightness, contrast and gamma (:class:`stnh_tf.data.pairs.PhotometricChange`) on top of its
    homography."""
    import tempfile

    from stnh_tf.data import stage1
    from stnh_tf.data import tfrecords as data

    with tempfile.TemporaryDirectory() as tmp:
        stage1.make_dataset(BUNDLED_CHECK["source"], tmp, BUNDLED_CHECK["split"],
                            seed=BUNDLED_CHECK["seed"],
                            samples_per_image=BUNDLED_CHECK["samples_per_image"], num_shards=1,
                            log=lambda *a, **k: None, photometric=photometric)
        return data.load_arrays(tmp, BUNDLED_CHECK["split"])


def bundled_check(stage_paths) -> dict:
    """What ``HomographyEstimator.estimate`` gives with the first k shipped stages, k = 1..n, on
    the seeded bundled test pairs (:data:`BUNDLED_CHECK`; stages loaded with its
    ``compute_dtype``, the estimator's default, and estimated with its ``fill``): the numbers the
    shipped weights must keep reproducing (``tests/test_shipped_weights.py``).

    Keys: ``count``, ``identity_mace``, ``estimate_mace_{k}_stages`` and ``implausible_{k}_stages``
    (pairs the estimate flags implausible) on the plain pairs; the same with the prefix
    ``photometric_`` on the pairs with a photometric change (:func:`bundled_pairs`), plus
    ``photometric_worse_than_identity_{k}_stages``, the pairs whose corner error exceeds the
    identity's; ``[photometric_]ungated_estimate_mace_{k}_stages`` (k > 1): the same without the
    estimator's stage gate (``gate_stages=False``); ``[photometric_]tta_estimate_mace_{n}_stages``
    (and ``photometric_tta_worse_than_identity_{n}_stages``), all n stages with
    ``tta=BUNDLED_CHECK["tta"]``; ``[photometric_]unsearched_estimate_mace_{n}_stages`` (and
    ``photometric_unsearched_worse_than_identity_{n}_stages``), all n stages with
    ``search="none"``, the network's estimates. Every other estimate uses
    ``search=BUNDLED_CHECK["search"]``."""
    import dataclasses

    import numpy as np

    from stnh_tf import geometry
    from stnh_tf.inference.estimator import HomographyEstimator
    from stnh_tf.inference.options import EstimateOptions

    stages = [HomographyEstimator.load(p, compute_dtype=BUNDLED_CHECK["compute_dtype"]).stages[0]
              for p in stage_paths]
    out = dict(BUNDLED_CHECK)
    options = EstimateOptions(fill=BUNDLED_CHECK["fill"], search=BUNDLED_CHECK["search"])
    variants = {"ungated": dataclasses.replace(options, gate_stages=False),
                "tta": dataclasses.replace(options, tta=BUNDLED_CHECK["tta"]),
                "unsearched": dataclasses.replace(options, search="none")}
    for prefix, photometric in (("", False), ("photometric_", True)):
        arrays = bundled_pairs(photometric)
        identity = geometry.corner_errors(np.broadcast_to(np.eye(3), arrays["h_ba"].shape),
                                          arrays["h_ba"])
        if not prefix:
            out["count"] = int(len(identity))
        out[f"{prefix}identity_mace"] = float(identity.mean())
        for k in range(1, len(stages) + 1):
            estimator = HomographyEstimator(stages[:k])
            result = estimator.estimate_with_info(arrays["patch_a"], arrays["patch_b"], options)
            errors = geometry.corner_errors(result.homography, arrays["h_ba"])
            out[f"{prefix}estimate_mace_{k}_stages"] = float(errors.mean())
            out[f"{prefix}implausible_{k}_stages"] = int(result.implausible.sum())
            if prefix:
                out[f"{prefix}worse_than_identity_{k}_stages"] = int((errors > identity).sum())
            if k > 1:
                ungated = geometry.corner_errors(estimator.estimate(
                    arrays["patch_a"], arrays["patch_b"], variants["ungated"]), arrays["h_ba"])
                out[f"{prefix}ungated_estimate_mace_{k}_stages"] = float(ungated.mean())
            if k == len(stages):
                for name in ("tta", "unsearched"):
                    errors = geometry.corner_errors(estimator.estimate(
                        arrays["patch_a"], arrays["patch_b"], variants[name]), arrays["h_ba"])
                    out[f"{prefix}{name}_estimate_mace_{k}_stages"] = float(errors.mean())
                    if prefix:
                        out[f"{prefix}{name}_worse_than_identity_{k}_stages"] = int(
                            (errors > identity).sum())
    return out


def refresh_check(weights_dir=None) -> dict:
    """Re-compute ``bundled_check`` in the model card of already shipped weights."""
    return _write_rechecked(*_shipped_card(weights_dir))


def _shipped_card(weights_dir=None):
    """``(weights_dir, card)`` of already shipped weights (default: the package's)."""
    from stnh_tf.inference import model_files

    weights_dir = weights_dir or model_files.default_weights_dir()
    with open(os.path.join(weights_dir, "model_card.json")) as f:
        return weights_dir, json.load(f)


def _write_rechecked(weights_dir, card) -> dict:
    """Write ``card`` into ``weights_dir`` (atomically) with its bundled check re-computed, and
    under ``machine`` the commit, machine and library versions of this run
    (:func:`stnh_tf.provenance.machine_info`)."""
    card["bundled_check"] = bundled_check([os.path.join(weights_dir, s["file"])
                                           for s in card["stages"]])
    card["machine"] = machine_info()
    atomic_write_json(os.path.join(weights_dir, "model_card.json"), card)
    return card
