"""The files of a chunked run's parts in its repository folder (:mod:`stnh_tf.training.chunks`,
whose docstring gives the layout): where a part's committed checkpoint and finished model lie,
the record written beside a finished part, and what a chunk stopped while finishing one left to
the next (its finishing row, its record).
"""

from __future__ import annotations

import os
import shutil

from stnh_tf.paths import atomic_write_json, read_json, stage_record_path
from stnh_tf.training import run_dir
from stnh_tf.training.ledger import (PENDING_FILE, add_pending_rows, chain, part_name,
                                     read_ledger, row_part)

RESUME_DIR = "resume"
"""The folder under a chunked run's root that holds each unfinished part's checkpoint."""


def resume_dir(root: str, part: int | str) -> str:
    """The repository folder of a part's (stage k: ``k``) committed checkpoint."""
    return os.path.join(root, RESUME_DIR, part_name(part))


def finished_model(root: str, part: int | str) -> str:
    """Where a finished part's model is kept (``stage<k>.keras``, ``<part>.keras``)."""
    return os.path.join(root, f"{part_name(part)}.keras")


def stage_record(root: str, part: int | str, config: dict) -> dict:
    """Write and return ``stage<k>.json`` (``<part>.json``) beside the finished part: its run's
    ``config`` (the ``config.json`` fields), the number of training photographs and pairs, the
    ledger rows of the chunks its model is made of (:func:`~stnh_tf.training.ledger.chain`) and
    their totals (steps, wall seconds, machines), and apart (``superseded_chunks``, not summed)
    its rows whose steps were trained again."""
    from stnh_tf.data import sources

    name = part_name(part)
    ledger = read_ledger(root)
    rows = chain(ledger, name)
    superseded = [r for r in ledger if row_part(r) == name and not any(r is c for c in rows)]
    images = len(sources.scan_image_folders(config["image_dir"],
                                            config.get("max_images", 0)).files) \
        if config.get("image_dir") else None
    record = {"format": run_dir.STAGE_RECORD_FORMAT, "stage": config.get("stage", part),
              **({"part": name} if isinstance(part, str) else {}), "config": config,
              "training_photographs": images,
              "training_pairs": images and images * config["samples_per_image"], "chunks": rows,
              **({"superseded_chunks": superseded} if superseded else {}),
              "final_step": max((r["to_step"] for r in rows), default=0),
              "wall_s": round(sum(r["wall_s"] for r in rows), 1),
              "machines": sorted({f"{r['device']} ({r['backend']})" for r in rows})}
    atomic_write_json(stage_record_path(finished_model(root, part)), record)
    return record


def drop_unfinished_rows(root) -> None:
    """Remove from ``root``'s pending rows (:data:`~stnh_tf.training.ledger.PENDING_FILE`) each
    finishing row whose part has no finished model (:func:`finished_model`): a chunk stopped
    while writing it; the chunk that finishes the part writes its own row."""
    pending = os.path.join(root, PENDING_FILE)
    if not os.path.exists(pending):
        return
    rows = read_json(pending, "pending ledger rows")
    kept = [r for r in rows
            if not (r.get("done") and not os.path.exists(finished_model(root, row_part(r))))]
    if len(kept) != len(rows):
        atomic_write_json(pending, kept)


def finish_record(cfg, root, key, printer) -> None:
    """A finished part's record (:func:`stage_record`, with the rows kept while the ledger did
    not read) and ``resume/`` removed, where the chunk that finished it could not: nothing where
    the ledger or the run folder's ``config.json`` does not read."""
    config = os.path.join(cfg.model_dir, run_dir.CONFIG_FILE)
    try:
        add_pending_rows(root)
        rows = chain(read_ledger(root), part_name(key))
        if not rows or not rows[-1].get("done"):
            raise ValueError(f"the ledger holds no row that finished it (its last ends at step "
                             f"{rows[-1]['to_step'] if rows else 0}); {resume_dir(root, key)} "
                             "is kept")
        stage_record(root, key, run_dir.read_run_config(config) if os.path.exists(config)
                     else cfg.to_json())
    except ValueError as e:
        printer(f"the record of the finished {part_name(key)} is not written: {e}")
        return
    shutil.rmtree(resume_dir(root, key), ignore_errors=True)
