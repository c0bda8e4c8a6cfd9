r"""The paper schedule's photographs, made small enough to carry to the GPU machine (docs/gpu.md).

  python -m experiments.device_photographs          # -> .devdata/part-K/ and the calls, as JSON

Copies coco_mini and photos_extra as they are, byte for byte, so that the pairs made on the GPU
machine are the pairs made here and a chunk's photographs (``ledger.listing_digest``: the
files' names and sizes) are those of the CPU chunks of the same part (a gray re-encoding of
coco_mini, smaller, had other sizes: every GPU chunk was refused). The
files are split into parts ``.devdata/part-1``, ``part-2``, ... that each fit one call of the
device tool beside the working tree that travels with it (64 MiB a call, the tree included; the
first part leaves room for ``.whl/``). Each part holds its files under their paths relative to
``.devdata/`` (``coco_mini/train/...``, ``photos_extra/imagenet/...``), so the parts copied over
one folder, as ``experiments/paper_schedule_gpu.sh`` does, rebuild the whole set. Packing by
file rather than by folder keeps working however large the tracked tree grows: it only adds
calls.

  python -m experiments.device_photographs --set_aside   # the same, unread files set aside first
  python -m experiments.device_photographs --restore     # after the last call: them back

``--set_aside`` first removes from the working tree the tracked files that no chunk reads
(:data:`ASIDE_PATTERNS`: the shipped weights, the semi-supervised experiment's models and the
camera-pair benchmarks' JSON records), so
that each call has room for more photographs and the set travels in fewer calls; they stay in
git, and ``--restore`` checks them out again. It refuses while any of them differs from HEAD.
Until they are restored, ``git status`` lists them as deleted: restore them before anything is
committed.

Every file it writes under ``--output_dir`` is listed first in ``--output_dir/``:data:`MARKER`; a
later run removes exactly those (:func:`clear_output`), and refuses a non-empty folder without
that list (one it did not make), so that nothing else there is ever deleted.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess

from absl import app, flags

from experiments import common
from stnh_tf.paper.budgets import SCHEDULE_PARTS
from stnh_tf.paths import atomic_write_text, inside, link_below

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SHARED = os.path.join(os.path.dirname(REPO), "shared", "data")
CALL_MIB = 64  # what one call of the device tool carries
# Tracked files that no chunk on the GPU machine reads (git pathspecs; ``*`` spans folders).
# Tracked files no chunk reads: models, and the camera-pair benchmarks' records (17 MB).
ASIDE_PATTERNS = ("semi_supervised/*.keras", "stnh_tf/weights/*.keras",
                  "docs/camera_pairs/*.json")
# The list of the files a run wrote under --output_dir, one relative path a line (OutputFiles).
MARKER = ".device_photographs_files"
MARKER_HEADER = "# written by experiments.device_photographs; its next run removes these files\n"

flags.DEFINE_string("coco_dir", os.path.join(SHARED, "coco_mini"), "coco_mini (train/, test/).")
flags.DEFINE_string("extra_dir", os.path.join(SHARED, "photos_extra"), "photos_extra.")
flags.DEFINE_string("output_dir", os.path.join(REPO, ".devdata"), "Where to write them.")
flags.DEFINE_string("wheels_dir", os.path.join(REPO, ".whl"), "The wheels the first call carries.")
flags.DEFINE_integer("call_mib", CALL_MIB, "MiB one call carries, the working tree included (the "
                     "device tool's limit; tests give more, so the repository's size does not "
                     "decide them).")
flags.DEFINE_bool("set_aside", False, "First remove the files of ASIDE_PATTERNS (models and "
                  "benchmark records no chunk reads) from the working tree (they stay in git), so "
                  "that each call carries more photographs.")
flags.DEFINE_bool("restore", False, "Only check the set-aside files out again, and exit.")
FLAGS = flags.FLAGS


def aside_files(repo: str = REPO) -> list:
    """The tracked files of :data:`ASIDE_PATTERNS` in ``repo`` (relative paths, sorted)."""
    listing = subprocess.run(["git", "ls-files", "-z", "--", *ASIDE_PATTERNS], cwd=repo,
                             capture_output=True, check=True).stdout.decode().split("\0")
    return sorted(p for p in listing if p)


def set_aside(repo: str = REPO) -> int:
    """Remove :func:`aside_files` from ``repo``'s working tree; returns the bytes removed.

    Raises:
        RuntimeError: one of them differs from HEAD (modified or staged): nothing is removed.
    """
    files = aside_files(repo)
    changed = subprocess.run(["git", "status", "--porcelain", "--", *files], cwd=repo,
                             capture_output=True, text=True, check=True).stdout.splitlines()
    changed = [line for line in changed if not line.startswith(" D")]  # set aside already
    if changed:
        raise RuntimeError("not setting files aside, these differ from HEAD: "
                           + "; ".join(changed))
    removed = 0
    for rel in files:
        path = os.path.join(repo, rel)
        if os.path.exists(path):
            removed += os.path.getsize(path)
            os.remove(path)
    return removed


def restore(repo: str = REPO) -> list:
    """Check the set-aside files out again from HEAD; returns those that were missing."""
    missing = [p for p in aside_files(repo) if not os.path.exists(os.path.join(repo, p))]
    if missing:
        subprocess.run(["git", "checkout", "HEAD", "--", *missing], cwd=repo, check=True)
    return missing


class OutputFiles:
    """The files a run writes under ``out``: each one's path relative to ``out`` is appended to
    ``out/``:data:`MARKER` before the file is written (so that a run killed midway still lists
    what it wrote), and a path that already holds something (not this tool's: :func:`clear_output`
    removed its own) is refused. Made by :func:`clear_output`::

        files = clear_output(out)
        shutil.copyfile(src, files.claim(os.path.join(out, "part-1", "a.png")))
    """

    def __init__(self, out: str):
        self.out = out
        self.written = []

    def claim(self, path: str) -> str:
        """List ``path`` (inside ``out``) as written; returns it, its folder made.

        Raises:
          FileExistsError: something is at ``path`` already, or a symbolic link is on the way to
            it from ``out`` (nothing is listed or written)."""
        rel = os.path.relpath(path, self.out)
        _refuse_links(self.out, [rel])
        if os.path.lexists(path):
            raise FileExistsError(f"{path} exists and was not written by device_photographs: "
                                  "not replacing it; move it away.")
        with open(os.path.join(self.out, MARKER), "a") as f:
            f.write(rel + "\n")
        self.written.append(rel)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        return path


def _refuse_links(out: str, rels) -> None:
    """Raise ``FileExistsError`` naming the first symbolic link on the way from ``out`` to one of
    ``rels`` (:func:`stnh_tf.paths.link_below`): this tool writes none, and one there may lead
    out of ``out`` (to the photographs it copies)."""
    for rel in rels:
        inside(out, rel, f"{os.path.join(out, MARKER)!r}, a listed file")  # (or ValueError)
        link = link_below(out, rel)
        if link is not None:
            raise FileExistsError(f"{link} is a symbolic link, not written by device_photographs; "
                                  "nothing is removed or written through it: remove the link.")


def _remove_files(out: str, rels) -> None:
    """Remove the files ``rels`` (relative to ``out``) that are there, as plain files, then every
    folder between them and ``out`` that this leaves empty. Refused before anything is removed
    where a symbolic link is on the way to one of them (:func:`_refuse_links`)."""
    _refuse_links(out, rels)
    folders = set()
    for rel in rels:
        path = inside(out, rel, f"{os.path.join(out, MARKER)!r}, a listed file")
        if os.path.isfile(path):
            os.remove(path)
        parent = os.path.dirname(os.path.normpath(rel))
        while parent:
            folders.add(parent)
            parent = os.path.dirname(parent)
    for rel in sorted(folders, key=lambda r: -r.count(os.sep)):  # deepest first
        path = os.path.join(out, rel)
        if os.path.isdir(path) and not os.path.islink(path) and not os.listdir(path):
            os.rmdir(path)


def clear_output(out: str) -> OutputFiles:
    """Make ``out`` ready for a run: create it, or remove what an earlier run wrote there (the
    files its :data:`MARKER` lists, and the folders that leaves empty) and nothing else; then
    start a new, empty list. Returns the :class:`OutputFiles` of the new run.

    Raises:
      FileExistsError: ``out`` is not empty and holds no :data:`MARKER` (a folder this tool did
        not make): nothing there is removed or written.
      NotADirectoryError: ``out`` is a file.
    """
    marker = os.path.join(out, MARKER)
    if os.path.exists(out) and not os.path.isdir(out):
        raise NotADirectoryError(f"--output_dir {out} exists and is not a folder.")
    if os.path.isdir(out) and not os.path.isfile(marker):
        if os.listdir(out):
            raise FileExistsError(
                f"--output_dir {out} is not empty and holds no {MARKER} (the list of what "
                "device_photographs wrote): nothing there is removed; choose a new or empty "
                "folder, or move its files away.")
    elif os.path.isfile(marker):
        with open(marker) as f:
            listed = [line.rstrip("\n") for line in f if line.strip() and
                      not line.startswith("#")]
        _remove_files(out, listed)
    os.makedirs(out, exist_ok=True)
    atomic_write_text(marker, MARKER_HEADER)
    return OutputFiles(out)


def size(path: str) -> int:
    if os.path.isfile(path):
        return os.path.getsize(path)
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(path) for f in fs)


def next_chunk(last_stage: int = 3) -> str | None:
    """What the next chunk trains, as the environment of ``experiments/paper_schedule_gpu.sh``:
    ``STAGE=K``, the hierarchical stage ``paper_schedule/ledger.json`` is at (its rows without a
    ``"part"``), until stage ``last_stage`` is done; then ``PART=NAME``, the first run of
    :data:`stnh_tf.paper.budgets.SCHEDULE_PARTS` without its ``paper_schedule/NAME.keras``;
    ``None`` once every one is finished."""
    with open(os.path.join(REPO, "paper_schedule", "ledger.json")) as f:
        last = [r for r in json.load(f) if "part" not in r][-1]
    stage = last["stage"] + 1 if last["done"] else last["stage"]
    if stage <= last_stage:
        return f"STAGE={stage}"
    todo = [name for name, fields in SCHEDULE_PARTS.items() if fields is not None
            and not os.path.exists(os.path.join(REPO, "paper_schedule", f"{name}.keras"))]
    return f"PART={todo[0]}" if todo else None


def parts(files: list, budget: int, first_extra: int) -> list:
    """``files`` (``(relative path, bytes)``, in order) split into consecutive parts of at most
    ``budget`` bytes; the first part also holds ``first_extra`` bytes.

    Raises:
        ValueError: one file (or the first part's extra) does not fit a part.
    """
    if budget <= first_extra:
        raise ValueError(f"no room for photographs: {budget / 2 ** 20:.1f} MiB a call, "
                         f"{first_extra / 2 ** 20:.1f} MiB of wheels in the first")
    out = [{"files": [], "bytes": first_extra}]
    for rel, nbytes in files:
        if nbytes > budget:
            raise ValueError(f"{rel} ({nbytes / 2 ** 20:.1f} MiB) does not fit one call")
        if out[-1]["bytes"] + nbytes > budget:
            out.append({"files": [], "bytes": 0})
        out[-1]["files"].append(rel)
        out[-1]["bytes"] += nbytes
    return out


def plan_calls() -> dict:
    """Write the parts and return the report: the photographs' counts, the tree's size and the
    calls (command, what each carries, its MiB)."""
    from stnh_tf.data import sources

    out = FLAGS.output_dir
    written = clear_output(out)  # what an earlier run wrote, and nothing else
    counts = {split: len(sources.scan_image_folder(os.path.join(FLAGS.coco_dir, split)).files)
              for split in ("train", "test")}
    source = {}  # path relative to .devdata/ -> the file to copy (byte for byte: the chunks'
    for root, prefix in ((FLAGS.coco_dir, "coco_mini"),  # listing digests hash the sizes)
                         (FLAGS.extra_dir, "photos_extra")):
        # the photographs as the training lists them (sources.scan_image_folder: a link to a
        # file listed already, a hidden file, a link leading out: not carried twice or at all)
        for path in sources.scan_image_folder(root).files:
            source[os.path.join(prefix, os.path.relpath(path, root))] = path
    files = [(rel, os.path.getsize(source[rel])) for rel in sorted(source)]
    tracked = subprocess.run(["git", "ls-files", "-z", "--cached", "--others",  # what travels
                              "--exclude-standard"], cwd=REPO, capture_output=True,
                             check=True).stdout.decode().split("\0")
    tree = sum(size(os.path.join(REPO, p)) for p in tracked if p and os.path.exists(
        os.path.join(REPO, p)))
    packed = parts(files, FLAGS.call_mib * 2 ** 20 - tree - 2 ** 20, size(FLAGS.wheels_dir))
    calls = []
    for k, part in enumerate(packed, start=1):
        folder = os.path.join(out, f"part-{k}")
        for rel in part["files"]:
            shutil.copyfile(source[rel], written.claim(os.path.join(folder, rel)))
        carry = [os.path.relpath(folder, REPO)]
        if k == 1:
            carry.append(os.path.relpath(FLAGS.wheels_dir, REPO))
        chunk = next_chunk() if k == len(packed) else None  # None: nothing left to train
        command = (f"{chunk} bash experiments/paper_schedule_gpu.sh chunk 535" if chunk else
                   "bash experiments/paper_schedule_gpu.sh stage")
        calls.append({"command": command, "carry": carry, "photographs": len(part["files"]),
                      "mib": round((part["bytes"] + tree) / 2 ** 20, 1)})
    return {"coco_mini": counts, "photographs": len(files),
            "tracked_mib": round(tree / 2 ** 20, 1), "calls": calls}


def main(argv):
    del argv
    if FLAGS.restore:
        print(json.dumps({"restored": restore()}, indent=1))
        return
    with common.user_errors("device_photographs", (ValueError, OSError, RuntimeError)):
        common.check_flags_apart(("output_dir",), ("coco_dir", "extra_dir", "wheels_dir"))
        aside = set_aside() if FLAGS.set_aside else 0
        try:
            report = plan_calls()
        except BaseException:
            if FLAGS.set_aside:
                restore()  # no calls planned: nothing stays set aside
            raise
    if FLAGS.set_aside:
        report["set_aside"] = {"mib": round(aside / 2 ** 20, 1), "after_the_calls":
                               "python -m experiments.device_photographs --restore"}
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    app.run(main)
