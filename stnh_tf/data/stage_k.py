"""Stage-k dataset generation for hierarchical STN-Homography (paper section 4), as a library.

``python -m data_prep.make_stage_dataset`` is the command-line wrapper around
:func:`make_stage_dataset`. From a stage-(k-1) dataset and the trained stage-(k-1) model:

1. the model predicts ``H_{k-1}`` on every stored pair (patch_a_{k-1}, patch_b), in read order
   and fixed batches (deterministic);
2. the estimate so far becomes ``H_prev_k = H_prev_{k-1} @ H_{k-1}``, subject to the
   degenerate-prediction rule of :mod:`stnh_tf.hierarchy` (non-finite or near-singular: the
   prediction is replaced by the identity; corners leaving the stored context: clipped onto its
   border and ``H`` refitted). Each case is counted by reason in ``metadata.json``; no sample is
   dropped;
3. ``patch_a_k(p) = patch_a(H_prev_k @ p)`` is re-cropped from the stored context with OpenCV
   (image content beyond the patch border, as the paper's hierarchy sees it);
4. the residual target ``H_k* = inv(H_prev_k) @ H_ba`` gives ``h_bar`` (normalized with the
   paper's ``M``), and ``patch_a_t_k = patch_a_k`` warped by ``H_k*`` (zero outside patch_a_k:
   what the stage's spatial transformer sees, so the L1 target matches it);
5. ``h_ba``, ``context_a``, ``square_xy``, ``image_id``, ``index`` and ``h_mask`` are kept.

The model runs in the parent process; the re-cropping runs in the writer's worker processes
(NumPy/OpenCV only). Sharding, atomic writes, metadata and progress are those of
:mod:`stnh_tf.data.writer` and :mod:`stnh_tf.data.metadata`, shared with the stage-1 generator.
"""

from __future__ import annotations

import collections
import os
import shlex
import sys

import numpy as np

from stnh_tf.data import metadata, writer
from stnh_tf import hierarchy, pixels
from stnh_tf.data import features
from stnh_tf.paths import check_output_dir

READ_BATCH = 256
"""Pairs per model call (fixed, so predictions do not depend on anything but the data)."""


def stage_sample(item: writer.WorkItem) -> list:
    """Worker: one stage-(k-1) record + the accepted composed estimate -> the stage-k sample.

    ``item.payload = (record_bytes, h_prev_k [3, 3] float64)``.
    """
    record, h_prev = item.payload
    s = features.decode_example(record)
    h_ba = np.asarray(s["h_ba"], np.float64).reshape(3, 3)
    pair = hierarchy.stage_pair(s["context_a"], h_ba, h_prev)
    return [{**s, **pair, "h_prev": h_prev.reshape(9).astype(np.float32)}]


def _records(paths):
    """Serialized records of the shards, in shard order then file order (no shuffling); a
    corrupted shard raises ``ShardError`` naming it."""
    from stnh_tf.data.tfrecords import _iter_records

    for path in paths:
        for record in _iter_records(path):
            yield record.numpy()


def made_from(input_dir: str, model_dir, split: str | None = None) -> dict:
    """What a stage-k split records of the stage-(k-1) dataset and model it is made from:
    ``input_dir`` and ``model_dir`` as absolute paths, the input's ``input_sha256`` (its train
    split, the dataset's identity: :func:`stnh_tf.data.tfrecords.split_digest`), with ``split``
    that split's own ``input_split_sha256`` (the pairs it is made from), and the model file's
    ``model_sha256`` (a folder's ``model.keras``); None where there is no such split or file."""
    from stnh_tf.data.tfrecords import split_digest
    from stnh_tf.paths import file_sha256

    model_file = os.path.join(model_dir, "model.keras") if os.path.isdir(model_dir) else model_dir
    return {"input_dir": os.path.abspath(input_dir), "model_dir": os.path.abspath(model_dir),
            "input_sha256": split_digest(input_dir, "train"),
            **({"input_split_sha256": split_digest(input_dir, split)} if split else {}),
            "model_sha256": file_sha256(model_file) if os.path.isfile(model_file) else None}


def _same_source(section: dict, source: dict) -> bool:
    """Whether a split's ``section`` was made from ``source`` (:func:`made_from`): the same
    input dataset and model, each by its digest where both record one (wherever the folders lie
    now: a folder moved is the same), else by its path."""
    def same(name):
        digest = f"{name}_sha256"
        if section.get(digest) and source.get(digest):
            return section[digest] == source[digest]
        paths = [section.get(f"{name}_dir"), source[f"{name}_dir"]]
        return len({os.path.realpath(p) if isinstance(p, str) else p for p in paths}) == 1

    return (same("input") and same("model")
            and ("input_split_sha256" not in source  # the split's own pairs, where asked and
                 or "input_split_sha256" not in section  # recorded (splits made before it:
                 or section["input_split_sha256"] == source["input_split_sha256"]))  # as then)


def check_one_source(output_dir: str, splits, source: dict) -> list:
    """The splits of ``splits`` that ``output_dir`` holds complete and made from ``source``
    (:func:`made_from`): those a re-run of the same command can skip. The splits of
    ``output_dir`` that ``splits`` leaves out (complete, or being written) must come from
    ``source`` too: one stage-k dataset holds the pairs of one stage-(k-1) dataset and model, or
    its test pairs would not be those of the model it trains.

    Raises:
      ValueError: naming a split of ``output_dir`` made from another dataset or model.
    """
    from stnh_tf.data.tfrecords import split_digest

    meta = metadata.read_metadata_file(output_dir) if os.path.isdir(output_dir) else {}
    done = []
    for name, section in meta.get("splits", {}).items():
        if "input_dir" not in section:
            continue  # (an incomplete section of a version that did not record it)
        same = _same_source(section, source)
        if name in splits:  # kept only where made from the input split as it is now
            own = {**source, "input_split_sha256": split_digest(source["input_dir"], name)}
            if _same_source(section, own) and section.get("status") == "complete":
                done.append(name)
        elif not same:
            raise ValueError(
                f"{output_dir} holds a {name!r} split made from {section.get('input_dir')} and "
                f"the model {section.get('model_dir')}, not from {source['input_dir']} and "
                f"{source['model_dir']}: every split of one stage-k dataset comes from one "
                f"dataset and model; make {name!r} again too (--splits with it, --overwrite), or "
                "write to another --output_dir.")
    return [s for s in splits if s in done]


def _items(paths, predict, counts: dict):
    """WorkItems in read order; runs ``predict`` on batches of :data:`READ_BATCH` records and
    applies the degenerate-prediction rule (counting rejections into ``counts``)."""
    batch = []
    index = 0

    def flush():
        nonlocal index
        decoded = [features.decode_example(r, names=("patch_a", "patch_b", "h_prev"))
                   for r in batch]
        patch_a = pixels.to_unit(np.stack([d["patch_a"] for d in decoded])[..., None])
        patch_b = pixels.to_unit(np.stack([d["patch_b"] for d in decoded])[..., None])
        h_prev = np.stack([np.asarray(d["h_prev"], np.float64).reshape(3, 3) for d in decoded])
        h_stage = predict(patch_a, patch_b)
        h_new, reasons = hierarchy.accept_or_reject(h_prev, h_stage)
        for r in reasons:
            counts[r or "accepted"] += 1
        out = [writer.WorkItem(index + i, f"record {index + i}", (rec, h))
               for i, (rec, h) in enumerate(zip(batch, h_new))]
        index += len(batch)
        batch.clear()
        return out

    for record in _records(paths):
        batch.append(record)
        if len(batch) == READ_BATCH:
            yield from flush()
    if batch:
        yield from flush()


def default_splits(input_dir: str) -> list:
    """The splits ``make_stage_dataset`` builds unless told: train and test, and the ``val``
    split (:mod:`stnh_tf.data.holdout`) where ``input_dir`` holds it complete."""
    from stnh_tf.data import holdout
    from stnh_tf.data import tfrecords as data

    return ["train", *([holdout.VAL_SPLIT] if data.has_split(input_dir, holdout.VAL_SPLIT)
                       else []), "test"]


def check_made(output_dir: str, split: str, input_dir: str, model_dir: str) -> None:
    """Refuse the complete ``split`` of ``output_dir`` where it was not made from ``input_dir``
    and ``model_dir`` (:func:`made_from`; a run that reuses the pairs it made would otherwise
    take those of an earlier model for its own).

    Raises:
      ValueError: naming the split, what it was made from and what is asked.
    """
    from stnh_tf.data import tfrecords as data

    section, source = data.split_info(output_dir, split), made_from(input_dir, model_dir, split)
    if not _same_source(section, source):
        if _same_source(section, {k: v for k, v in source.items() if k != "input_split_sha256"}):
            raise ValueError(f"{output_dir} holds the {split!r} pairs made from another "
                             f"{split!r} split of {source['input_dir']} than the one there now "
                             "(or from one it did not record): move it aside to make them again.")
        raise ValueError(f"{output_dir} holds the {split!r} pairs made from "
                         f"{section.get('input_dir')} and the model {section.get('model_dir')}, "
                         f"not from {source['input_dir']} and {source['model_dir']}: move it "
                         "aside to make them again.")


def check_stage_arguments(stage: int, input_dir: str, output_dir: str, splits, *,
                          num_shards: int = 0, model_dir=None) -> list:
    """Check what :func:`make_stage_dataset` is given, before any model is loaded or folder
    made: ``stage >= 2``; ``num_shards`` an integer >= 0; ``splits`` (a list of names) not empty,
    without repeats, each a plain name present and complete in ``input_dir``, which holds
    stage-(k-1) data; ``output_dir`` another folder, and one whose ``metadata.json``, if any, is a
    dataset's (:func:`stnh_tf.data.metadata.read_metadata_file`), and (given ``model_dir``)
    whose other splits come from the same input and model (:func:`check_one_source`). Returns
    the splits as a list.

    Raises:
      ValueError: naming the argument (``--stage``, ``--num_shards``, ``--splits``...) or file.
      FileNotFoundError: ``input_dir`` holds no dataset.
    """
    from stnh_tf.data import tfrecords as data

    if isinstance(stage, bool) or not isinstance(stage, int) or stage < 2:
        raise ValueError(f"--stage must be >= 2, an integer (stage 1 is data_prep.make_dataset); "
                         f"received {stage!r}.")
    if isinstance(num_shards, bool) or not isinstance(num_shards, int) or num_shards < 0:
        raise ValueError(f"--num_shards must be an integer >= 0 (0: as many as the input split "
                         f"has); received {num_shards!r}.")
    splits = [splits] if isinstance(splits, str) else list(splits)
    if not splits:
        raise ValueError("--splits names no split; give one or more, e.g. --splits=train,test.")
    repeated = sorted({s for s in splits if splits.count(s) > 1})
    if repeated:
        raise ValueError(f"--splits names {repeated} more than once; received {splits}.")
    for split in splits:
        metadata.check_split_name(split)
    meta = data.read_metadata(input_dir)
    if int(meta.get("stage", 1)) != stage - 1:
        raise ValueError(f"{input_dir} holds stage-{meta.get('stage', 1)} data; stage {stage} is "
                         f"built from stage-{stage - 1} data.")
    for split in splits:
        data.split_info(input_dir, split)
    if os.path.abspath(input_dir) == os.path.abspath(output_dir):
        raise ValueError("output_dir must differ from input_dir.")
    if os.path.isdir(output_dir):
        metadata.read_metadata_file(output_dir)
    if model_dir is not None:
        check_one_source(output_dir, splits, made_from(input_dir, model_dir))
    return splits


def make_stage_dataset(stage: int, input_dir: str, output_dir: str, split: str, *,
                       model_dir: str | None = None, predict=None, num_shards: int = 0,
                       num_workers: int = 1, log=print, command=None,
                       overwrite: bool = False, writing=None) -> dict:
    """Write the stage-``stage`` ``split`` from the stage-(k-1) data and model. Returns the split's
    metadata section (``degenerate_predictions`` counts by reason).

    Every argument is checked (:func:`check_stage_arguments`) before the model is loaded or
    ``output_dir`` is made; a model that fails to load leaves no new ``output_dir`` behind.

    Args:
      model_dir: the trained stage-(k-1) model; or
      predict: ``predict(patch_a [N,S,S,1], patch_b [N,S,S,1]) -> pixel H [N,3,3]`` (float
        patches in [0, 1]; e.g. an oracle in tests).
      writing: every split the caller writes with this input and model (``split`` among them;
        default ``[split]``): the folder's other splits must come from them
        (:func:`check_one_source`), these may be made again one after another.
    Raises:
      ValueError: ``stage < 2``, a bad ``num_shards`` or split name, the input is not stage
        ``k-1`` data, or the split is missing.
      FileNotFoundError: no model in ``model_dir``.
    """
    from stnh_tf.data import tfrecords as data
    from stnh_tf.modeling import runner

    if (model_dir is None) == (predict is None):
        raise ValueError("give exactly one of model_dir and predict.")
    check_stage_arguments(stage, input_dir, output_dir, list(writing or [split]),
                          num_shards=num_shards, model_dir=model_dir)
    info = data.split_info(input_dir, split)
    paths = data.shard_paths(input_dir, split, "size")
    made_dir = not os.path.exists(output_dir)
    output_dir = check_output_dir(output_dir)
    if predict is None:
        try:
            predict = runner.predictor(runner.load_model(model_dir), batch_size=READ_BATCH)
        except BaseException:
            if made_dir and not os.listdir(output_dir):
                os.rmdir(output_dir)
            raise
    counts = collections.Counter()
    split_metadata = {
        "source": "stage",
        **(made_from(input_dir, model_dir, split) if model_dir else
           {"input_dir": os.path.abspath(input_dir), "model_dir": repr(predict)}),
        "input_seed": info.get("seed"),
        "protocol": info.get("protocol"),
        "degenerate_rule": "non-finite or near-singular (|det| < 1e-6, or w <= 0 at a corner) "
                           "composition: prediction replaced by identity (estimate so far kept); "
                           "a patch corner mapped outside the stored context: corners clipped onto "
                           "the context border and H refitted (stnh_tf.hierarchy)",
        "command": command or " ".join(shlex.quote(a) for a in getattr(sys, "orig_argv", sys.argv)),
    }
    return writer.write_sharded(
        output_dir, split, _items(paths, predict, counts), stage_sample,
        num_shards=num_shards or len(paths), num_items=int(info["num_samples"]),
        num_workers=num_workers, split_metadata=split_metadata, top_metadata={"stage": stage},
        log=log, overwrite=overwrite, final_metadata=lambda: {"degenerate_predictions": {
            k: int(counts.get(k, 0)) for k in ("accepted", *hierarchy.REJECT_REASONS)}})
