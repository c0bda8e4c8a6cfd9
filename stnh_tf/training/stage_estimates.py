"""The finished stages' estimates of an in-memory stage-k run's pairs, kept in its run folder
per split (:data:`stnh_tf.training.run_dir.ESTIMATES_FILES`), so that a resumed chunk does not
estimate them again (:func:`stnh_tf.training.streams.stage_pairs`)."""

from __future__ import annotations

import json
import os
import zipfile

import numpy as np

from stnh_tf.paths import fsync_replace
from stnh_tf.training.run_dir import ESTIMATES_FILES


def save_estimates(model_dir: str, split: str, key: str, h_prev: np.ndarray,
                   rejected: dict) -> str:
    """Keep the finished stages' estimates of a stage-k run's in-memory pairs of ``split`` in
    ``model_dir`` (``h_prev [N, 3, 3]`` as float32, the degenerate-rule counts, and ``key``, what
    they are the estimates of), written through a temporary file. Returns the path."""
    path = os.path.join(model_dir, ESTIMATES_FILES[split])
    tmp = f"{path}.tmp-{os.getpid()}.npz"
    np.savez_compressed(tmp, h_prev=np.asarray(h_prev, np.float32), key=np.array(key),
                        rejected=np.array(json.dumps(rejected, sort_keys=True)))
    fsync_replace(tmp, path)
    return path


def saved_estimates_key(model_dir: str, split: str):
    """The ``key`` of the estimates :func:`save_estimates` kept for ``split`` in ``model_dir``
    (what pairs and stages they are of), or ``None`` where there are none or they are
    unreadable."""
    try:
        with np.load(os.path.join(model_dir, ESTIMATES_FILES[split])) as saved:
            return str(saved["key"])
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
        return None


def load_estimates(model_dir: str, split: str, key: str):
    """``(h_prev, rejected)`` saved by :func:`save_estimates` for ``split`` under the same
    ``key``; ``None`` where there are none, they are unreadable, or they are of other pairs or
    stages (another key)."""
    path = os.path.join(model_dir, ESTIMATES_FILES[split])
    try:
        with np.load(path) as saved:
            if str(saved["key"]) != key:
                return None
            return saved["h_prev"].astype(np.float64), json.loads(str(saved["rejected"]))
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
        return None
