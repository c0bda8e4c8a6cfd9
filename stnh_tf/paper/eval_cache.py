"""A reproduction's evaluation cache (``eval/<key>.json``): what each evaluation was measured on,
so that one is reused only for the same models on the same test pairs.

An evaluation records :data:`CACHE_KEY`: the sha256 of each model file it evaluated and the
digest of the test pairs (a TFRecord split's :func:`stnh_tf.data.tfrecords.split_digest`, or the
pairs made in memory). One written before the record is kept while it is newer than every model
it evaluated (the rule then).
"""

from __future__ import annotations

import hashlib
import json
import os

CACHE_KEY = "measured_on"
"""The key of an evaluation's record of its models and pairs."""


def pairs_digest(run) -> str | None:
    """The digest of reproduction ``run``'s stage-1 test pairs: its TFRecord test split's
    (:func:`stnh_tf.data.tfrecords.split_digest`), or, with ``in_memory``, the sha256 of the
    pairs' ``h_ba``, ``patch_a`` and ``patch_b`` arrays; None where the TFRecords are not there
    (an evaluation is then taken for these pairs: :func:`cached`)."""
    if run.in_memory:
        pairs = run.test_pairs()
        digest = hashlib.sha256()
        for name in ("h_ba", "patch_a", "patch_b"):
            digest.update(json.dumps([name, str(pairs[name].dtype), pairs[name].shape]).encode())
            digest.update(pairs[name].tobytes())
        return digest.hexdigest()
    from stnh_tf.data.tfrecords import split_digest

    return split_digest(run.data_dir(1), "test")  # (None where not made: nothing is made here)


def key(model_dirs, pairs: str | None) -> dict:
    """:data:`CACHE_KEY`'s value for an evaluation of ``model_dirs`` (run folders or model
    files) on the test pairs of digest ``pairs`` (:func:`pairs_digest`)."""
    from stnh_tf.paths import file_sha256
    from stnh_tf.training import run_dir

    models = []
    for d in model_dirs:
        path = os.path.join(d, run_dir.FINAL_MODEL) if os.path.isdir(d) else d
        models.append(file_sha256(path) if os.path.isfile(path) else None)
    return {"models": models, "pairs": pairs}


def cached(path: str, wanted: dict, model_dirs) -> dict | None:
    """The evaluation at ``path`` where it was measured on ``wanted`` (:func:`key`): the same
    pairs, and the same model files where they are still there (a model removed once evaluated,
    as HomographyNet's, keeps its evaluation); else None. One that records no key is kept while
    it is newer than every model file of ``model_dirs`` still there."""
    from stnh_tf.training import run_dir

    if not os.path.exists(path):
        return None
    with open(path) as f:
        doc = json.load(f)
    if CACHE_KEY in doc:
        had = doc[CACHE_KEY]
        same = ((wanted["pairs"] is None or had.get("pairs") == wanted["pairs"])
                and len(had.get("models", [])) == len(wanted["models"])
                and all(w is None or w == h for w, h in zip(wanted["models"], had["models"])))
        return doc if same else None
    finals = [os.path.join(d, run_dir.FINAL_MODEL) if os.path.isdir(d) else d for d in model_dirs]
    return doc if all(os.path.getmtime(f) < os.path.getmtime(path)
                      for f in finals if os.path.exists(f)) else None


def check_pairs_kind(result: dict, path: str, in_memory: bool) -> dict:
    """``result``, an evaluation read from ``path``, after checking it was made on the pairs of
    the kind a reproduction uses: made in memory (``in_memory``) or read from TFRecords.

    Raises:
      ValueError: naming ``path`` and the two kinds.
    """
    if bool(result.get("in_memory")) != bool(in_memory):
        kinds = ("pairs made in memory", "TFRecords")
        made, wanted = (kinds[0], kinds[1]) if result.get("in_memory") else (kinds[1], kinds[0])
        raise ValueError(f"{path} is an evaluation on {made}; this reproduction evaluates on "
                         f"{wanted}: give it an output folder of its own.")
    return result
