"""One training run continued in chunks on whatever machine is at hand: each chunk resumes the run
from the newest checkpoint (the run folder's own, or the one committed in the repository), trains
until a time limit, and commits its checkpoint back; a ledger records where each chunk ran.

Layout of a chunked run's repository folder ``root`` (e.g. ``paper_schedule/``):

* ``resume/stage<k>/``: the checkpoint of the unfinished stage k: ``config.json`` (the
  :class:`~stnh_tf.training.config.TrainConfig`, and the sha256 of the finished stages it is
  made from: :func:`~stnh_tf.training.run_dir.config_document`), ``state.json`` (step, RNG
  states) and the one ``ckpt-<step>.weights.h5`` it names (weights and optimizer state; over
  8 MiB, as ``.part-NNN`` files and their ``.parts.json`` manifest:
  :mod:`stnh_tf.training.file_parts`, so that no committed file reaches 10 MB), and
  for k > 1 the finished stages' estimates its pairs are made from
  (``stage_estimates_<split>.npz``: :func:`stnh_tf.training.streams.stage_pairs`); replaced by
  each chunk and removed when the stage is done;
* ``stage<k>.keras``: a finished stage (weights without optimizer state), and beside it
  ``stage<k>.json`` (:func:`stage_record`: the run's configuration and its chunks), what
  ``experiments.ship_weights`` puts in a model card;
* ``ledger.json``: one row per chunk (stage, steps, machine, steps/s, date);
* while a chunk runs, its lock (``.stnh_tf_run.lock``, :class:`~stnh_tf.training.run_dir.RunLock`
  on ``root``): one chunk at a time on ``root``, whatever its run folder; a second is refused.

Before a chunk copies or trains anything it checks that the part is not finished, that the
ledger reads (:func:`read_ledger`), that ``resume/<part>`` is a folder, that the run folder is of
the same run (:func:`~stnh_tf.training.run_dir.check_same_run`: the finished stages it is made
from compared by their files' sha256, not by where the checkout is; the photograph folders and
the run folder may be anywhere) and that the committed weights read whole
(:func:`~stnh_tf.training.checkpoints.check_weights_file`): a refusal leaves everything as it was.

A run other than a hierarchical stage (the 2-stage sequence model, a stage 1 with other loss
weights) is a *part* named by a string (``resume/<part>/``, ``<part>.keras``, ``<part>.json``;
its ledger rows carry ``"part"``); an int part ``k`` is hierarchical stage k (:func:`part_name`).

    >>> ledger_table([{"stage": 1, "from_step": 0, "to_step": 500, "device": "2-core CPU",
    ...                "backend": "tensorflow", "steps_per_s": 1.52, "wall_s": 400.0,
    ...                "date": "2026-11-27"}]).splitlines()[2]
    '| 1 | 0 -> 500 | 2-core CPU | tensorflow | 1.52 | 7 | 2026-11-27 |'
"""

from __future__ import annotations

import datetime
import os
import re
import shutil
import tempfile
import time

from stnh_tf.paths import (atomic_write_json, atomic_write_text, inside, read_json,
                           stage_record_path)
from stnh_tf.provenance import machine_info
from stnh_tf.training import checkpoints, file_parts, run_dir
from stnh_tf.training.config import TrainConfig

RESUME_DIR = "resume"
LEDGER_FILE = "ledger.json"
LEDGER_START = "<!-- ledger:start -->"
LEDGER_END = "<!-- ledger:end -->"
ROOT_BUSY = ("another chunk is running on {folder} (it holds {lock}); one chunk at a time "
             "trains a repository folder's runs: wait for it to finish.")
""":func:`run_chunk`'s refusal while another chunk holds the repository folder's lock."""


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


def resume_dir(root: str, part: int | str) -> str:
    """The repository folder of a part's (stage k: ``k``) committed checkpoint."""
    return os.path.join(root, RESUME_DIR, part_name(part))


def finished_model(root: str, part: int | str) -> str:
    """Where a finished part's model is kept (``stage<k>.keras``, ``<part>.keras``)."""
    return os.path.join(root, f"{part_name(part)}.keras")


def stage_record(root: str, part: int | str, config: dict) -> dict:
    """Write and return ``stage<k>.json`` (``<part>.json``) beside the finished part: its run's
    ``config`` (the ``config.json`` fields), the number of training photographs and pairs, the
    ledger rows of its chunks, and their totals (steps, wall seconds, machines)."""
    from stnh_tf.data import sources

    name = part_name(part)
    rows = [r for r in read_ledger(root) if row_part(r) == name]
    images = len(sources.scan_image_folders(config["image_dir"],
                                            config.get("max_images", 0)).files) \
        if config.get("image_dir") else None
    record = {"format": run_dir.STAGE_RECORD_FORMAT, "stage": config.get("stage", part),
              **({"part": name} if isinstance(part, str) else {}), "config": config,
              "training_photographs": images,
              "training_pairs": images and images * config["samples_per_image"], "chunks": rows,
              "final_step": max((r["to_step"] for r in rows), default=0),
              "wall_s": round(sum(r["wall_s"] for r in rows), 1),
              "machines": sorted({f"{r['device']} ({r['backend']})" for r in rows})}
    atomic_write_json(stage_record_path(finished_model(root, part)), record)
    return record


def _step(checkpoint_dir) -> int:
    """The step of the checkpoint of ``checkpoint_dir`` (-1: none; errors as
    :func:`stnh_tf.training.checkpoints.find_checkpoint`)."""
    found = checkpoints.find_checkpoint(checkpoint_dir)
    return -1 if found is None else int(found[1])


def _copy_checkpoint(src_dir, dst_dir, extra_files=(), max_bytes=None) -> int:
    """Copy the checkpoint of ``src_dir`` (the weights :func:`checkpoints.find_checkpoint` finds
    and the state naming them, where there is one) and ``extra_files`` into ``dst_dir``, replaced
    whole (written beside it, then swapped in); with ``max_bytes``, weights over it as parts
    (:func:`stnh_tf.training.file_parts.write_parts`). Returns the checkpoint's step."""
    tmp, old = f"{dst_dir}.tmp-{os.getpid()}", f"{dst_dir}.old-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    os.makedirs(tmp)
    weights, step, state = checkpoints.find_checkpoint(src_dir)
    written = file_parts.write_parts(weights, os.path.join(tmp, os.path.basename(weights)),
                                     max_bytes or max(os.path.getsize(weights), 1))
    if state is None and len(written) > 1:  # parts are found through the state naming them
        atomic_write_json(os.path.join(tmp, run_dir.CHECKPOINT_STATE),
                          {"step": int(step), "weights": os.path.basename(weights)})
    state = [os.path.join(src_dir, run_dir.CHECKPOINT_STATE)] if state is not None else []
    for path in (*state, *extra_files):
        shutil.copy2(path, os.path.join(tmp, os.path.basename(path)))
    if os.path.exists(dst_dir):
        os.rename(dst_dir, old)
    os.rename(tmp, dst_dir)
    shutil.rmtree(old, ignore_errors=True)
    return int(step)


def _whole_weights(resume: str, state: dict | None, tmp: str) -> str:
    """``resume`` itself where the weights its ``state`` (its ``state.json``) names are there
    whole (or there is no state); where :func:`sync_out` kept them in parts, the folder ``tmp``
    holding that ``state.json`` and the weights made whole
    (:func:`stnh_tf.training.file_parts.read_whole`: every part checked against their manifest).

    Raises:
      ValueError: naming the manifest or part that is missing or wrong.
    """
    if state is None:
        return resume
    weights = inside(resume, state.get("weights", checkpoints.CHECKPOINT_WEIGHTS),
                     f"{os.path.join(resume, run_dir.CHECKPOINT_STATE)!r}, its 'weights'")
    if not file_parts.in_parts(weights):
        return resume  # whole, or missing: find_checkpoint names the missing file
    file_parts.read_whole(weights, os.path.join(tmp, os.path.basename(weights)))
    shutil.copy2(os.path.join(resume, run_dir.CHECKPOINT_STATE), tmp)
    return tmp


def _estimates(folder: str) -> list:
    """The saved stage estimates (:data:`stnh_tf.training.run_dir.ESTIMATES_FILES`) in
    ``folder``."""
    return [os.path.join(folder, name) for name in run_dir.ESTIMATES_FILES.values()
            if os.path.exists(os.path.join(folder, name))]


def sync_in(resume: str, model_dir: str, cfg: TrainConfig | None = None) -> int | None:
    """Copy the committed checkpoint in ``resume`` into the run folder ``model_dir`` where it is
    newer than the folder's own (or the folder has none), with the saved stage estimates beside
    it that the folder lacks. Returns the step copied in, else ``None``.

    Checks first, copies after, holding ``model_dir``'s lock
    (:class:`~stnh_tf.training.run_dir.RunLock`): nothing is copied while another run holds it
    (``FileExistsError``), nor into a folder that is not a run, or is a run of another
    configuration than the committed one or than ``cfg`` where given (``ValueError``:
    :func:`~stnh_tf.training.run_dir.check_same_run`); ``cfg`` is then checked even when
    nothing is to be copied. Nor is a newer committed checkpoint that does not read whole
    (``ValueError`` in one line naming its weights file, or the part or manifest of weights
    kept in parts that is missing or wrong: :func:`~stnh_tf.training.checkpoints.check_weights_file`,
    :func:`~stnh_tf.training.file_parts.read_whole`): the folder keeps its own.

    Raises:
      NotADirectoryError: ``resume`` exists and is not a folder (a checkpoint is one).
    """
    if not os.path.isdir(resume):
        if os.path.lexists(resume):
            raise NotADirectoryError(f"{resume} is not a folder: a committed checkpoint is one "
                                     "(state.json, its weights, config.json); move the file "
                                     "away.")
        return None
    ckpt = os.path.join(model_dir, run_dir.CHECKPOINT_DIR)

    def refused(e):
        own = _step(ckpt)
        kept = f"its checkpoint of step {own} is kept" if own >= 0 else "it has none"
        return ValueError(f"{e}; nothing was copied into {model_dir} ({kept}): put back a "
                          "complete copy of the committed one (git checkout, or the archive it "
                          "came in).")

    # no other run there while this checks and copies
    with run_dir.RunLock(model_dir), tempfile.TemporaryDirectory() as tmp:
        try:
            state = checkpoints.read_checkpoint_state(resume)
        except ValueError as e:
            raise refused(e) from None
        newer = (state["step"] if state is not None else _step(resume)) > _step(ckpt)
        estimates = [p for p in _estimates(resume)
                     if not os.path.exists(os.path.join(model_dir, os.path.basename(p)))]
        if not (newer or estimates or cfg is not None):
            return None
        run_dir.check_same_run(model_dir, os.path.join(resume, run_dir.CONFIG_FILE), cfg)
        if newer:
            try:
                committed = _whole_weights(resume, state, tmp)
                weights, step, _ = checkpoints.find_checkpoint(committed)
                checkpoints.check_weights_file(weights, step)
            except ValueError as e:  # named as committed, made whole from its parts or not
                raise refused(str(e).replace(tmp, resume)) from None
        for path in estimates:
            shutil.copy2(path, model_dir)
        if not newer:
            return None
        config = os.path.join(model_dir, run_dir.CONFIG_FILE)
        if not os.path.exists(config):
            shutil.copy2(os.path.join(resume, run_dir.CONFIG_FILE), config)
        return _copy_checkpoint(committed, ckpt)


def sync_out(model_dir: str, resume: str) -> int:
    """Replace ``resume`` by the run folder's committed checkpoint, ``config.json`` and saved
    stage estimates; weights over :data:`stnh_tf.training.file_parts.MAX_PART_BYTES` (the 2-stage
    sequence model's with their momentum: 12.5 MB) as parts under it and their manifest, which
    :func:`sync_in` checks and joins. Returns its step."""
    ckpt = os.path.join(model_dir, run_dir.CHECKPOINT_DIR)
    os.makedirs(os.path.dirname(resume), exist_ok=True)
    return _copy_checkpoint(ckpt, resume,
                            [os.path.join(model_dir, run_dir.CONFIG_FILE), *_estimates(model_dir)],
                            max_bytes=file_parts.MAX_PART_BYTES)


def strip_optimizer(src: str, dst: str) -> None:
    """Save the model of ``src`` (``.keras``) to ``dst`` without its optimizer state (loaded
    uncompiled by :func:`stnh_tf.modeling.runner.load_model`, as ``ship_weights`` copies
    stages), written beside ``dst`` and then renamed."""
    from stnh_tf.modeling import runner

    tmp = f"{dst}.tmp-{os.getpid()}.keras"
    os.makedirs(os.path.dirname(os.path.abspath(dst)), exist_ok=True)
    runner.load_model(src).save(tmp)
    os.replace(tmp, dst)


def run_chunk(cfg: TrainConfig, root: str, time_limit_s: float, device: str,
              printer=print, commit: str | None = None, part: str | None = None) -> dict:
    """One chunk of ``cfg``'s run: resume from the newest checkpoint (``cfg.model_dir``'s or the
    one committed under ``root``), train until ``time_limit_s`` or a SIGTERM (:func:`stnh_tf.training.loop.train`
    stops within one step and saves that step's checkpoint), then commit the checkpoint back under ``root``, or, once the
    stage is done, its model as ``stage<k>.keras`` (and remove the checkpoint), and add a row to
    the ledger (``commit``: the code's, recorded in the row where given; ``machine``: the commit,
    machine and library versions, :func:`stnh_tf.provenance.machine_info`). Returns the row.
    ``part``: the run's name under ``root`` where it is not hierarchical stage ``cfg.stage``
    (:func:`part_name`; recorded in the row as ``"part"``).

    The chunk holds ``root``'s lock (:class:`~stnh_tf.training.run_dir.RunLock` on ``root``,
    whatever its run folder) from its first check to its ledger row: two chunks of one
    repository folder would train from the same checkpoint, and one of them be lost. Before
    anything is copied or trained, the ledger is read and checked (:func:`read_ledger`), after
    the check that the stage is not finished.

    Raises:
      FileExistsError: the stage is finished (``stage<k>.keras`` under ``root``), or another
        chunk holds ``root``'s lock: nothing is trained or written. ``ValueError``: the ledger
        is broken (:func:`read_ledger`), before anything is copied or trained; as :func:`sync_in`
        (before anything is copied) and :func:`stnh_tf.training.loop.train`; a bad ``part``
        (:func:`part_name`). ``NotADirectoryError`` / ``OSError``: as :func:`sync_in` and
        :func:`stnh_tf.training.loop.train`.
    """
    key = cfg.stage if part is None else part
    finished = finished_model(root, key)
    with run_dir.RunLock(root, busy=ROOT_BUSY):  # one chunk at a time on root, to its end
        if os.path.exists(finished):
            what = f"stage {cfg.stage}" if part is None else f"part {part_name(part)}"
            record = stage_record_path(finished)
            also = f" and {record}" if os.path.exists(record) else ""
            raise FileExistsError(f"{what} is finished: {finished} exists; it is not trained "
                                  f"again (move it{also} away to train it anew).")
        try:
            read_ledger(root)
        except ValueError as e:
            raise ValueError(f"{e} No chunk was started: mend it first (git checkout), so that "
                             "the chunk's row can be added.") from None
        return _run_chunk(cfg, root, key, time_limit_s, device, printer, commit, part)


def _run_chunk(cfg, root, key, time_limit_s, device, printer, commit, part) -> dict:
    """:func:`run_chunk`'s chunk, under ``root``'s lock, of the checked part ``key``."""
    import keras

    from stnh_tf.training import loop

    finished = finished_model(root, key)
    resume = resume_dir(root, key)
    copied = sync_in(resume, cfg.model_dir, cfg)
    if copied is not None:
        printer(f"resuming from the committed checkpoint at step {copied} ({resume})")
    start_step = max(_step(os.path.join(cfg.model_dir, run_dir.CHECKPOINT_DIR)), 0)
    t0 = time.time()
    result = loop.train(cfg, printer=printer, time_limit_s=time_limit_s)
    final = os.path.join(cfg.model_dir, run_dir.FINAL_MODEL)
    done = result["final_step"] >= cfg.train_steps and os.path.exists(final)
    if done:
        strip_optimizer(final, finished)
    else:
        sync_out(cfg.model_dir, resume)
    steps = result["final_step"] - start_step
    row = {"stage": cfg.stage, **({"part": part_name(part)} if part is not None else {}),
           "from_step": start_step, "to_step": result["final_step"],
           "done": bool(done), "device": device, "backend": keras.backend.backend(),
           "steps_per_s": round(steps / max(result["wall_s_this_run"], 1e-9), 3),
           "wall_s": round(time.time() - t0, 1), "date": datetime.date.today().isoformat(),
           **({"commit": commit} if commit else {}), "machine": machine_info()}
    add_ledger_row(root, row)
    if done:
        stage_record(root, key,
                     run_dir.read_run_config(os.path.join(cfg.model_dir, run_dir.CONFIG_FILE)))
        shutil.rmtree(resume, ignore_errors=True)
    return row


MIN_NEXT_STAGE_S = 120.0
"""Seconds a chunk must have left, after finishing its stage, to start the next stage (whose
pairs are first re-made from the finished stages' predictions)."""


def run_stages(make_config, first: int, last: int, root: str, time_limit_s: float, device: str,
               printer=print, commit: str | None = None,
               min_next_s: float = MIN_NEXT_STAGE_S, clock=time.monotonic) -> list:
    """:func:`run_chunk` of stage ``first`` (``make_config(k)``: stage k's configuration), then,
    where that chunk finished its stage and ``last`` is further on, the next stage's chunk in the
    time left, and so on: a stage's leftover minutes are spent on the next one. With
    ``time_limit_s`` 0 (no limit) each stage trains to its end. Returns the chunks' ledger rows.

    A stage is not started with less than ``min_next_s`` of ``time_limit_s`` left (``clock``:
    seconds, for the time spent).

    Raises:
      ValueError: ``first`` > ``last``. Otherwise as :func:`run_chunk`.
    """
    if first > last:
        raise ValueError(f"the first stage ({first}) comes after the last ({last}).")
    start, rows = clock(), []
    for stage in range(first, last + 1):
        left = time_limit_s - (clock() - start) if time_limit_s else 0.0
        if rows and not rows[-1]["done"]:
            break
        if rows and time_limit_s and left < min_next_s:
            printer(f"stage {stage} not started: {left:.0f} s left, under {min_next_s:.0f} s")
            break
        if rows:
            printer(f"stage {stage - 1} is finished; stage {stage} in the {left:.0f} s left"
                    if time_limit_s else f"stage {stage - 1} is finished; stage {stage} next")
        rows.append(run_chunk(make_config(stage), root, left, device, printer, commit))
    return rows


LEDGER_FIELDS = ("stage", "from_step", "to_step", "device", "backend", "steps_per_s", "wall_s",
                 "date")
"""What every ledger row holds (:func:`ledger_table` shows them, :func:`stage_record` sums
them)."""


def read_ledger(root: str) -> list:
    """``root``'s ledger, a list of rows (``[]`` where it has none yet).

    Raises:
      ValueError: naming the file, where it is not valid JSON, not a list of JSON objects, or a
        row lacks one of :data:`LEDGER_FIELDS`.
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
    return ledger


def add_ledger_row(root: str, row: dict) -> list:
    """Append ``row`` to ``root``'s ledger (:func:`read_ledger`); returns the ledger."""
    ledger = read_ledger(root)
    ledger.append(row)
    atomic_write_json(os.path.join(root, LEDGER_FILE), ledger)
    return ledger


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
      ValueError: ``doc`` lacks the markers.
    """
    ledger = read_ledger(root)
    with open(doc) as f:
        text = f.read()
    if LEDGER_START not in text or LEDGER_END not in text:
        raise ValueError(f"{doc} has no {LEDGER_START} ... {LEDGER_END} block.")
    head, rest = text.split(LEDGER_START, 1)
    _, tail = rest.split(LEDGER_END, 1)
    new = f"{head}{LEDGER_START}\n{ledger_table(ledger)}\n{LEDGER_END}{tail}"
    if new != text:
        atomic_write_text(doc, new)
    return new != text
