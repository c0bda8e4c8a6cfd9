"""The folder of a SavedModel export (:mod:`stnh_tf.inference.export`): its lock, the checks
before anything is written, the staging folder's swap into place and the verified marker.

Kept apart from the export's TensorFlow code so that these file rules read (and are tested) on
their own; what they guarantee is in :mod:`stnh_tf.inference.export`'s docstring ("Writing").
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import tempfile

from stnh_tf import paths
from stnh_tf.inference import export_contract

VERIFIED_FILE = export_contract.VERIFIED_FILE
"""The marker of a verified export (:mod:`stnh_tf.inference.export`)."""
VERIFIED_FORMAT = "stnh_tf.export_verified"
SAVED_MODEL_ENTRIES = (VERIFIED_FILE, "saved_model.pb", "fingerprint.pb", "variables", "assets")
"""What a SavedModel export writes into its folder: ``overwrite`` replaces these and nothing
else (the marker first, so that an export cut short leaves none)."""
LOCK_FILE = ".stnh_tf_export.lock"
"""The output folder's lock file (:mod:`stnh_tf.inference.export`); not part of the export (a
folder holding only it counts as empty)."""
STAGING_MARKER = ".stnh_tf_export_staging"
"""The file inside an export's hidden staging folder that marks it as the export's (its JSON
names the output)."""
STAGING_PREFIX = STAGING_MARKER + "."
"""The name of an export's staging folder inside its output, ``tempfile``'s 8 characters
after it."""
ASIDE = ".previous"
"""The folder inside the staging folder that the old export's entries are moved aside to."""


def _check_output(output_dir, overwrite):
    """``FileExistsError`` unless ``output_dir`` is missing, empty (its lock file aside), or a
    SavedModel with ``overwrite``."""
    if not os.path.lexists(output_dir):
        return
    if not os.path.isdir(output_dir):
        raise FileExistsError(f"{output_dir} exists and is not a folder; choose another path.")
    if not {name for name in os.listdir(output_dir)
            if name != LOCK_FILE and not name.startswith(STAGING_PREFIX)}:
        return
    is_saved_model = os.path.isfile(os.path.join(output_dir, "saved_model.pb"))
    if not overwrite or not is_saved_model:
        unverified = verified_problem(output_dir) if is_saved_model else None
        why = ("it is not a SavedModel; choose another path" if not is_saved_model else
               "it holds a SavedModel; pass overwrite=True (--overwrite) to replace it"
               if unverified is None else f"{unverified}: pass overwrite=True (--overwrite) to "
               "export it again")
        raise FileExistsError(f"{output_dir} exists and is not empty; {why}.")


def _staging_pattern(output_dir):
    """The names the code before :data:`STAGING_PREFIX` gave the staging folders it made beside
    the output (``tempfile.mkdtemp(prefix=".<output name>.")``)."""
    return re.compile(re.escape(f".{os.path.basename(os.path.abspath(output_dir))}.")
                      + r"[a-z0-9_]{8}")


def _marker_owner(folder):
    """The output the staging marker inside ``folder`` names, or ``None`` (no marker, a link, not
    a folder, unreadable)."""
    if os.path.islink(folder) or not os.path.isdir(folder):
        return None
    try:
        return paths.read_json(os.path.join(folder, STAGING_MARKER)).get("output")
    except (OSError, ValueError, AttributeError):
        return None


def _remove_stale_staging(output_dir) -> list:
    """Remove the staging folders that killed exports to ``output_dir`` left (call with the
    output's lock held: no live export owns one then): inside it, those named
    :data:`STAGING_PREFIX` holding the marker; beside it, those the code before left (named by
    :func:`_staging_pattern`, holding the marker naming this output). An old export that a
    killed or failed swap (:func:`swap_in`) left aside in one (:data:`ASIDE`) is put back first
    where the output has no entry of its name; a folder still holding some of it is kept.
    Returns the paths removed."""
    output_dir = os.path.abspath(output_dir)
    parent, removed = os.path.dirname(output_dir), []
    inside = [os.path.join(output_dir, name) for name in sorted(os.listdir(output_dir))
              if name.startswith(STAGING_PREFIX)]
    beside = [os.path.join(parent, name) for name in sorted(os.listdir(parent))
              if _staging_pattern(output_dir).fullmatch(name)]
    for folder in inside + beside:
        owner = _marker_owner(folder)
        if owner is None or not (folder in inside or owner == output_dir):
            continue
        aside = os.path.join(folder, ASIDE)
        if os.path.isdir(aside) and not os.path.islink(aside):
            for name in sorted(os.listdir(aside)):
                if not os.path.lexists(os.path.join(output_dir, name)):
                    os.replace(os.path.join(aside, name), os.path.join(output_dir, name))
            if os.listdir(aside):  # an old entry beside a new one of its name: the user's call
                continue
        shutil.rmtree(folder)
        removed.append(folder)
    return removed


@contextlib.contextmanager
def output_lock(output_dir, overwrite: bool = False):
    """Check ``output_dir`` (as :func:`stnh_tf.inference.export.export_saved_model`), create
    it, and hold its lock (:data:`LOCK_FILE`) inside the ``with``, with the checks made again
    under the lock and the staging folders killed exports left removed
    (:mod:`stnh_tf.inference.export`).

    Raises:
      FileExistsError: ``output_dir`` cannot be written (see
        :func:`stnh_tf.inference.export.export_saved_model`), or another export holds its lock
        (naming the folder).
    """
    output_dir = os.fspath(output_dir)
    _check_output(output_dir, overwrite)  # before anything is created in a user's folder
    os.makedirs(output_dir, exist_ok=True)
    lock = os.path.join(output_dir, LOCK_FILE)
    with paths.exclusive_lock(lock, f"another export is writing to {output_dir} (it holds "
                                    f"{lock}); wait for it to finish, or export to another "
                                    "--output."):
        _remove_stale_staging(output_dir)  # (an old export it puts back is checked as any)
        _check_output(output_dir, overwrite)  # another export may have finished meanwhile
        yield output_dir


@contextlib.contextmanager
def staging(output_dir):
    """A new staging folder inside ``output_dir`` (:data:`STAGING_PREFIX`, holding the marker
    that names the output) for the ``with``; removed at its end, except where a failed
    :func:`swap_in` left the old export aside in it (the error names it then)."""
    folder = tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=output_dir)
    try:
        with open(os.path.join(folder, STAGING_MARKER), "w") as f:
            json.dump({"output": os.path.abspath(output_dir)}, f)
        yield folder
    except BaseException:
        aside = os.path.join(folder, ASIDE)
        if not (os.path.isdir(aside) and os.listdir(aside)):
            shutil.rmtree(folder, ignore_errors=True)
        raise
    shutil.rmtree(folder, ignore_errors=True)


def saved_model_digest(path) -> str:
    """The SHA-256 of the SavedModel's files in the folder ``path`` (:data:`SAVED_MODEL_ENTRIES`
    but the marker; each file's path relative to ``path`` and content, in sorted order)."""
    digest = hashlib.sha256()
    path = os.fspath(path)
    for name in SAVED_MODEL_ENTRIES[1:]:
        top = os.path.join(path, name)
        files = [top] if os.path.isfile(top) else sorted(
            os.path.join(folder, f) for folder, _, names in os.walk(top) for f in names)
        for file in files:
            digest.update(os.path.relpath(file, path).encode() + b"\0"
                          + bytes.fromhex(paths.file_sha256(file)))
    return digest.hexdigest()


def verified_problem(path) -> str | None:
    """Why the export in the folder ``path`` is not known to be verified, or ``None``: no
    :data:`VERIFIED_FILE` (its export or check was cut short, or the check failed), one that is
    not an export's, or one whose digest is not the files' (:func:`saved_model_digest`)."""
    marker = os.path.join(os.fspath(path), VERIFIED_FILE)
    if not os.path.isfile(marker):
        return (f"{os.fspath(path)} was never verified (no {VERIFIED_FILE}: its export or its "
                "check was cut short, the check failed, or it was exported before stnh_tf "
                "wrote the marker)")
    try:
        doc = paths.read_json(marker)
    except (OSError, ValueError) as e:
        return f"{marker} cannot be read ({e})"
    if not isinstance(doc, dict) or doc.get("format") != VERIFIED_FORMAT:
        return f"{marker} is not an export's marker"
    if doc.get("saved_model_sha256") != saved_model_digest(path):
        return (f"the SavedModel files in {os.fspath(path)} changed since they were verified "
                f"({VERIFIED_FILE})")
    return None


def swap_in(staging, output_dir) -> list:
    """Move the export written in ``staging`` into ``output_dir``: the old export's entries
    (:data:`SAVED_MODEL_ENTRIES`, the marker first, and the documents an export wrote) are moved
    aside into ``staging`` first, and put back if any move fails (``OSError`` naming the
    output). Returns the user's documents kept (:func:`stnh_tf.inference.export._write_export`)."""
    aside = os.path.join(staging, ASIDE)
    os.mkdir(aside)
    kept, moved_aside, moved_in = [], [], []
    try:
        for name in SAVED_MODEL_ENTRIES + export_contract.DOC_FILES:
            old = os.path.join(output_dir, name)
            if not os.path.lexists(old):
                continue
            if name in export_contract.DOC_FILES and not (
                    os.path.isfile(old) and not os.path.islink(old)
                    and export_contract.written_by_export(old)):
                kept.append(old)  # a user's file of that name stays; the export's is dropped
                os.remove(os.path.join(staging, name))
                continue
            os.replace(old, os.path.join(aside, name))
            moved_aside.append(name)
        for name in sorted(os.listdir(staging)):
            if name not in (STAGING_MARKER, ASIDE):
                os.replace(os.path.join(staging, name), os.path.join(output_dir, name))
                moved_in.append(name)
    except OSError as e:
        try:
            for name in moved_in:
                new = os.path.join(output_dir, name)
                shutil.rmtree(new) if os.path.isdir(new) and not os.path.islink(new) \
                    else os.remove(new)
            for name in moved_aside:
                os.replace(os.path.join(aside, name), os.path.join(output_dir, name))
        except OSError as again:  # the old export stays where it was moved aside
            raise OSError(f"cannot move the new SavedModel into {output_dir} ({e}), nor the old "
                          f"export back ({again}): the old export's entries are in {aside}; "
                          "move them back by hand (the next export to it puts them back "
                          "first)") from None
        raise OSError(f"cannot move the new SavedModel into {output_dir} ({e}); the old export "
                      "there is kept as it was") from None
    return kept
