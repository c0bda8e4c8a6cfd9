"""Where the models :meth:`stnh_tf.inference.estimator.HomographyEstimator.load` reads are:
hierarchy manifests, the accepted layouts on disk, and the shipped default in ``stnh_tf/weights/``.

Hierarchy manifest (a JSON file; by convention ``hierarchy.json``)::

    {
      "format": "stnh_tf.hierarchy",
      "version": 1,
      "stages": ["stage1/model.keras", "stage2", "stage3.keras"],
      "description": "optional free text"
    }

``stages`` lists the stage models in order: each a ``.keras`` file or a training run directory
holding ``model.keras``, given relative to the manifest's folder and inside it (absolute paths
and ``../`` are refused, so a manifest cannot make the loader read models from elsewhere). Each
stage may be a single-stage or a sequence model. :func:`write_manifest` writes one.
:func:`resolve_model_paths` (and so :meth:`~stnh_tf.inference.estimator.HomographyEstimator.load`)
accepts

* a ``.keras`` file;
* a ``.json`` manifest;
* a directory holding ``model.keras`` (a training run: single or sequence model);
* a directory holding ``hierarchy.json`` (the manifest);
* a directory holding ``default.json`` (a manifest) or ``default.keras``: a weights folder as
  ``experiments.ship_weights`` writes it (the package's ``stnh_tf/weights/`` or a copy), loaded
  as shipped whatever other stage files lie beside it;
* a directory holding stage models named ``stage1``, ``stage2``, ... (sub-directories holding
  ``model.keras``, or files ``stage1.keras``, ...), taken as a hierarchy in numeric order (a gap
  in the numbers, or two models for one stage, is refused, naming the files);
* nothing: the shipped default in the package folder ``stnh_tf/weights/``: ``default.json`` (a
  manifest) if present, else ``default.keras``.

Standard library only: nothing here loads a model.
"""

from __future__ import annotations

import os
import re

from stnh_tf.paths import atomic_write_json, inside, read_json

MANIFEST_FORMAT = "stnh_tf.hierarchy"
MANIFEST_VERSION = 1
MANIFEST_FILE = "hierarchy.json"
MODEL_FILE = "model.keras"
DEFAULT_MANIFEST = "default.json"
DEFAULT_MODEL = "default.keras"
PAPER_RECIPE_WEIGHTS = "paper_recipe"
"""Folder under :func:`default_weights_dir` of the paper recipe's CPU-budget hierarchy (the default
before the fast recipe's)."""
PAPER_SCHEDULE_WEIGHTS = "paper_schedule"
"""Folder under :func:`default_weights_dir` of the stages trained at the paper's schedule
(91,000 steps each: ``experiments.paper_schedule``)."""


def default_weights_dir() -> str:
    """The package folder ``stnh_tf/weights`` (may not exist before weights are shipped)."""
    return os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "weights")


def default_source() -> str:
    """The shipped weights' manifest (or single model) that ``load()`` reads."""
    folder = default_weights_dir()
    manifest = os.path.join(folder, DEFAULT_MANIFEST)
    return manifest if os.path.isfile(manifest) else os.path.join(folder, DEFAULT_MODEL)


# --------------------------------------------------------------------------------------------
# Manifests
# --------------------------------------------------------------------------------------------
def write_manifest(path, stages, description: str = "") -> str:
    """Write a hierarchy manifest to ``path`` naming ``stages`` (model files or run directories).

    Every stage must lie in the manifest's folder or below it (:func:`read_manifest` reads no
    other); it is stored relative to the folder, so the folder can be moved. Returns ``path``.

    Raises:
      ValueError: no stage, or a stage outside the manifest's folder.
    """
    folder = os.path.dirname(os.path.abspath(path))
    entries = []
    for stage in stages:
        full = os.path.abspath(os.fspath(stage))
        rel = os.path.relpath(full, folder)
        if rel == os.pardir or rel.startswith(os.pardir + os.sep):
            raise ValueError(f"stage {full} is outside the manifest's folder {folder}: a manifest "
                             "names stages beside it or below it; write it next to the stages, "
                             "or copy the stage models into its folder.")
        entries.append(rel.replace(os.sep, "/"))
    if not entries:
        raise ValueError("a hierarchy manifest needs at least one stage; received none.")
    doc = {"format": MANIFEST_FORMAT, "version": MANIFEST_VERSION, "stages": entries}
    if description:
        doc["description"] = description
    atomic_write_json(path, doc, sort_keys=False)
    return os.fspath(path)


def read_manifest(path) -> list:
    """The stage model paths (absolute, in order) named by the hierarchy manifest at ``path``.

    Every stage must be a relative path inside the manifest's folder (beside it or below it);
    absolute paths and ``../`` escapes raise ``ValueError`` (:func:`stnh_tf.paths.inside`). A
    stage that exists must be a ``.keras`` file or a folder (a training run): the manifest
    itself, another manifest or any other file raises ``ValueError`` naming the manifest and
    the stage (a missing one is left to the loader, which names it)."""
    path = os.fspath(path)
    doc = read_json(path, "hierarchy manifest")
    if not isinstance(doc, dict) or doc.get("format") != MANIFEST_FORMAT:
        raise ValueError(f"{path} is not a hierarchy manifest: expected a JSON object with "
                         f"\"format\": \"{MANIFEST_FORMAT}\"; received {str(doc)[:200]}.")
    if doc.get("version") != MANIFEST_VERSION:
        raise ValueError(f"hierarchy manifest {path} has version {doc.get('version')!r}; this "
                         f"version of stnh_tf reads version {MANIFEST_VERSION}.")
    stages = doc.get("stages")
    if (not isinstance(stages, list) or not stages
            or not all(isinstance(s, str) and s for s in stages)):
        raise ValueError(f"hierarchy manifest {path}: \"stages\" must be a non-empty list of "
                         f"paths; received {stages!r}.")
    folder = os.path.dirname(os.path.abspath(path))
    stage_paths = [inside(folder, s, f"hierarchy manifest {path}, stage {k}")
                   for k, s in enumerate(stages, start=1)]
    for k, (name, stage) in enumerate(zip(stages, stage_paths), start=1):
        if not os.path.isfile(stage) or stage.endswith(".keras"):
            continue
        what = ("the manifest itself" if os.path.samefile(stage, path) else
                "not a .keras model or a run folder (a manifest's stages are models; a "
                "manifest cannot name another)")
        raise ValueError(f"hierarchy manifest {path}, stage {k}: {name!r} is {what}.")
    return stage_paths


# --------------------------------------------------------------------------------------------
# Layouts
# --------------------------------------------------------------------------------------------
def _numbered_stages(directory):
    """``stage1``, ``stage2``, ... (directories or ``.keras`` files) in ``directory``, in order.

    Raises:
      ValueError: naming the files, when the numbers do not run 1, 2, ..., n without a gap, or
        when two entries give the same stage (``stage1/`` and ``stage1.keras``, ``stage01``):
        which models make the hierarchy would otherwise be a guess.
    """
    found = {}
    for name in sorted(os.listdir(directory)):
        m = re.fullmatch(r"stage(\d+)(\.keras)?", name)
        if m:
            found.setdefault(int(m.group(1)), []).append(name)
    clashes = {k: names for k, names in found.items() if len(names) > 1}
    if clashes:
        listed = "; ".join(f"stage {k}: {', '.join(names)}" for k, names in sorted(clashes.items()))
        raise ValueError(f"{directory} holds more than one model for a stage ({listed}): keep "
                         "one of each, or list the stages in a hierarchy.json manifest.")
    if found and sorted(found) != list(range(1, len(found) + 1)):
        missing = sorted(set(range(1, max(found) + 1)) - set(found))
        listed = ", ".join(found[k][0] for k in sorted(found))
        why = (f"stage {', '.join(map(str, missing))} missing" if missing
               else "no stage 0")
        raise ValueError(f"{directory} holds stage models {listed}: the stages of a hierarchy are "
                         f"numbered 1, 2, ... without a gap ({why}); add the missing ones, "
                         "rename the files, or list the stages in a hierarchy.json manifest.")
    return [os.path.join(directory, found[k][0]) for k in sorted(found)]


def resolve_model_paths(path=None) -> list:
    """The stage model paths that :meth:`~stnh_tf.inference.estimator.HomographyEstimator.load`
    would load (see the module docstring for the accepted layouts). Raises ``FileNotFoundError``
    with the places looked at, and ``ValueError`` naming the files for numbered stages with a gap or
    two models for one stage."""
    if path is None:
        folder = default_weights_dir()
        manifest, model = (os.path.join(folder, DEFAULT_MANIFEST),
                           os.path.join(folder, DEFAULT_MODEL))
        if os.path.isfile(manifest):
            return read_manifest(manifest)
        if os.path.isfile(model):
            return [model]
        raise FileNotFoundError(
            f"no shipped weights: this copy of stnh_tf has neither {manifest} nor {model}. Pass "
            "the path of a trained model (.keras file, run directory or hierarchy manifest) "
            "instead.")
    path = os.fspath(path)
    if os.path.isdir(path):
        # a weights folder as shipped (stnh_tf/weights/ or a copy) holds default.json: the
        # hierarchy it names, not the stage files beside it
        for candidate in (MODEL_FILE, MANIFEST_FILE, DEFAULT_MANIFEST, DEFAULT_MODEL):
            if os.path.isfile(os.path.join(path, candidate)):
                break
        else:
            stages = _numbered_stages(path)
            if stages:
                return stages
            raise FileNotFoundError(
                f"{path} holds no model: expected {MODEL_FILE}, {MANIFEST_FILE}, "
                f"{DEFAULT_MANIFEST}, {DEFAULT_MODEL} or stage1, stage2, ... models.")
        path = os.path.join(path, candidate)
    if not os.path.exists(path):
        raise FileNotFoundError(f"no model at {path}.")
    if path.endswith(".json"):
        return read_manifest(path)
    return [path]
