r"""A model card's ``evaluation``, re-measured by one committed command (issue 78): the library core
of ``python -m experiments.ship_weights --refresh_evaluation --test_image_dir=DIR``.

Each evaluation a shipped card holds is re-run on the shipped files, on test pairs made from
``DIR`` exactly as ``data_prep.make_dataset`` makes them (:data:`TEST_PAIRS`: seed 1, three pairs
a photograph, the pairs BENCHMARKS.md's commands evaluate), and is written back under the same
key with ``machine`` (the commit, the machine and the library versions of this run,
:func:`stnh_tf.provenance.machine_info`) and ``test_pairs`` (how the pairs were made). What an
entry re-runs is data, :data:`NAMED`, chosen by its key:

- a card whose ``evaluation`` is one ``experiments.evaluate`` result (``paper_recipe``,
  ``paper_schedule``): that hierarchy, stored dtype, the clipping rule as the result records it;
- a card with named entries (the shipped default): every key of :data:`NAMED`, among them the
  same hierarchy on the photographs shipped inside installed packages, which no shipped model
  was trained on or chosen with; ``training`` (a record of how the stages were trained, not a
  measurement) is kept as it is.

The pairs must be the ones the card was measured on: where an entry records the identity's MACE
and the new pairs' differs, nothing is written (:class:`OtherPairs`).

    >>> sorted(NAMED)[:2]
    ['implausibility_coco_mini_test', 'implausibility_coco_mini_test_photometric']
"""

from __future__ import annotations

import dataclasses
import os
import tempfile

TEST_PAIRS = {"source": "folder", "split": "test", "seed": 1, "samples_per_image": 3}
"""How the test pairs are made from ``--test_image_dir`` (``stnh_tf.data.stage1.make_dataset``)."""

ROOT = ""
"""The key of a card whose ``evaluation`` is a single ``experiments.evaluate`` result."""


@dataclasses.dataclass(frozen=True)
class Evaluation:
    """One entry of a card's ``evaluation``.

    Attributes:
      kind: ``"hierarchy"`` (:func:`stnh_tf.evaluation.mace.evaluate` of the shipped stages, MACE
        after each stage with image context) or ``"implausibility"``
        (:func:`stnh_tf.evaluation.mace.implausibility_check` of ``estimate`` on bare patches).
      photometric: pairs with a photometric change of patch_b (``make_dataset --photometric``).
      clip_to_context: ``"hierarchy"``: the degenerate-prediction rule's clipping.
      compute_dtype: ``"float32"`` or ``None`` (the stages as saved).
      search: ``"implausibility"``: ``EstimateOptions.search``.
      source: the pairs' photographs: ``"folder"`` (``--test_image_dir``) or ``"bundled"``
        (those shipped inside installed packages,
        :func:`stnh_tf.data.bundled_photos.bundled_images`:
        photographs no shipped model was trained on or chosen with).
      baselines: ``"hierarchy"``: the baselines measured beside the model (a card's single
        ``evaluate`` result keeps those it has).
    """

    kind: str
    photometric: bool = False
    clip_to_context: bool = True
    compute_dtype: str | None = "float32"
    search: str = "none"
    source: str = "folder"
    baselines: tuple = ()


NAMED = {
    "plain_coco_mini_test": Evaluation("hierarchy"),
    "plain_coco_mini_test_no_clip": Evaluation("hierarchy", clip_to_context=False),
    "photometric_coco_mini_test": Evaluation("hierarchy", photometric=True),
    "implausibility_coco_mini_test": Evaluation("implausibility"),
    "implausibility_coco_mini_test_photometric": Evaluation("implausibility", photometric=True),
    "plain_bundled_test": Evaluation("hierarchy", source="bundled"),
}
"""What each named entry of the shipped default's card measures."""

KEPT = ("training",)
"""Named entries that record rather than measure: kept as they are."""


class OtherPairs(ValueError):
    """The test pairs differ from those an entry was measured on (its identity MACE)."""


def plan(evaluation: dict, num_stages: int = 3) -> dict[str, Evaluation]:
    """``{key: Evaluation}`` of what re-measuring ``evaluation`` (a card's, of ``num_stages``
    stages) runs: a single result, again, with its baselines; named entries, every entry of
    :data:`NAMED` (those the card lacks are added) but, for one stage, those without the
    clipping rule (it changes only a hierarchy).

    Raises:
      ValueError: a named entry that is neither in :data:`NAMED` nor :data:`KEPT`.
    """
    if "model" in evaluation:
        # A result written before --no_clip existed records no clip_to_context: it clipped.
        clip = bool(evaluation["model"].get("clip_to_context", True))
        return {ROOT: Evaluation("hierarchy", compute_dtype=None, clip_to_context=clip,
                                 baselines=tuple(sorted(evaluation.get("baselines") or {})))}
    unknown = sorted(set(evaluation) - set(NAMED) - set(KEPT))
    if unknown:
        raise ValueError(f"the card's evaluation has entries this command cannot re-measure: "
                         f"{unknown} (known: {sorted(NAMED)}; kept: {list(KEPT)}).")
    return {k: e for k, e in NAMED.items() if e.clip_to_context or num_stages > 1}


def _identity_mace(entry: dict):
    for path in (("identity", "mace"), ("ordinary", "identity_mace")):
        node = entry
        for k in path:
            node = node.get(k) if isinstance(node, dict) else None
        if node is not None:
            return float(node)
    return None


def refresh(weights_dir: str, card: dict, test_image_dir: str, log=print) -> dict:
    """``card`` with its ``evaluation`` re-measured on the stage files in ``weights_dir``.

    Args:
      weights_dir: the folder of the card and its stages (``card["stages"][k]["file"]``).
      card: the model card (not modified).
      test_image_dir: the test photographs (:data:`TEST_PAIRS` are made from them in a
        temporary folder).
      log: called with one line per entry measured.

    Returns:
      A new card, every entry of :func:`plan` replaced by its new measurement with ``machine`` and
      ``test_pairs``.

    Raises:
      OtherPairs: the new pairs' identity MACE differs from one an entry recorded.
      ValueError: as :func:`plan`; sources.SourceError: no photographs in ``test_image_dir``.
    """
    from stnh_tf.data import stage1
    from stnh_tf.evaluation import mace
    from stnh_tf.inference.options import EstimateOptions
    from stnh_tf.provenance import machine_info

    evaluation = card.get("evaluation") or {}
    todo = plan(evaluation, len(card["stages"]))
    stages = [os.path.join(weights_dir, s["file"]) for s in card["stages"]]
    new = {} if ROOT in todo else dict(evaluation)
    with tempfile.TemporaryDirectory() as tmp:
        data_dirs = {}
        for source, photometric in sorted({(e.source, e.photometric) for e in todo.values()}):
            data_dirs[source, photometric] = os.path.join(
                tmp, f"{source}_{'photometric' if photometric else 'plain'}")
            stage1.make_dataset(source, data_dirs[source, photometric], TEST_PAIRS["split"],
                                image_dir=test_image_dir if source == "folder" else None,
                                seed=TEST_PAIRS["seed"],
                                samples_per_image=TEST_PAIRS["samples_per_image"],
                                num_shards=1, log=lambda *a, **k: None, photometric=photometric)
        for key, spec in todo.items():
            data_dir = data_dirs[spec.source, spec.photometric]
            if spec.kind == "hierarchy":
                result = mace.evaluate(stages, data_dir, TEST_PAIRS["split"],
                                       baselines=spec.baselines,
                                       compute_dtype=spec.compute_dtype,
                                       clip_to_context=spec.clip_to_context)
                files = [s["file"] for s in card["stages"]]  # (one: a single model's result)
                result["model"].update({"model_dirs": files} if len(files) > 1
                                       else {"model_dir": files[0]})
            else:
                result = mace.implausibility_check(  # the folder's stage{k}.keras, in order
                    weights_dir, data_dir, TEST_PAIRS["split"],
                    options=EstimateOptions(search=spec.search))
                result["model"] = [s["file"] for s in card["stages"]]
                result["photometric"] = spec.photometric  # (its data_dir's pairs: as made)
            old = evaluation if key == ROOT else evaluation.get(key, {})
            before, after = _identity_mace(old), _identity_mace(result)
            if before is not None and after is not None and abs(before - after) > 1e-6:
                raise OtherPairs(
                    f"{key or 'evaluation'}: the pairs made from {test_image_dir} are not those "
                    f"the card was measured on (identity MACE {after:.4f}, recorded "
                    f"{before:.4f}); nothing was written. Give the card's test photographs.")
            result.pop("data_dir", None)
            result["test_pairs"] = {**TEST_PAIRS, "source": spec.source,
                                    "image_dir": test_image_dir if spec.source == "folder"
                                    else None, "photometric": spec.photometric}
            result["machine"] = machine_info()
            log(f"{key or 'evaluation'}: measured")
            if key == ROOT:
                new = result
            else:
                new[key] = result
    return {**card, "evaluation": new}


def refresh_card(weights_dir: str | None, test_image_dir: str, log=print) -> dict:
    """Re-measure the card in ``weights_dir`` (default: the package's ``stnh_tf/weights``) with
    :func:`refresh` and write it back atomically; returns the new card. Raises as
    :func:`refresh` (nothing written), ``FileNotFoundError`` without a card, and
    ``FileExistsError`` while a ship holds the folder (:func:`~stnh_tf.inference.shipped_weights.
    locked`)."""
    import json

    from stnh_tf.inference import model_files, shipped_weights
    from stnh_tf.paths import atomic_write_json

    weights_dir = weights_dir or model_files.default_weights_dir()
    path = os.path.join(weights_dir, "model_card.json")
    with shipped_weights.locked(weights_dir):  # (no ship may replace the files meanwhile)
        with open(path) as f:
            card = json.load(f)
        card = refresh(weights_dir, card, test_image_dir, log)
        card.pop("evaluation_stale", None)  # (re-measured on the files shipped now)
        atomic_write_json(path, card)
    return card
