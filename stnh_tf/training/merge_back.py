"""What a chunk on another machine sends back (``experiments/paper_schedule_gpu.sh``'s archives,
unpacked into a folder of their own), merged into this repository's ``paper_schedule/``
without losing what was committed here meanwhile: a returned checkpoint replaces a part's
committed one only where it is of a later step or the same; the ledger gets the returned rows
it lacks (those of a checkpoint not taken placed off the kept checkpoint's chain), and keeps
its own; a finished part's model and record come in where they are not here
(a different one here is refused). Untarring the archives over the repository, as the runbook
said before, put an older checkpoint back over a CPU chunk's newer one and dropped that chunk's
ledger row.

  python -m experiments.paper_schedule --merge_back=/tmp/back
"""

from __future__ import annotations

import json
import os
import shutil

from stnh_tf.paths import atomic_copy, atomic_write_json, file_sha256
from stnh_tf.training.ledger import (LEDGER_FILE, PENDING_FILE, keep_pending, read_ledger,
                                     row_part)
from stnh_tf.training.part_records import RESUME_DIR


def _step(resume: str) -> int:
    from stnh_tf.training.chunks import _committed_step

    return _committed_step(resume) if os.path.isdir(resume) else -1


def _rows(folder: str, name: str) -> list:
    path = os.path.join(folder, name)
    if not os.path.exists(path):
        return []
    if name == LEDGER_FILE:
        return read_ledger(folder)
    with open(path, encoding="utf-8") as f:
        rows = json.load(f)
    if not isinstance(rows, list):
        raise ValueError(f"{path} is not a list of ledger rows.")
    return rows


def _dead_branch_place(ledger: list, row: dict) -> int:
    """Where a returned ``row`` of a part whose checkpoint here was kept (newer) goes in
    ``ledger``: before this repository's row of the part that goes on from the same step or
    later, so that :func:`~stnh_tf.training.ledger.chain` from the kept checkpoint's last row
    never walks through it and the next chunk resumes from the kept step (appended, it was the
    part's last row: the record credited the discarded chunk and the next chunk its step)."""
    for i, other in enumerate(ledger):
        if row_part(other) == row_part(row) and other["from_step"] >= row["from_step"]:
            return i
    return len(ledger)


def merge_back(root: str, back: str, printer=print) -> dict:
    """Merge ``back`` (a folder holding the returned ``paper_schedule/``) into ``root`` (this
    repository's ``paper_schedule/``). Everything is checked before anything is written.

    Returns:
      ``{"checkpoints": {part: step taken in}, "kept": {part: step kept here}, "rows": n,
      "pending": n, "finished": [files taken in]}``.
    Raises:
      ValueError: ``back`` holds no ``paper_schedule/``, a ledger that does not read, or a
        finished model or record other than the one here of the same name (nothing written).
    """
    returned = os.path.join(back, "paper_schedule")
    if not os.path.isdir(returned):
        raise ValueError(f"{back} holds no paper_schedule/ (unpack the call's archives there).")
    own_rows, back_rows = read_ledger(root), _rows(returned, LEDGER_FILE)
    pending = _rows(returned, PENDING_FILE)
    finished = []
    for name in sorted(os.listdir(returned)):
        if name.endswith((".keras", ".json")) and name not in (LEDGER_FILE, PENDING_FILE):
            here, there = os.path.join(root, name), os.path.join(returned, name)
            if os.path.exists(here) and file_sha256(here) != file_sha256(there):
                raise ValueError(f"{there} differs from {here}: a finished part's model or "
                                 "record is not replaced; nothing merged.")
            if not os.path.exists(here):
                finished.append(name)
    finished.sort(key=lambda name: (name.endswith(".json"), name))  # each model before its record
    out = {"checkpoints": {}, "kept": {}, "rows": 0, "pending": 0, "finished": finished}
    parts = os.path.join(returned, RESUME_DIR)
    for part in sorted(os.listdir(parts)) if os.path.isdir(parts) else ():
        src, dst = os.path.join(parts, part), os.path.join(root, RESUME_DIR, part)
        step, own = _step(src), _step(dst)
        if step < own:
            out["kept"][part] = own
            printer(f"{part}: kept the committed checkpoint of step {own} here (the returned "
                    f"one is of step {step})")
            continue
        tmp = f"{dst}.merging-{os.getpid()}"
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.copytree(src, tmp)
        if os.path.isdir(dst):
            shutil.rmtree(dst)
        os.makedirs(os.path.dirname(dst), exist_ok=True)
        os.replace(tmp, dst)
        out["checkpoints"][part] = step
    for name in finished:  # the record after its model (a model without a record: unfinished)
        atomic_copy(os.path.join(returned, name), os.path.join(root, name))
        part = name[:-len(".keras")] if name.endswith(".keras") else None
        if part and not os.path.isdir(os.path.join(parts, part)):  # finished there
            shutil.rmtree(os.path.join(root, RESUME_DIR, part), ignore_errors=True)
    key = lambda row: json.dumps(row, sort_keys=True)  # noqa: E731
    have = {key(r) for r in own_rows}
    new, ledger = [row for row in back_rows if key(row) not in have], list(own_rows)
    for row in new:  # appended; where the returned weights were not taken, off their chain
        ledger.insert(_dead_branch_place(ledger, row) if row_part(row) in out["kept"]
                      else len(ledger), row)
    if new:
        atomic_write_json(os.path.join(root, LEDGER_FILE), ledger)
    out["rows"] = len(new)
    kept = os.path.join(root, PENDING_FILE)
    have |= {key(r) for r in (_rows(root, PENDING_FILE) if os.path.exists(kept) else [])}
    for row in pending:  # (rows the ledger there did not take: the next chunk here adds them)
        if key(row) not in have:
            keep_pending(root, row)
            out["pending"] += 1
    return out
