"""A file too large to commit, kept as numbered parts under a size limit with a manifest that
checks them (git hosts refuse large files; this project commits none of 10 MB or more).

A file ``f`` over ``max_bytes`` is written as ``f.part-000``, ``f.part-001``, ... (each at most
``max_bytes``) and ``f.parts.json`` (:data:`MANIFEST_SUFFIX`: the whole file's name, size and
sha256, and each part's), and read back whole only when every part and the whole match the
manifest. A file within the limit is copied as it is. Byte parts, not a re-encoding: the file
(an HDF5 checkpoint, say) comes back bit for bit, whatever it holds.

    >>> import os, tempfile
    >>> d = tempfile.mkdtemp()
    >>> src = os.path.join(d, "w.h5")
    >>> with open(src, "wb") as f:
    ...     _ = f.write(bytes(range(256)) * 10)
    >>> [os.path.basename(p) for p in write_parts(src, os.path.join(d, "kept.h5"), 1000)]
    ['kept.h5.part-000', 'kept.h5.part-001', 'kept.h5.part-002', 'kept.h5.parts.json']
    >>> read_whole(os.path.join(d, "kept.h5"), os.path.join(d, "back.h5"))
    >>> open(os.path.join(d, "back.h5"), "rb").read() == open(src, "rb").read()
    True
"""

from __future__ import annotations

import hashlib
import os
import shutil

from stnh_tf.paths import atomic_write_json, inside, read_json

MAX_PART_BYTES = 8 * 1024 * 1024
"""The size of a part (8 MiB): under the 10 MB this project's committed files stay below."""
MANIFEST_SUFFIX = ".parts.json"
PART_SUFFIX = ".part-{index:03d}"


def manifest_path(path: str) -> str:
    """The manifest of the file ``path`` kept in parts."""
    return path + MANIFEST_SUFFIX


def in_parts(path: str) -> bool:
    """Whether ``path`` is not there whole but kept in parts (its manifest, or its first part
    without one)."""
    return not os.path.isfile(path) and (os.path.isfile(manifest_path(path)) or os.path.isfile(
        path + PART_SUFFIX.format(index=0)))


def write_parts(src: str, dst: str, max_bytes: int = MAX_PART_BYTES) -> list:
    """Copy the file ``src`` to ``dst`` (in an existing folder): as it is where it holds at most
    ``max_bytes``, else as parts of ``max_bytes`` beside ``dst`` and their manifest (written
    last). Returns the files written, in order.

    Raises:
      ValueError: ``max_bytes`` is not positive.
    """
    if max_bytes <= 0:
        raise ValueError(f"max_bytes must be positive, not {max_bytes}")
    if os.path.getsize(src) <= max_bytes:
        shutil.copy2(src, dst)
        return [dst]
    written, parts, whole, size = [], [], hashlib.sha256(), 0
    with open(src, "rb") as f:
        while block := f.read(max_bytes):
            whole.update(block)
            size += len(block)
            part = dst + PART_SUFFIX.format(index=len(parts))
            with open(part, "wb") as out:
                out.write(block)
                out.flush()
                os.fsync(out.fileno())  # on disk before the manifest that vouches for it
            parts.append({"name": os.path.basename(part), "bytes": len(block),
                          "sha256": hashlib.sha256(block).hexdigest()})
            written.append(part)
    atomic_write_json(manifest_path(dst), {"file": os.path.basename(dst), "bytes": size,
                                           "sha256": whole.hexdigest(), "parts": parts})
    return [*written, manifest_path(dst)]


def _parts(path: str) -> list:
    """``[(part_path, entry)]`` of the manifest of ``path``, checked for form (not content)."""
    manifest = manifest_path(path)
    doc = read_json(manifest, "manifest of a file in parts")
    folder = os.path.dirname(manifest)
    if not (isinstance(doc, dict) and doc.get("file") == os.path.basename(path)
            and isinstance(doc.get("parts"), list) and doc["parts"]
            and all(isinstance(e, dict) and isinstance(e.get("name"), str) for e in doc["parts"])):
        raise ValueError(f"{manifest} is not the manifest of {os.path.basename(path)} in parts "
                         "(its 'file' and a list of 'parts' with their names)")
    return [(inside(folder, e["name"], f"{manifest!r}, a part's 'name'"), e)
            for e in doc["parts"]]


def read_whole(path: str, dst: str) -> None:
    """Write the file ``path`` to ``dst``: copied where it is whole; else made from its parts,
    written beside ``dst`` and renamed into place only once every part and the whole match the
    manifest's sizes and sha256.

    Raises:
      FileNotFoundError: neither ``path`` nor any part of it is there.
      ValueError: naming the manifest or the part that is missing, another size or other bytes
        (``dst`` is then not written).
    """
    if os.path.isfile(path):
        shutil.copy2(path, dst)
        return
    if not os.path.isfile(manifest_path(path)):
        if in_parts(path):
            raise ValueError(f"{manifest_path(path)} is missing: the parts of {path} cannot be "
                             "checked without it")
        raise FileNotFoundError(f"{path} is missing, whole or in parts ({manifest_path(path)})")
    parts, doc = _parts(path), read_json(manifest_path(path), "manifest of a file in parts")
    tmp = f"{dst}.tmp-{os.getpid()}"
    whole = hashlib.sha256()
    try:
        with open(tmp, "wb") as out:
            for part, entry in parts:
                if not os.path.isfile(part):
                    raise ValueError(f"{part} is missing: a part of {path} "
                                     f"({manifest_path(path)})")
                with open(part, "rb") as f:
                    block = f.read()
                if len(block) != entry.get("bytes") \
                        or hashlib.sha256(block).hexdigest() != entry.get("sha256"):
                    raise ValueError(f"{part} is not the part of {path} that "
                                     f"{manifest_path(path)} names ({len(block)} bytes, its "
                                     "manifest another size or other bytes)")
                whole.update(block)
                out.write(block)
        if os.path.getsize(tmp) != doc.get("bytes") or whole.hexdigest() != doc.get("sha256"):
            raise ValueError(f"the parts of {path} do not make the file {manifest_path(path)} "
                             "names (another size or other bytes)")
        os.replace(tmp, dst)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)

