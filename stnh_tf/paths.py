"""Files the package reads and writes: JSON parsed with errors naming the file, text and JSON
written atomically, paths read from files kept inside their folder, output folders checked before
any work, one writer at a time (:func:`exclusive_lock`).

Standard library only (data-generation workers and the TF-free pipelines import it).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os


def read_json(path, what: str = "JSON file"):
    """The parsed JSON document at ``path``.

    Raises:
      FileNotFoundError / OSError: the file cannot be opened (the message names it).
      ValueError: not valid JSON (or not UTF-8 text); the message names ``what`` and ``path``.
    """
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except ValueError as e:  # JSONDecodeError and UnicodeDecodeError
        raise ValueError(f"{what} {path!r} is not valid JSON: {e}.") from None


def fsync_replace(tmp, path) -> None:
    """Flush the finished file ``tmp`` to disk, then rename it to ``path`` (atomic on POSIX), so
    ``path`` is never seen half-written, even after a crash."""
    with open(tmp, "rb+") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)


def atomic_copy(src, dst) -> None:
    """``shutil.copy2(src, dst)`` (``dst`` a file path) through ``<dst>.tmp-<pid>``, fsynced and
    renamed: a kill or a full disk midway leaves ``dst`` as it was, never a truncated copy that
    counts as there; the temporary file is removed where the copy fails."""
    import shutil

    dst = os.fspath(dst)
    tmp = f"{dst}.tmp-{os.getpid()}"
    try:
        shutil.copy2(src, tmp)
        fsync_replace(tmp, dst)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise


def atomic_write_text(path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` through a temporary file beside it
    (``<path>.tmp-<pid>``), fsynced and renamed: ``path`` holds its old text or the new one,
    never part of either (a crash, a full disk). The temporary file is removed where writing it
    fails. A ``path`` that exists and is not a regular file (``/dev/stdout``, a FIFO) is written
    directly: it cannot be replaced.

    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     atomic_write_text(os.path.join(d, "a.md"), "new\\n")
    ...     sorted(os.listdir(d))
    ['a.md']
    """
    atomic_write_bytes(path, text.encode("utf-8"))


def read_document(path) -> tuple[str, str]:
    """``(text, newline)`` of the UTF-8 text file ``path``: its text with ``\n`` line ends, and
    the line end it uses (``"\r\n"`` where it holds one, else ``"\n"``), so that a block
    rewritten in it (:func:`write_document`) leaves the rest byte for byte, whatever the locale
    and the checkout's line ends."""
    with open(path, encoding="utf-8", newline="") as f:
        raw = f.read()
    return raw.replace("\r\n", "\n"), "\r\n" if "\r\n" in raw else "\n"


def document_text(text: str, newline: str) -> str:
    """``text`` (``\n`` line ends) with the line end :func:`read_document` found."""
    return text if newline == "\n" else text.replace("\n", newline)


def atomic_write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` as :func:`atomic_write_text` writes text (an encoded image,
    e.g.: ``cv2.imencode``'s bytes)."""
    path = os.fspath(path)
    if os.path.exists(path) and not os.path.isfile(path):
        with open(path, "wb") as f:
            f.write(data)
        return
    tmp = f"{path}.tmp-{os.getpid()}"
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        fsync_replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise


def atomic_write_json(path, obj, sort_keys: bool = True) -> None:
    """Write ``obj`` as JSON (indented, keys sorted unless ``sort_keys`` is False, NumPy scalars
    as floats) to ``path`` by :func:`atomic_write_text`."""
    atomic_write_text(path, json_text(obj, sort_keys))


def json_text(obj, sort_keys: bool = True) -> str:
    """:func:`atomic_write_json`'s text of ``obj``."""
    return json.dumps(obj, indent=2, sort_keys=sort_keys, default=float) + "\n"


def atomic_write_files(named: dict) -> None:
    """Write ``{path: bytes}`` as a set: every temporary file first (``<path>.tmp-<pid>``), then
    each renamed into place, so that a failure while writing them (a full disk) leaves every old
    file as it was, never a new one beside an old one (an overlay and its JSON)."""
    staged = [f"{os.fspath(path)}.tmp-{os.getpid()}" for path in named]
    try:
        for tmp, data in zip(staged, named.values()):
            write_synced(tmp, data)
        for tmp, path in zip(staged, named):  # (renames in one folder: a moment apart)
            os.replace(tmp, path)
    finally:
        for tmp in staged:
            with contextlib.suppress(OSError):
                os.remove(tmp)


def write_synced(path, data: bytes) -> None:
    """Write ``data`` to ``path`` and flush it to disk."""
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def inside(folder, name, what: str) -> str:
    """``folder/name`` for a ``name`` read from a file in ``folder`` (a shard of a dataset's
    metadata, the weights a checkpoint state names, a stage of a manifest).

    ``name`` must be a non-empty relative path that stays inside ``folder`` once ``.`` and
    ``..`` are resolved (checked lexically: symbolic links placed inside ``folder`` are followed
    as they are). Absolute paths and ``../`` escapes raise ``ValueError`` naming ``what``.
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"{what}: expected a relative path inside {os.fspath(folder)!r}; "
                         f"received {name!r}.")
    norm = os.path.normpath(name)
    if os.path.isabs(name) or norm == os.pardir or norm.startswith(os.pardir + os.sep) \
            or norm == os.curdir:
        raise ValueError(f"{what}: {name!r} is not a path inside {os.fspath(folder)!r} (absolute "
                         "paths and '..' are refused).")
    return os.path.join(os.fspath(folder), norm)


def link_below(folder, name) -> str | None:
    """The first symbolic link met going from ``folder`` down to ``folder/name`` (``name`` a
    relative path inside it: :func:`inside`), ``name`` itself included and ``folder`` not; None
    where there is none. A path with a link on the way may lead out of ``folder``: what is
    removed or written there must not follow it.

    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     os.symlink(tempfile.gettempdir(), os.path.join(d, "elsewhere"))
    ...     [os.path.relpath(p, d) if p else p
    ...      for p in (link_below(d, "elsewhere/a.png"), link_below(d, "own/a.png"))]
    ['elsewhere', None]
    """
    path = os.fspath(folder)
    for part in os.path.normpath(name).split(os.sep):
        path = os.path.join(path, part)
        if os.path.islink(path):
            return path
    return None


def check_output_dir(output_dir) -> str:
    """Create ``output_dir`` if needed and prove it writable (a probe file is written and
    removed); returns its absolute path.

    Raises:
      OSError: it cannot be created (e.g. a file is in the way) or written; the message names it.
    """
    path = os.path.abspath(os.fspath(output_dir))
    try:
        os.makedirs(path, exist_ok=True)
        probe = os.path.join(path, f".write-test-{os.getpid()}")
        with open(probe, "w") as f:
            f.write("ok")
        os.remove(probe)
    except OSError as e:
        raise OSError(f"output directory {path!r} is not writable: {e.strerror or e}") from None
    return path


def check_output_file(path) -> str:
    """Prepare to write the file ``path`` later: its folder is created if needed and proved
    writable (:func:`check_output_dir`), ``path`` itself must not be a folder, nor a record
    this project keeps (:func:`project_record`: a dataset's ``metadata.json``, a run's
    ``config.json``, a shard or a model). Returns the absolute path. Raises ``OSError`` naming
    the path."""
    path = os.path.abspath(os.fspath(path))
    if os.path.isdir(path):
        raise IsADirectoryError(f"output file {path!r} is a directory.")
    what = project_record(path)
    if what:
        raise FileExistsError(f"output file {path!r} is {what}, which this output would replace; "
                              "choose another path.")
    check_output_dir(os.path.dirname(path))
    return path


def project_record(path) -> str | None:
    """What the existing file ``path`` is, where it is a record stnh_tf keeps and an output must
    never replace: a JSON file whose ``format`` is one of this project's (``stnh_tf.*``: a
    dataset's ``metadata.json``, a run's ``config.json``, a hierarchy manifest, a camera-pair
    set's manifest, an export's marker...), a model card (``stages`` and ``bundled_check``), a
    chunk ledger (a list of rows with ``from_step`` and ``to_step``), a TFRecord shard or a
    model file; else ``None``."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        return None
    if path.endswith((".tfrecord", ".keras", ".h5")):
        return "a shard or model file"
    if path.endswith(".json") and os.path.getsize(path) < 64 << 20:
        try:
            with open(path, encoding="utf-8") as f:
                doc = json.load(f)
        except (OSError, ValueError):
            return None
        kind = doc.get("format") if isinstance(doc, dict) else None
        if isinstance(kind, str) and kind.startswith("stnh_tf."):
            return f"a {kind} record"
        if isinstance(doc, dict) and {"stages", "bundled_check"} <= set(doc):
            return "a model card of shipped weights"
        if isinstance(doc, list) and doc and all(
                isinstance(r, dict) and {"from_step", "to_step"} <= set(r) for r in doc):
            return "a ledger of training chunks"
    return None


def _named_paths(named: dict):
    """``(name, path as given, real path)`` for each path of ``{name: path | paths | None}``
    (``None``, ``""`` and ``"-"``, standard output, skipped)."""
    for name, value in named.items():
        values = [value] if isinstance(value, (str, os.PathLike)) else list(value or ())
        for path in values:
            if path and os.fspath(path) != "-":
                yield name, os.fspath(path), os.path.realpath(path)


def file_sha256(path: str) -> str:
    """The sha256 (hex) of the bytes of the file ``path``, read in blocks of 1 MiB (``OSError``
    where it cannot be read). ``hashlib.file_digest`` does the same from Python 3.11 on; this
    project supports 3.10."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def check_apart(outputs: dict, inputs: dict) -> None:
    """Refuse, before anything is written, outputs that would overwrite what a run reads or be
    read back by it as input.

    ``outputs`` and ``inputs`` map a name as the user knows it (a flag: ``"--json_out"``) to a
    path, a list of paths, or ``None`` (unset; ``""`` and ``"-"``, standard output, are skipped
    too). Paths are compared once symbolic links are resolved (:func:`os.path.realpath`), so a
    link to an input is that input. Refused: an output that is an input (``--json_out`` naming the
    dataset's ``metadata.json``), an output inside an input folder (a result written into the
    dataset or model folder it reads, pairs written among the photographs they are made from),
    and an output folder that holds an input (photographs that an ``--overwrite`` could delete or
    a later run read back).

    Raises:
      ValueError: naming the output, the input and how they overlap.

    >>> check_apart({"--json_out": "D/result.json"}, {"--data_dir": "E", "--model": None})
    >>> check_apart({"--json_out": "D/metadata.json"}, {"--data_dir": ["E", "D"]})
    Traceback (most recent call last):
    ...
    ValueError: --json_out 'D/metadata.json' is inside --data_dir 'D', an input of this run: ...
    """
    for out_name, out, out_real in _named_paths(outputs):
        for in_name, given, in_real in _named_paths(inputs):
            if out_real == in_real:
                how = "is"
            elif out_real.startswith(in_real.rstrip(os.sep) + os.sep):
                how = "is inside"
            elif in_real.startswith(out_real.rstrip(os.sep) + os.sep):
                how = "holds"
            else:
                continue
            raise ValueError(f"{out_name} {out!r} {how} {in_name} {given!r}, an input of this run: "
                             "writing there could overwrite what it reads, or be read back as "
                             "input; nothing was written: choose an output outside the inputs.")


def stage_record_path(model_file) -> str:
    """The record beside a chunked run's finished stage (``stage<k>.keras`` -> ``stage<k>.json``:
    :func:`stnh_tf.training.part_records.stage_record`), which ``experiments.ship_weights`` reads.

    >>> stage_record_path("paper_schedule/stage1.keras")
    'paper_schedule/stage1.json'
    """
    return os.path.splitext(os.fspath(model_file))[0] + ".json"


@contextlib.contextmanager
def exclusive_lock(lock_path, busy: str, wait: bool = False):
    """Hold ``fcntl.flock`` on the file ``lock_path`` (created if missing, never removed; an
    existing folder is locked as itself, nothing created in it) for one writer: a second holder,
    in this process or another, fails at once with
    ``FileExistsError(busy)`` instead of waiting or writing over the first one's files (with
    ``wait``, it waits for the first to let go: writers that only choose names, as ``predict``'s
    output stems). The lock goes with the process, so a killed writer leaves none held (its lock
    file stays and is reused). make_dataset's split lock
    (:func:`stnh_tf.data.metadata.split_lock`), the SavedModel export's
    (:func:`stnh_tf.inference.export.export_saved_model`), ``predict``'s and the shipped weights'
    folder's (:mod:`stnh_tf.inference.shipped_weights`) are this lock.

        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     path = os.path.join(folder, ".lock")
        ...     with exclusive_lock(path, "busy"):
        ...         try:
        ...             with exclusive_lock(path, "busy: another writer holds it"):
        ...                 pass
        ...         except FileExistsError as e:
        ...             print(e)
        busy: another writer holds it
    """
    import fcntl

    # a folder is locked as itself: nothing is created in it (the shipped weights' folder)
    fd = os.open(lock_path, os.O_RDONLY if os.path.isdir(lock_path)
                 else os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)  # (open()'s, less umask)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except BlockingIOError:
            raise FileExistsError(busy) from None
        try:
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)

