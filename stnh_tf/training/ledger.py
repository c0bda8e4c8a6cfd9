"""The ledger of a chunked run's repository folder ``root`` (``root/ledger.json``): one row per
chunk (part, steps, machine, steps/s, date, the photographs: :func:`photographs`), read and
checked before a chunk trains, the rows a part's checkpoint is made of (:func:`chain`), and its
Markdown table in the docs.

A row holds :data:`LEDGER_FIELDS`; a part other than a hierarchical stage carries ``"part"``
(:func:`part_name`); a chunk stopped by an error carries ``"error"`` (its checkpoint committed
all the same: :func:`stnh_tf.training.chunks.run_chunk`).

    >>> rows = [{"stage": 1, "from_step": 0, "to_step": 1399}, {"stage": 1, "from_step": 0,
    ...         "to_step": 2322}, {"stage": 1, "from_step": 2322, "to_step": 4763}]
    >>> [(r["from_step"], r["to_step"]) for r in chain(rows, "stage1")]
    [(0, 2322), (2322, 4763)]
    >>> ledger_table([{"stage": 1, "from_step": 0, "to_step": 500, "device": "2-core CPU",
    ...                "backend": "tensorflow", "steps_per_s": 1.52, "wall_s": 400.0,
    ...                "date": "2026-11-27"}]).splitlines()[2]
    '| 1 | 0 -> 500 | 2-core CPU | tensorflow | 1.52 | 7 | 2026-11-27 |'
"""

from __future__ import annotations

import hashlib
import os
import re

from stnh_tf.paths import (atomic_write_json, atomic_write_text, document_text, read_document,
                           read_json)

LEDGER_FILE = "ledger.json"
LEDGER_START = "<!-- ledger:start -->"
LEDGER_END = "<!-- ledger:end -->"
PENDING_FILE = "ledger.pending.json"
"""Rows of chunks that ended while the ledger did not read (:func:`add_ledger_row`)."""


def part_name(part: int | str) -> str:
    """The name of a chunked run under ``root``: ``stage<k>`` for hierarchical stage ``k`` (an
    int), else the part's own name (lower-case letters, digits, ``_``, ``-`` and ``.``).

    >>> part_name(2), part_name("sequence2")
    ('stage2', 'sequence2')

    Raises:
      ValueError: an empty name or one with other characters (it names files and folders).
    """
    if isinstance(part, int) and not isinstance(part, bool):
        return f"stage{part}"
    if not isinstance(part, str) or not re.fullmatch(r"[a-z0-9][a-z0-9_.-]*", part):
        raise ValueError(f"a part is a stage number or a name of lower-case letters, digits, "
                         f"'_', '-' and '.'; received {part!r}.")
    return part


def row_part(row: dict) -> str:
    """The :func:`part_name` of a ledger row (its ``"part"``, else its stage's)."""
    return row.get("part") or part_name(row["stage"])


LEDGER_FIELDS = ("stage", "from_step", "to_step", "device", "backend", "steps_per_s", "wall_s",
                 "date")
"""What every ledger row holds (:func:`ledger_table` shows them,
:func:`stnh_tf.training.part_records.stage_record` sums them)."""


def read_ledger(root: str) -> list:
    """``root``'s ledger, a list of rows (``[]`` where it has none yet).

    Raises:
      ValueError: naming the file, where it is not valid JSON, not a list of JSON objects, or a
        row lacks one of :data:`LEDGER_FIELDS` or holds no number where a step, a stage, a rate
        or a time is.
    """
    path = os.path.join(root, LEDGER_FILE)
    if not os.path.exists(path):
        return []
    ledger = read_json(path, "ledger")
    if not isinstance(ledger, list):
        raise ValueError(f"ledger {path!r} holds a JSON {type(ledger).__name__}, not a list of "
                         "rows.")
    for i, row in enumerate(ledger):
        missing = [k for k in LEDGER_FIELDS if not isinstance(row, dict) or k not in row]
        if missing:
            raise ValueError(f"ledger {path!r}: its row {i} is not a chunk's row (it lacks "
                             f"{missing}).")
        wrong = [k for k in ("stage", "from_step", "to_step", "steps_per_s", "wall_s")
                 if isinstance(row[k], bool) or not isinstance(row[k], (int, float))
                 or (k in ("stage", "from_step", "to_step") and not isinstance(row[k], int))]
        if wrong:  # (a hand edit or a merge: a bare TypeError later, in the table or a check)
            raise ValueError(f"ledger {path!r}: its row {i} holds no number in {wrong}.")
    return ledger


def add_ledger_row(root: str, row: dict) -> list:
    """Append ``row`` to ``root``'s ledger (:func:`read_ledger`); returns the ledger.

    Raises:
      ValueError: the ledger does not read (changed while the chunk ran: a merge, an edit); the
        row is then kept in ``root/ledger.pending.json`` (:data:`PENDING_FILE`), which
        :func:`add_pending_rows` adds once the ledger reads again.
    """
    try:
        ledger = read_ledger(root)
    except ValueError as e:
        raise ValueError(f"{e} {keep_pending(root, row)}") from None
    ledger.append(row)
    atomic_write_json(os.path.join(root, LEDGER_FILE), ledger)
    return ledger


def keep_pending(root: str, row: dict) -> str:
    """Append ``row`` to ``root/``:data:`PENDING_FILE` (the rows :func:`add_pending_rows` adds
    to the ledger); returns the sentence that says so."""
    pending = os.path.join(root, PENDING_FILE)
    atomic_write_json(pending, [*_pending(pending), row])
    return (f"The chunk's row is kept in {pending}: mend the ledger (git checkout) and the next "
            "chunk adds it.")


def _pending(path: str) -> list:
    """The rows kept in the pending file ``path`` (``[]`` where there is none); ``ValueError``
    naming it where it is not a list of JSON objects."""
    rows = read_json(path, "pending ledger rows") if os.path.exists(path) else []
    if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
        raise ValueError(f"{path} is not a list of ledger rows: mend it (the rows the ledger did "
                         "not take) or move it away.")
    return rows


def add_pending_rows(root: str) -> int:
    """Add the rows :func:`add_ledger_row` kept in :data:`PENDING_FILE` to ``root``'s ledger
    (those it does not hold already), then remove the file; returns how many were added.
    Raises ``ValueError`` as :func:`read_ledger`."""
    pending = os.path.join(root, PENDING_FILE)
    if not os.path.exists(pending):
        return 0
    ledger = read_ledger(root)
    rows = [r for r in _pending(pending) if r not in ledger]
    atomic_write_json(os.path.join(root, LEDGER_FILE), [*ledger, *rows])
    os.remove(pending)
    return len(rows)


def ledger_table(ledger: list) -> str:
    """The ledger as a Markdown table (stage, steps, machine, backend, steps/s, minutes, date;
    a part other than a hierarchical stage shows its name in the stage column)."""
    lines = ["| stage | steps | machine | backend | steps/s | minutes | date |",
             "|---|---|---|---|---|---|---|"]
    for r in ledger:
        lines.append(f"| {r.get('part', r['stage'])} | {r['from_step']} -> {r['to_step']} | "
                     f"{r['device']} | "
                     f"{r['backend']} | {r['steps_per_s']:.2f} | {r['wall_s'] / 60:.0f} | "
                     f"{r['date']} |")
    return "\n".join(lines)


def write_ledger_table(root: str, doc: str) -> bool:
    """Rewrite the block between :data:`LEDGER_START` and :data:`LEDGER_END` in the Markdown file
    ``doc`` with :func:`ledger_table` of ``root``'s ledger. Returns whether it changed.

    Raises:
      ValueError: ``doc`` lacks the markers or holds them more than once.
    """
    ledger = read_ledger(root)
    text, newline = read_document(doc)  # (the rest written back as read)
    if text.count(LEDGER_START) != 1 or text.count(LEDGER_END) != 1:
        raise ValueError(f"{doc} must hold one {LEDGER_START} ... {LEDGER_END} block.")
    head, rest = text.split(LEDGER_START, 1)
    _, tail = rest.split(LEDGER_END, 1)
    new = f"{head}{LEDGER_START}\n{ledger_table(ledger)}\n{LEDGER_END}{tail}"
    if new != text:
        atomic_write_text(doc, document_text(new, newline))
    return new != text


def chain(rows: list, part: str) -> list:
    """The rows of ``part`` (a :func:`part_name`) whose chunks its newest checkpoint is made of,
    in order: its last row, and back from it each time the latest earlier row that ended at or
    before the step the later one started from (before it: a chunk that ended without its row),
    to a row from step 0. The rest of the part's rows are superseded: a chunk whose checkpoint
    was lost (never committed), trained again from an earlier step."""
    mine = [r for r in rows if row_part(r) == part]
    if not mine:
        return []
    kept, end = [mine[-1]], len(mine) - 1
    while kept[0]["from_step"] > 0:
        earlier = [i for i in range(end) if mine[i]["to_step"] <= kept[0]["from_step"]]
        if not earlier:
            break
        end = earlier[-1]
        kept.insert(0, mine[end])
    return kept


def recorded_step(rows: list, part: str) -> int | None:
    """The step the ledger last recorded for ``part`` (its last row's ``to_step``; ``None``:
    no row, or a last row that finished the part, which is then trained anew): where the
    part's next chunk must start."""
    mine = [r for r in rows if row_part(r) == part]
    return mine[-1]["to_step"] if mine and not mine[-1].get("done") else None


def photographs(cfg) -> dict | None:
    """What identifies the photographs a run of ``cfg`` (a
    :class:`~stnh_tf.training.config.TrainConfig`) trains and validates on, wherever their
    folders are: ``{"train": ..., "val": ...}``, each ``{"count": N, "sha256": ...}`` over the
    image ids and sizes of :func:`stnh_tf.data.sources.scan_image_folders`' listing (relative to
    the folders given); ``None`` for a run without ``image_dir`` (TFRecords), or where the
    training folders cannot be listed here (the run's own check then names it); no ``"val"``
    where there are no validation folders or they cannot be listed."""
    if not cfg.image_dir:
        return None
    out = {}
    for key, folders, most in (("train", cfg.image_dir, cfg.max_images),
                               ("val", cfg.val_image_dir, 0)):
        if not folders:
            continue
        out[key] = listing_digest(folders, most)
        if out[key] is None:
            if key == "train":
                return None
            del out[key]
    return out


def listing_digest(folders, most: int = 0) -> dict | None:
    """``{"count": N, "sha256": ...}`` over the image ids and sizes of
    :func:`stnh_tf.data.sources.scan_image_folders`' listing of ``folders`` (its first ``most``;
    0: all), the same wherever the folders are; ``None`` where they cannot be listed here."""
    from stnh_tf.data import sources

    try:
        listing = sources.scan_image_folders(folders, most)
        digest = hashlib.sha256("".join(
            f"{listing.image_id(p)}\t{os.path.getsize(p)}\n" for p in listing.files).encode())
    except (OSError, ValueError):  # (SourceError is a ValueError)
        return None
    return {"count": len(listing.files), "sha256": digest.hexdigest()}


def check_photographs(recorded, seen, part, cfg, printer=print) -> None:
    """Refuse a chunk of ``part`` on other training photographs than its last chunk's: ``seen``
    (:func:`photographs` of ``cfg``) against the last of ``recorded`` (the part's rows'
    ``"photographs"``, in order; ``None`` for rows before they were recorded). Other validation
    photographs only monitor: said through ``printer``, the chunk goes on.

    Raises:
      ValueError: in one line naming ``cfg.image_dir`` and both records; nothing was trained.

    >>> same = {"train": {"count": 3, "sha256": "a"}, "val": {"count": 2, "sha256": "b"}}
    >>> check_photographs([None, same], same, "stage1", None)  # nothing said, nothing raised
    """
    earlier = [r for r in recorded if r]
    if not seen or not earlier:
        return
    if earlier[-1].get("train") != seen.get("train"):
        raise ValueError(
            f"the photographs of {cfg.image_dir!r} are not those the last chunk of {part} "
            f"trained on ({seen.get('train')} here, {earlier[-1].get('train')} in the ledger): "
            "nothing was trained; point --image_dir at the same photographs (their pairs would "
            "come in another order).")
    if earlier[-1].get("val") != seen.get("val"):
        here = repr(cfg.val_image_dir) if seen.get("val") else "none (or not listed)"
        printer(f"the validation photographs here, {here}, are not those of the last chunk of "
                f"{part} ({seen.get('val')} here, {earlier[-1].get('val')} in the ledger): "
                "training goes on; its validation numbers are on another set from here")
