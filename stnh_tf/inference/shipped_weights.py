"""Trained stage models copied into the package as its shipped weights, with a model card
(library core of ``experiments.ship_weights``, whose docstring lists the files written).

:func:`ship` writes ``stage{k}.keras`` (weights and architecture only), the manifest
``default.json`` and ``model_card.json``; :func:`replace_stage` swaps one stage of weights already
shipped; :func:`bundled_check` is the card's check that
``tests/test_shipped_weights.py`` re-computes, and :func:`refresh_check` re-records it for
weights already shipped.
"""

from __future__ import annotations

import contextlib
import json
import os
import re

from stnh_tf.paths import (atomic_write_bytes, atomic_write_json, exclusive_lock, json_text,
                           stage_record_path)
from stnh_tf.provenance import machine_info


def ship(model_dirs, weights_dir=None, eval_json=None, allow_worse: bool = False) -> dict:
    """Copy the trained stages ``model_dirs`` (in order) into ``weights_dir`` (default: the
    package's ``stnh_tf/weights``) with the manifest and the model card; returns the card.

    Every model and ``eval_json`` is read, and the new files written and checked in a staging
    folder, before anything shipped is replaced; the files, manifest and card then go in
    together (:func:`_install`), or nothing does. Stage files of the weights replaced beyond the
    new stages (``stage3.keras`` where two stages are shipped over three) go with them.

    Raises:
      FileNotFoundError: a model or ``eval_json`` that is not there.
      ValueError: a bundled-check number worse than the card being replaced says
        (:func:`worse_checks`) while ``allow_worse`` is off.
    """
    from stnh_tf.inference import model_files

    weights_dir = weights_dir or model_files.default_weights_dir()
    stages = [_read_stage(d, f"stage{k}.keras") for k, d in enumerate(model_dirs, start=1)]
    card = {"stages": [entry for _, entry in stages]}
    if eval_json:
        card["evaluation"] = _read_json(eval_json)
    os.makedirs(weights_dir, exist_ok=True)
    with locked(weights_dir):
        old_card = _card_if_any(weights_dir)
        return _install(weights_dir, {e["file"]: m for m, e in stages}, card, old_card,
                        allow_worse, manifest=f"{len(stages)}-stage hierarchy shipped with stnh-tf")


@contextlib.contextmanager
def locked(weights_dir):
    """Hold the weights folder ``weights_dir`` (an existing folder) for one writer of its files
    or card (:func:`ship`, :func:`replace_stage`, :func:`refresh_check`,
    :func:`stnh_tf.evaluation.card_evaluation.refresh_card`), after putting back what a ship
    killed there left (:func:`put_back`). The lock is the folder's own ``flock``
    (:func:`stnh_tf.paths.exclusive_lock`): nothing is written for it, and a killed holder
    leaves none held.

    Raises:
      FileExistsError: another writer holds it (nothing is read or replaced).
      FileNotFoundError: ``weights_dir`` is not a folder.
    """
    if not os.path.isdir(weights_dir):
        raise FileNotFoundError(f"no weights folder {weights_dir} (its model_card.json and "
                                "stage files).")
    with exclusive_lock(weights_dir, f"another ship_weights is writing in {weights_dir} (it "
                                     "holds the folder's lock): nothing replaced; run one at "
                                     "a time."):
        put_back(weights_dir)
        yield


def _read_stage(model_dir, name) -> tuple:
    """``(model, card entry)`` of run ``model_dir`` to ship as ``name``: the entry holds the
    file, the source, the run's config and result without the history. ``model_dir`` may also
    be a chunked run's finished ``stage<k>.keras`` (:mod:`stnh_tf.training.chunks`): its config
    and chunks then come from the ``stage<k>.json`` beside it."""
    from stnh_tf.modeling import runner

    model = runner.load_model(model_dir)
    entry = {"file": name, "source": os.path.abspath(model_dir)}
    record = stage_record_path(model_dir)
    if os.path.isfile(model_dir) and os.path.exists(record):
        doc = _read_json(record)
        entry.update(config=doc["config"], chunks=doc["chunks"], final_step=doc["final_step"],
                     wall_s=doc["wall_s"], machines=doc["machines"])
    for extra in ("config.json", "result.json"):
        path = os.path.join(model_dir, extra)
        if os.path.exists(path):
            doc = _read_json(path)
            entry[extra[:-5]] = ({key: v for key, v in doc.items() if key != "history"}
                                 if extra == "result.json" else doc)
    return model, entry


def replace_stage(stage: int, model_dir, weights_dir=None, eval_json=None,
                  init_from_previous: bool = False, allow_worse: bool = False) -> dict:
    """Replace stage ``stage`` (1-based) of already shipped weights by the trained run
    ``model_dir``, keeping the other stages' files and card entries; returns the card.

    The card's entry for the stage is rebuilt from the run; with ``init_from_previous`` (the run
    was initialised from the stage it replaces) the replaced entry is kept in it as
    ``init_from_run``, so the card records the whole chain of runs. ``eval_json`` (if given)
    replaces the card's ``evaluation``; without it the evaluation, measured on the old stage, is
    kept marked ``evaluation_stale`` (``ship_weights --refresh_evaluation`` re-measures it). The
    bundled check is re-computed; files and card go in together (:func:`_install`).

    Raises:
      FileNotFoundError: no model card in ``weights_dir``, no model in ``model_dir``, or no
        ``eval_json``.
      ValueError: ``stage`` is not one of the shipped stages; a bundled-check number worse than
        the card says (:func:`worse_checks`) while ``allow_worse`` is off.
    """
    from stnh_tf.inference import model_files

    weights_dir = weights_dir or model_files.default_weights_dir()
    with locked(weights_dir):
        return _replace_stage(stage, model_dir, weights_dir, eval_json, init_from_previous,
                              allow_worse)


def _replace_stage(stage, model_dir, weights_dir, eval_json, init_from_previous, allow_worse):
    """:func:`replace_stage` in the locked folder ``weights_dir``."""
    card = _shipped_card(weights_dir)
    if isinstance(stage, bool) or not 1 <= int(stage) <= len(card["stages"]):
        raise ValueError(f"stage must be one of 1..{len(card['stages'])} (the shipped stages); "
                         f"received {stage!r}.")
    stage = int(stage)
    old_card = json.loads(json.dumps(card))
    previous = card["stages"][stage - 1]
    model, entry = _read_stage(model_dir, previous["file"])  # the manifest's name stays
    if init_from_previous:
        entry["init_from_run"] = previous
    card["stages"][stage - 1] = entry
    if eval_json:
        card["evaluation"] = _read_json(eval_json)
        card.pop("evaluation_stale", None)
    elif "evaluation" in card:
        card["evaluation_stale"] = (
            f"stage {stage} ({previous['file']}) was replaced after this evaluation was "
            "measured: re-measure it (experiments.ship_weights --refresh_evaluation).")
    return _install(weights_dir, {previous["file"]: model}, card, old_card, allow_worse)


WORSE_TOLERANCE = (0.05, 0.05)
"""``(relative, px)``: a bundled-check MACE counts as worse beyond ``old * 1.05 + 0.05`` px
(the same model's number moves by far less between CPUs and OpenCV paths)."""


def worse_checks(old: dict, new: dict) -> dict:
    """``{key: [old, new]}`` of the bundled-check MACEs (``[photometric_]estimate_mace_{k}_stages``
    and their ``unsearched``/``tta`` forms) both checks hold where ``new`` is worse than ``old``
    beyond :data:`WORSE_TOLERANCE`.

    >>> worse_checks({"estimate_mace_1_stages": 2.0}, {"estimate_mace_1_stages": 3.1})
    {'estimate_mace_1_stages': [2.0, 3.1]}
    """
    import re

    rel, px = WORSE_TOLERANCE
    return {k: [old[k], v] for k, v in (new or {}).items()
            if re.fullmatch(r"(photometric_)?((un)?searched_|tta_)?estimate_mace_\d+_stages", k)
            and isinstance(old.get(k) if old else None, (int, float))
            and v > old[k] * (1 + rel) + px}


def _install(weights_dir, models: dict, card: dict, old_card, allow_worse, manifest=None):
    """Save ``models`` (``{file name: Keras model}``) into a staging folder inside
    ``weights_dir``, re-compute ``card``'s bundled check there (with the shipped files of the
    stages not replaced), refuse a worse check than ``old_card``'s unless ``allow_worse``, then
    move the files into place, the old ones aside, and write the manifest (``manifest``: its
    description; None: kept) and the card; where any of that fails, the old files, manifest and
    card are put back (a process killed meanwhile: :func:`put_back`, by the next ship). The
    card records ``bundled_check_change`` (the numbers that moved)."""
    import tempfile

    staging = tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=weights_dir)
    return _install_staged(weights_dir, staging, models, card, old_card, allow_worse, manifest)


def put_back(weights_dir) -> list:
    """Undo what a ship killed in ``weights_dir`` left (its staging folder): by the plan it wrote before moving anything, the files it had set aside in the
    folder's ``.previous`` (models, manifest, card) go back over what it had placed, a model file
    it placed where none was goes, and the folder goes: the old weights as before it. A ship
    killed after writing its card (the swap done, its folder not yet marked so) is left as it
    finished. Called first by :func:`locked` (every writer of the folder), so every staging
    folder it finds is a dead writer's: whether that process's id now names another process
    says nothing (ids are reused, across containers at once); returns the names put back or
    removed."""
    import shutil

    names = []
    for stale in sorted(os.listdir(weights_dir)):
        folder = os.path.join(weights_dir, stale)
        if not (stale.startswith(STAGING_PREFIX) and os.path.isdir(folder)
                and not os.path.islink(folder)):
            continue
        # no plan: killed before it moved anything; no .previous, or its new card and every
        # new model in place (none left in the staging folder): killed after the swap
        plan = (_read_json(os.path.join(folder, PLAN))
                if os.path.isdir(os.path.join(folder, PREVIOUS))
                and os.path.exists(os.path.join(folder, PLAN))
                else {"swap": [], "new": [], "kept": []})
        if _swap_done(weights_dir, folder, plan):
            plan = {"swap": [], "new": [], "kept": []}
        # (nothing else: no half-written temp file)
        for name in plan["swap"] + plan["kept"] + plan.get("dropped", []):
            old, target = os.path.join(folder, PREVIOUS, name), os.path.join(weights_dir, name)
            if os.path.exists(old):
                os.replace(old, target)
                names.append(name)
            elif name in plan["new"] and os.path.exists(target):
                os.remove(target)
                names.append(name)
        shutil.rmtree(folder, ignore_errors=True)
    return names


def _swap_done(weights_dir, folder, plan) -> bool:
    """Whether the ship whose staging folder is ``folder`` (its ``plan``) had finished its swap:
    the card it was writing is the folder's, and each model it swapped is in the weights folder,
    none in the staging folder (a swap being undone moves them back there first)."""
    new_card = _bytes_if_any(os.path.join(folder, NEW_CARD))
    return (new_card is not None
            and new_card == _bytes_if_any(os.path.join(weights_dir, "model_card.json"))
            and all(os.path.exists(os.path.join(weights_dir, n))
                    and not os.path.exists(os.path.join(folder, n)) for n in plan["swap"]))


def _install_staged(weights_dir, staging, models, card, old_card, allow_worse, manifest):
    """:func:`_install` in the staging folder ``staging`` (removed at the end)."""
    import shutil

    from stnh_tf.inference import model_files

    try:
        for name, model in models.items():
            model.save(os.path.join(staging, name))  # (a save cut short: in staging only)
        card["bundled_check"] = bundled_check([
            os.path.join(staging if s["file"] in models else weights_dir, s["file"])
            for s in card["stages"]])
        card["machine"] = machine_info()
        before = (old_card or {}).get("bundled_check") or {}
        worse = worse_checks(before, card["bundled_check"])
        if worse and not allow_worse:
            raise ValueError(f"the new weights' bundled check is worse than the card in "
                             f"{weights_dir} says ({_pairs_text(worse)}): nothing replaced; "
                             "pass --allow_worse to ship them anyway.")
        card["bundled_check_change"] = {
            k: [before[k], v] for k, v in card["bundled_check"].items()
            if isinstance(v, float) and isinstance(before.get(k), float) and v != before[k]}
        kept = {n: _bytes_if_any(os.path.join(weights_dir, n))
                for n in ("default.json", "model_card.json")}
        # a ship of fewer stages: the earlier ship's later stage files go with the old files (a
        # folder load of numbered stages would run them)
        dropped = [] if manifest is None else sorted(
            n for n in os.listdir(weights_dir) if re.fullmatch(r"stage\d+\.keras", n)
            and n not in {s["file"] for s in card["stages"]})
        aside = os.path.join(staging, PREVIOUS)
        # the card as it will be written: put_back's sign that the swap was done
        atomic_write_bytes(os.path.join(staging, NEW_CARD), json_text(card).encode())
        os.makedirs(aside)
        for name, data in kept.items():  # (for put_back, should this process be killed)
            if data is not None:
                atomic_write_bytes(os.path.join(aside, name), data)
        atomic_write_json(os.path.join(staging, PLAN), {
            "swap": list(models), "kept": [n for n, d in kept.items() if d is not None],
            "new": [n for n in models if not os.path.exists(os.path.join(weights_dir, n))],
            "dropped": dropped})
        moved, placed = [], []
        try:
            for name in models:
                target = os.path.join(weights_dir, name)
                if os.path.exists(target):
                    os.replace(target, os.path.join(aside, name))
                    moved.append(name)
                os.replace(os.path.join(staging, name), target)
                placed.append(name)
            for name in dropped:
                os.replace(os.path.join(weights_dir, name), os.path.join(aside, name))
                moved.append(name)
            if manifest is not None:
                model_files.write_manifest(os.path.join(weights_dir, "default.json"),
                                           [os.path.join(weights_dir, s["file"])
                                            for s in card["stages"]], description=manifest)
            atomic_write_json(os.path.join(weights_dir, "model_card.json"), card)
            os.replace(aside, os.path.join(staging, ".shipped"))  # the swap is done: no put_back
        except BaseException as e:
            try:
                os.remove(os.path.join(staging, NEW_CARD))  # (undoing: never a finished swap)
                for name in placed:
                    os.replace(os.path.join(weights_dir, name), os.path.join(staging, name))
                for name in moved:
                    os.replace(os.path.join(aside, name), os.path.join(weights_dir, name))
                for name, data in kept.items():
                    if data is not None:
                        atomic_write_bytes(os.path.join(weights_dir, name), data)
            except BaseException as undo:
                staging = None  # kept: its .previous holds the old files
                raise RuntimeError(f"shipping failed ({e!r}) and so did putting the old files "
                                   f"back ({undo!r}): they are in {aside}; the next ship into "
                                   f"{weights_dir} from a new process puts them back.") from e
            raise
    finally:
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)
    return card


PREVIOUS, PLAN, NEW_CARD = ".previous", ".plan.json", ".new_card.json"
""":func:`_install_staged`'s folder, inside the staging folder, of the files it replaces, its
record of the swap (the model files, those new, the manifest and card kept) for :func:`put_back`,
and the card it writes last (in place: the swap was done)."""


STAGING_PREFIX = ".stnh_tf_ship."
"""The hidden folders inside the weights folder that new files are written and checked in
(``tempfile.mkdtemp``'s names); one found by the next writer, under the folder's lock, is a
killed ship's (:func:`put_back`)."""


def _pairs_text(worse: dict) -> str:
    return ", ".join(f"{k} {a:.3f} -> {b:.3f} px" for k, (a, b) in sorted(worse.items()))


def _bytes_if_any(path):
    if not os.path.exists(path):
        return None
    with open(path, "rb") as f:
        return f.read()


def _read_json(path):
    with open(path) as f:
        return json.load(f)


def _card_if_any(weights_dir):
    path = os.path.join(weights_dir, "model_card.json")
    return _read_json(path) if os.path.exists(path) else None


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
    """Re-compute ``bundled_check`` in the model card of already shipped weights (default: the
    package's)."""
    from stnh_tf.inference import model_files

    weights_dir = weights_dir or model_files.default_weights_dir()
    with locked(weights_dir):
        return _write_rechecked(weights_dir, _shipped_card(weights_dir))


def _shipped_card(weights_dir):
    """The model card of the weights shipped in ``weights_dir``."""
    with open(os.path.join(weights_dir, "model_card.json")) as f:
        return json.load(f)


def _write_rechecked(weights_dir, card) -> dict:
    """Write ``card`` into ``weights_dir`` (atomically) with its bundled check re-computed, and
    under ``machine`` the commit, machine and library versions of this run
    (:func:`stnh_tf.provenance.machine_info`)."""
    card["bundled_check"] = bundled_check([os.path.join(weights_dir, s["file"])
                                           for s in card["stages"]])
    card["machine"] = machine_info()
    atomic_write_json(os.path.join(weights_dir, "model_card.json"), card)
    return card
