"""What a folder or a model file says it is: a training run's folder (:func:`holds_run`), a model
of which hierarchical stage (:func:`trained_stage`). Read from the files
:mod:`stnh_tf.training.run_dir` and :mod:`stnh_tf.training.chunks` write; nothing is written."""

from __future__ import annotations

import os

from stnh_tf.paths import read_json, stage_record_path
from stnh_tf.training.run_dir import (CHECKPOINT_DIR, CONFIG_FILE, FINAL_MODEL,
                                      STAGE_RECORD_FORMAT, read_run_config)


def holds_run(folder) -> bool:
    """Whether ``folder`` holds a training run: its ``config.json`` is a run's
    (:func:`read_run_config`), or, where that file is unreadable, it has a run's
    ``checkpoint/`` beside it (a run whose configuration was damaged is still a run)."""
    config_path = os.path.join(os.fspath(folder), CONFIG_FILE)
    if not os.path.isfile(config_path):
        return False
    try:
        read_run_config(config_path)
    except (ValueError, OSError):
        return os.path.isdir(os.path.join(os.fspath(folder), CHECKPOINT_DIR))
    return True


def trained_stage(model) -> tuple[int, str] | None:
    """``(stage, record)``: the hierarchical stage the model ``model`` was trained as, and the
    file that says so: the ``config.json`` of a run folder (``model`` the folder or its
    ``model.keras``), or the record ``<name>.json`` beside a model file ``<name>.keras``
    (:func:`stnh_tf.paths.stage_record_path`): a chunked run's stage record
    (:data:`STAGE_RECORD_FORMAT`) or a run's configuration. ``None`` where no such file says it
    (a ``.keras`` file alone, a folder or file beside a JSON file of another kind).
    """
    model = os.fspath(model)
    folder = model if os.path.isdir(model) else (
        os.path.dirname(model) if os.path.basename(model) == FINAL_MODEL else None)
    if folder is not None and os.path.isfile(os.path.join(folder, CONFIG_FILE)):
        record = os.path.join(folder, CONFIG_FILE)
    elif os.path.isfile(model) and os.path.isfile(stage_record_path(model)):
        record = stage_record_path(model)
    else:
        return None
    try:
        doc = read_json(record, "model record")
        if not isinstance(doc, dict) or doc.get("format") != STAGE_RECORD_FORMAT:
            doc = read_run_config(record)
    except ValueError:  # not valid JSON, or not a run's configuration
        return None
    stage = doc.get("stage", 1)
    return (stage, record) if isinstance(stage, int) and not isinstance(stage, bool) else None


def data_model_sha256(model) -> str | None:
    """The sha256 of the stage-(k-1) model the training pairs of the model ``model`` were made
    with: its run's ``config.json`` (:func:`trained_stage`'s record) names its ``data_dir``,
    whose train split records ``model_sha256`` (:func:`stnh_tf.data.stage_k.made_from`).
    ``None`` where any of these is not recorded or no longer there (stage-1 pairs included)."""
    from stnh_tf.data import metadata

    found = trained_stage(model)
    try:
        config = read_json(found[1], "model record") if found else None
        data_dir = config.get("data_dir") if isinstance(config, dict) else None
        if not isinstance(data_dir, str) or not os.path.isdir(data_dir):
            return None
        train = metadata.read_metadata_file(data_dir).get("splits", {}).get("train", {})
    except ValueError:
        return None
    digest = train.get("model_sha256") if isinstance(train, dict) else None
    return digest if isinstance(digest, str) else None
