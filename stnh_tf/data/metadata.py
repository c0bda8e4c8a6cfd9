"""``metadata.json`` of a dataset being written, and the locks of its writers.

* **metadata.json** (``{"format": "stnh_tf.dataset", "format_version": 1, "stage": ...,
  "feature_spec": ..., "splits": {split: {...}}}``) is read-modify-written under a file lock
  (``.metadata.lock``) and replaced atomically, so separate commands can write ``train`` and
  ``test`` into one directory (:func:`update_metadata`). A ``metadata.json`` this project did not
  write is refused, never merged into (:func:`read_metadata_file`).
* **One writer per split.** :func:`split_lock` holds the split's lock (``.{split}.lock``) for one
  writer; a second writer of the same split fails at once.

The readers' side is :mod:`stnh_tf.data.tfrecords`. Standard library only
(with :mod:`stnh_tf.paths`).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
from typing import Optional

from stnh_tf.data.tfrecords import METADATA_FILE
from stnh_tf.paths import atomic_write_json, exclusive_lock, read_json

LOCK_FILE = ".metadata.lock"
METADATA_MARKER = {"format": "stnh_tf.dataset", "format_version": 1}
"""Written into metadata.json: what makes it a dataset's metadata (:func:`read_metadata_file`)."""
# The top-level keys of the metadata.json files written before METADATA_MARKER.
_LEGACY_KEYS = frozenset({"stage", "feature_spec", "splits"})
_SPLIT_STATUSES = ("incomplete", "complete", "empty")


@contextlib.contextmanager
def _metadata_lock(output_dir: str):
    import fcntl

    with open(os.path.join(output_dir, LOCK_FILE), "a") as f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def _legacy_problem(meta: dict) -> Optional[str]:
    """Why ``meta``, a metadata.json without :data:`METADATA_MARKER`, is not one this project wrote
    before the marker existed (None if it is): only the keys ``stage`` (an integer >= 1),
    ``feature_spec`` (an object) and ``splits`` (an object of split sections, each an object
    with a ``status`` the writer sets)."""
    unknown = sorted(set(meta) - _LEGACY_KEYS)
    if unknown:
        return f"its keys {unknown[:5]} are not a dataset's"
    splits = meta.get("splits")
    if not isinstance(splits, dict):
        return "it has no 'splits' object"
    for name, section in splits.items():
        if not isinstance(section, dict) or section.get("status") not in _SPLIT_STATUSES:
            return f"its split {name!r} is not a section the writer made (no status)"
    stage = meta.get("stage", 1)
    if isinstance(stage, bool) or not isinstance(stage, int) or stage < 1:
        return f"its stage is {stage!r}, not an integer >= 1"
    if not isinstance(meta.get("feature_spec", {}), dict):
        return "its feature_spec is not an object"
    return None


def read_metadata_file(output_dir: str) -> dict:
    """The ``metadata.json`` being written in ``output_dir`` ({} before the first split).

    Raises:
      ValueError: naming the file, when it is not valid JSON, or not one this project wrote
        (without :data:`METADATA_MARKER`, and not one written before the marker existed:
        :func:`_legacy_problem`): a user's own ``metadata.json`` is never merged into.
    """
    path = os.path.join(output_dir, METADATA_FILE)
    if not os.path.exists(path):
        return {}
    try:
        meta = read_json(path, "dataset metadata")
    except ValueError as e:
        raise ValueError(f"{e} Move it away.") from None
    if not isinstance(meta, dict):
        why = f"it holds a JSON {type(meta).__name__}, not an object"
    elif "format" in meta:
        why = (None if meta["format"] == METADATA_MARKER["format"]
               else f"its format is {meta['format']!r}")
        if why is None and meta.get("format_version") != METADATA_MARKER["format_version"]:
            raise ValueError(f"{path} has format_version {meta.get('format_version')!r}; this "
                             f"version of stnh_tf writes version "
                             f"{METADATA_MARKER['format_version']}.")
    else:
        why = _legacy_problem(meta)
    if why is not None:
        raise ValueError(f"{path} is not the metadata of a stnh-tf dataset (no \"format\": "
                         f"\"{METADATA_MARKER['format']}\", and not one written before that "
                         f"marker: {why}); it is neither changed nor merged into: write to "
                         "another --output_dir, or move the file away.")
    return meta


def update_metadata(output_dir: str, split: str, section: Optional[dict],
                    top: Optional[dict] = None, check=None) -> dict:
    """Merge ``top`` into metadata.json and set ``splits[split] = section`` (locked, atomic;
    ``section`` None: the split's section is left as it is). ``check(metadata)`` is called under
    the lock first: what it raises leaves the file unchanged.

    Raises:
      ValueError: ``top`` contradicts a value already there (e.g. another ``stage``).
    """
    with _metadata_lock(output_dir):
        meta = read_metadata_file(output_dir)
        if check is not None:
            check(meta)
        for key, value in (top or {}).items():
            if key in meta and meta[key] != value and key in ("stage", "feature_spec"):
                raise ValueError(f"{os.path.join(output_dir, METADATA_FILE)} has {key}="
                                 f"{json.dumps(meta[key])[:200]}, this run has "
                                 f"{json.dumps(value)[:200]}; write to another --output_dir.")
            meta[key] = value
        meta.setdefault("splits", {})
        meta.update(METADATA_MARKER)
        if section is not None:
            meta["splits"][split] = section
        atomic_write_json(os.path.join(output_dir, METADATA_FILE), meta)
        return meta


def check_split_name(split: str) -> str:
    """``split`` if it is a plain name like ``train`` (letters, digits, ``_`` and ``.``, not
    starting with ``.``: no ``..``; not ``metadata``, whose split lock would be the metadata's
    own, :data:`LOCK_FILE`: a writer waited on itself for ever), else ``ValueError``: it names
    files in the output folder."""
    if not isinstance(split, str) or not re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_.]*", split):
        raise ValueError(f"split must be a plain name like 'train' (letters, digits, '_' and '.', "
                         f"not starting with '.'); received {split!r}.")
    if f".{split.lower()}.lock" == LOCK_FILE:  # (a file system blind to case: one file)
        raise ValueError(f"split {split!r} is reserved (its lock would be the dataset's "
                         f"{LOCK_FILE}); choose another name.")
    return split


@contextlib.contextmanager
def split_lock(output_dir: str, split: str):
    """Hold ``output_dir``'s lock of ``split`` (``.{split}.lock``, ``fcntl.flock``) for one
    writer: a second writer of the same split, in this process or another, fails at once with
    ``FileExistsError`` instead of deleting the first one's temporary shards. The lock goes with
    the process (nothing stale is left by a killed run): :func:`stnh_tf.paths.exclusive_lock`."""
    path = os.path.join(output_dir, f".{split}.lock")
    with exclusive_lock(path, f"another process is writing split {split!r} in {output_dir} (it "
                              f"holds {path}); wait for it to finish, or write to another "
                              "--output_dir or --split."):
        yield
