"""The ``val`` split: training photographs held out by a hash of each photograph's id, so that a
run can validate (and a researcher choose) on photographs that are neither trained on nor the
test photographs (docs/data.md, "A validation split").

A photograph is held out iff the first 8 bytes of the sha256 of its key (:func:`photograph_key`:
its path relative to its folder, POSIX separators, or a bundled photograph's id), read as a
big-endian integer, are below ``fraction * 2**64``. The choice depends on that key alone: the
same on every machine, whatever the order or number of the folders listed and the photographs
beside it, and a larger fraction holds out a superset of a smaller one's photographs.

``data_prep.make_dataset --split=val --val_fraction=F`` writes the held-out photographs,
``--split=train --val_fraction=F`` the others (each photograph keeping its index in the full
listing, so its pairs are those it has without the hold-out); ``F = 0``, the default, holds
nothing out (the paper's training data). Standard library only.

    >>> [held_out(key, 0.5) for key in ("a.jpg", "b.jpg", "c.jpg", "d.jpg")]
    [True, True, False, True]
"""

from __future__ import annotations

import hashlib
import math
import numbers
import os

VAL_SPLIT = "val"
SPLITS = ("train", VAL_SPLIT)
"""The splits a hold-out divides the photographs between: the kept ones, the held-out ones."""
KEY_RULE = "sha256 of the photograph's path in its folder, first 8 bytes < val_fraction * 2**64"


def photograph_key(image_id: str, several_folders: bool) -> str:
    """The key a photograph is held out by: its ``image_id`` (the id stored with its pairs),
    less the ``<k>:`` folder number of a listing of ``several_folders``
    (:meth:`stnh_tf.data.sources.FolderListing.image_id`), so that the order of the folders
    does not change the choice.

    >>> photograph_key("1:sub/a.jpg", True), photograph_key("1:sub/a.jpg", False)
    ('sub/a.jpg', '1:sub/a.jpg')
    """
    return image_id.split(":", 1)[1] if several_folders else image_id


def held_out(key: str, fraction: float) -> bool:
    """Whether the photograph of ``key`` (:func:`photograph_key`) is in the ``val`` split of a
    hold-out of ``fraction`` of the photographs (module docstring)."""
    digest = hashlib.sha256(key.encode("utf-8")).digest()
    return int.from_bytes(digest[:8], "big") < fraction * 2 ** 64  # (exact: a power of 2)


def check_arguments(split: str, fraction, source: str) -> None:
    """``make_dataset``'s ``val_fraction`` for ``split`` from ``source``: a number in [0, 1);
    above 0 only for :data:`SPLITS` and not for the streamed ``coco2014`` source; above 0 for
    the ``val`` split.

    Raises:
      ValueError: naming ``--val_fraction``, its value and what to give instead.
    """
    if (isinstance(fraction, bool) or not isinstance(fraction, numbers.Real)
            or not math.isfinite(fraction) or not 0 <= fraction < 1):
        raise ValueError(f"--val_fraction must be a number in [0, 1) (0: no val split); "
                         f"received {fraction!r}.")
    if split == VAL_SPLIT and fraction == 0:
        raise ValueError("--split=val writes the photographs held out of the training "
                         "photographs: give --val_fraction > 0 (e.g. 0.05) with the train "
                         "split's --source and --image_dir, and the same --val_fraction to "
                         "--split=train (docs/data.md).")
    if fraction and split not in SPLITS:
        raise ValueError(f"--val_fraction holds photographs of the train split out for the val "
                         f"split; --split={split} keeps all its photographs: leave "
                         "--val_fraction at 0.")
    if fraction and source == "coco2014":
        raise ValueError("--val_fraction needs the whole listing before writing, which the "
                         "streamed --source=coco2014 does not give: use --source=folder with "
                         "the extracted COCO folders (docs/scale.md).")


def select(items: list, key, fraction: float, split: str) -> tuple:
    """``(mine, others)``: the ``items`` of ``split`` (the held-out ones for ``val``, the others
    for ``train``; all of them where ``fraction`` is 0) and how many went to the other split.
    ``key(item)`` is the item's :func:`photograph_key`; the items keep their order and index."""
    if not fraction:
        return list(items), 0
    want = split == VAL_SPLIT
    mine = [item for item in items if held_out(key(item), fraction) == want]
    return mine, len(items) - len(mine)


def split_section(fraction: float, split: str, others: int) -> dict:
    """What a split's ``metadata.json`` section records of its hold-out: ``val_fraction``, the
    key rule, and how many photographs of its listing are in the other split (``held_apart``,
    ``held_apart_in``)."""
    if not fraction:
        return {"val_fraction": 0.0}
    other = SPLITS[1 - SPLITS.index(split)]
    return {"val_fraction": float(fraction), "holdout_key": KEY_RULE, "held_apart": others,
            "held_apart_in": other}


def _photographs(section: dict) -> tuple:
    """What a section says its photographs are drawn from: the source and its folders (in any
    order)."""
    folders = section.get("image_dir")
    return section.get("source"), tuple(sorted(folders.split(","))) if folders else None


def check_beside(meta: dict, split: str, fraction: float, section: dict, where: str) -> None:
    """Before ``split`` (with ``val_fraction`` ``fraction`` and the source fields of
    ``section``) is written into the dataset ``where`` whose ``metadata.json`` is ``meta``:
    where that dataset holds the other split of the hold-out, complete or being written (or
    left incomplete), both are divided with the same fraction from the same photographs, so that
    no photograph is in both. A ``val`` split is refused beside a train split that kept every
    photograph, and a train split that keeps every photograph beside a ``val`` split. The
    writer calls it again under the metadata's lock (``write_sharded``'s ``check``), so that two
    runs writing the two splits at once cannot both pass.

    Raises:
      ValueError: naming both splits, their ``--val_fraction`` and what to give.
    """
    if split not in SPLITS:
        return
    other = SPLITS[1 - SPLITS.index(split)]
    theirs = meta.get("splits", {}).get(other, {})
    if theirs.get("status") != "complete" and "val_fraction" not in theirs:
        return  # (none, or an incomplete one of a version that did not record its flags)
    state = ("" if theirs.get("status") == "complete"
             else " being written or left incomplete (its flags recorded)")
    their_fraction = float(theirs.get("val_fraction", 0.0))
    if their_fraction != fraction:
        raise ValueError(
            f"{where} holds a {other} split{state} written with --val_fraction={their_fraction:g}; "
            f"this {split} split with --val_fraction={fraction:g} would share photographs with "
            f"it: give --val_fraction={their_fraction:g}"
            + (f", or rewrite {other} with the same value (--overwrite)." if fraction else
               " (val holds out a share of the train split's photographs)."))
    if _photographs(theirs) != _photographs(section):
        raise ValueError(
            f"{where} holds a {other} split{state} of other photographs ({theirs.get('source')} "
            f"{theirs.get('image_dir', '')}); the val split is a share of the train split's "
            f"own photographs: give the same --source and --image_dir to both.")


def real_folders(spec) -> list:
    """The real paths, sorted, of the folders a comma-separated ``spec`` names (none for an
    empty one)."""
    return sorted(os.path.realpath(f) for f in spec.split(",")) if spec else []


def _folders(section: dict) -> list:
    """The real paths of the photograph folders a split's section names (none for another
    source)."""
    return real_folders(section.get("image_dir") if section.get("source") == "folder" else None)


def sharing_splits(meta: dict, split: str, section: dict) -> list:
    """The other splits of the dataset whose ``metadata.json`` is ``meta`` that ``split`` (the
    source fields of ``section``) shares photographs with by its folders: one of its photograph
    folders is, holds or lies in one of theirs (a folder's listing takes every folder below it:
    a train split of ``photos`` holds a test split of ``photos/test``), and any two splits of
    the bundled photographs (``source="bundled"``: the same few for every split). The two splits
    of one hold-out share their folders by design and are not counted (:func:`check_beside`).

        >>> meta = {"splits": {"train": {"source": "folder", "image_dir": "/p"}}}
        >>> sharing_splits(meta, "test", {"source": "folder", "image_dir": "/p/test"})
        ['train']
        >>> sharing_splits(meta, "test", {"source": "folder", "image_dir": "/q"})
        []
    """
    mine, out = _folders(section), []
    for other, theirs in sorted(meta.get("splits", {}).items()):
        if other == split or (split in SPLITS and other in SPLITS):
            continue
        if (section.get("source") == theirs.get("source") == "bundled"  # (the same few photos)
                or any(os.path.commonpath([a, b]) in (a, b)
                       for a in mine for b in _folders(theirs))):
            out.append(other)
    return out


def sharing_line(where: str, split: str, others: list) -> str:
    """The line that says ``split`` of the dataset ``where`` shares photographs with
    ``others`` (:func:`sharing_splits`)."""
    return (f"note: the {split} split of {where} is made from the same photographs (or "
            f"photograph folders, one inside the other) as its {' and '.join(others)} split: "
            "its pairs come from photographs those splits also hold, so numbers on it are not on "
            "unseen photographs; give folders apart (--source=folder, e.g. photos/train and "
            "photos/test) for a held-out test.")
