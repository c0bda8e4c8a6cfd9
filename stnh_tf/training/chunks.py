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
  (``stage_estimates_<split>.npz``: :func:`stnh_tf.training.streams.stage_pairs`); updated in
  place by each chunk (``state.json`` last) and removed when the stage is done;
* ``stage<k>.keras``: a finished stage (weights without optimizer state), and beside it
  ``stage<k>.json`` (:func:`~stnh_tf.training.part_records.stage_record`: the run's
  configuration and its chunks), what ``experiments.ship_weights`` puts in a model card;
* ``ledger.json``: one row per chunk (stage, steps, machine, steps/s, date;
  :mod:`stnh_tf.training.ledger`);
* while a chunk runs, its lock (``.stnh_tf_run.lock``, :class:`~stnh_tf.training.run_dir.RunLock`
  on ``root``): one chunk at a time on ``root``, whatever its run folder; a second is refused.

Before a chunk copies or trains anything it checks that the part is not finished, that the
ledger reads (:func:`read_ledger`), that ``resume/<part>`` is a folder, that the run folder is of
the same run (:func:`~stnh_tf.training.run_dir.check_same_run`: the finished stages it is made
from compared by their files' sha256, not by where the checkout is; the photograph folders and
the run folder may be anywhere), that the training photographs are those of the part's last
chunk (:func:`check_photographs`) and that the committed weights read whole
(:func:`~stnh_tf.training.checkpoints.check_weights_file`): a refusal leaves everything as it was.
A chunk that would then start below the step the ledger recorded for its part is refused before
it trains (the run folder holding the newest checkpoint found).

A run other than a hierarchical stage (the 2-stage sequence model, a stage 1 with other loss
weights) is a *part* named by a string (``resume/<part>/``, ``<part>.keras``, ``<part>.json``;
its ledger rows carry ``"part"``); an int part ``k`` is hierarchical stage k (:func:`part_name`).
The ledger itself: :mod:`stnh_tf.training.ledger`.
"""

from __future__ import annotations

import datetime
import os
import shutil
import tempfile
import time

from stnh_tf.paths import atomic_copy, fsync_replace, inside, stage_record_path
from stnh_tf.provenance import machine_info
from stnh_tf.training import checkpoints, file_parts, run_dir
from stnh_tf.training.callbacks import TrainingClock, deferred_signals
from stnh_tf.training.config import TrainConfig
from stnh_tf.training.ledger import (add_ledger_row, add_pending_rows, check_photographs,
                                     keep_pending, part_name, photographs, read_ledger,
                                     recorded_step, row_part)
from stnh_tf.training.part_records import (RESUME_DIR, drop_unfinished_rows,  # noqa: F401
                                           finish_record, finished_model, resume_dir,
                                           stage_record)

ROOT_BUSY = ("another chunk is running on {folder} (it holds {lock}); one chunk at a time "
             "trains a repository folder's runs: wait for it to finish.")
""":func:`run_chunk`'s refusal while another chunk holds the repository folder's lock."""


def _step(checkpoint_dir) -> int:
    """The step of the checkpoint of ``checkpoint_dir`` (-1: none; errors as
    :func:`stnh_tf.training.checkpoints.find_checkpoint`)."""
    found = checkpoints.find_checkpoint(checkpoint_dir)
    return -1 if found is None else int(found[1])


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
    :func:`~stnh_tf.training.file_parts.read_whole`), nor a committed checkpoint without its
    ``config.json``, or weights in parts without the ``state.json`` that names them
    (``ValueError``): the folder keeps its own.

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
        # parts with their manifest but no state were taken for no checkpoint (trained from
        # 0); parts without a manifest are a first commit cut short (the manifest and
        # state.json come last): ignored
        if state is None and any(f.endswith(file_parts.MANIFEST_SUFFIX)
                                 for f in os.listdir(resume)):
            raise refused(f"{resume} holds weights in parts but no {run_dir.CHECKPOINT_STATE} "
                          "naming them (or, never committed, move the folder away)")
        committed_step = state["step"] if state is not None else _step(resume)
        newer = committed_step > _step(ckpt)
        estimates = [p for p in _estimates(resume)
                     if not os.path.exists(os.path.join(model_dir, os.path.basename(p)))]
        if not (newer or estimates or cfg is not None):
            return None
        if (committed_step >= 0 or estimates) and not os.path.isfile(
                os.path.join(resume, run_dir.CONFIG_FILE)):
            raise refused(f"{resume} holds a checkpoint but not its {run_dir.CONFIG_FILE}, which "
                          "says what run it is of")
        run_dir.check_same_run(model_dir, os.path.join(resume, run_dir.CONFIG_FILE), cfg)
        if newer:
            try:
                committed = _whole_weights(resume, state, tmp)
                weights, step, _ = checkpoints.find_checkpoint(committed)
                checkpoints.check_weights_file(weights, step)
            except ValueError as e:  # named as committed, made whole from its parts or not
                raise refused(str(e).replace(tmp, resume)) from None
        for path in estimates:
            atomic_copy(path, os.path.join(model_dir, os.path.basename(path)))
        if not newer:
            return None
        config = os.path.join(model_dir, run_dir.CONFIG_FILE)
        if not os.path.exists(config):
            atomic_copy(os.path.join(resume, run_dir.CONFIG_FILE), config)
        return checkpoints.copy_checkpoint(committed, ckpt)


def _committed_step(resume: str) -> int:
    """The step of the checkpoint committed in ``resume`` (its ``state.json``'s, else its weights'
    name's; -1: none, or a state that does not read)."""
    try:
        state = checkpoints.read_checkpoint_state(resume) if os.path.isdir(resume) else None
        return state["step"] if state is not None else _step(resume)
    except (OSError, ValueError):
        return -1


def sync_out(model_dir: str, resume: str) -> int:
    """Put the run folder's committed checkpoint, ``config.json`` and saved stage estimates into
    ``resume``; weights over :data:`stnh_tf.training.file_parts.MAX_PART_BYTES` (the 2-stage
    sequence model's with their momentum: 12.5 MB) as parts under it and their manifest, which
    :func:`sync_in` checks and joins; updated in place, ``state.json`` last
    (:func:`~stnh_tf.training.checkpoints.copy_checkpoint`: a kill at any moment leaves a
    complete checkpoint there). Returns its step.

    Raises:
      ValueError: ``resume`` holds a newer checkpoint than the run folder (another chunk's,
        committed meanwhile), or other weights of the same step: nothing is replaced.
    """
    ckpt = os.path.join(model_dir, run_dir.CHECKPOINT_DIR)
    committed, own = _committed_step(resume), _step(ckpt)
    if committed > own:
        raise ValueError(f"{resume} holds a checkpoint of step {committed}, newer than the run "
                         f"folder's {own} ({ckpt}): not replaced (another chunk committed it); "
                         "the run folder keeps its own.")
    os.makedirs(os.path.dirname(resume), exist_ok=True)
    return checkpoints.copy_checkpoint(ckpt, resume,
                            [os.path.join(model_dir, run_dir.CONFIG_FILE), *_estimates(model_dir)],
                            max_bytes=file_parts.MAX_PART_BYTES)


def strip_optimizer(src: str, dst: str) -> None:
    """Save the model of ``src`` (``.keras``) to ``dst`` without its optimizer state (loaded
    uncompiled by :func:`stnh_tf.modeling.runner.load_model`, as ``ship_weights`` copies
    stages), written beside ``dst`` and then renamed."""
    from stnh_tf.modeling import runner

    tmp = f"{dst}.tmp-{os.getpid()}.keras"
    os.makedirs(os.path.dirname(os.path.abspath(dst)), exist_ok=True)
    try:
        runner.load_model(src).save(tmp)
        fsync_replace(tmp, dst)  # on disk before the committed checkpoint goes
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def run_chunk(cfg: TrainConfig, root: str, time_limit_s: float, device: str,
              printer=print, commit: str | None = None, part: str | None = None,
              step_back: bool = False) -> dict:
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
    the check that the stage is not finished; before training, the step it starts from is
    compared with the ledger's last row of the part: below it (the checkpoint of recorded steps
    missing) the chunk is refused unless ``step_back``. Where training raises after a
    checkpoint past the start, that checkpoint and a row with the error are committed before
    the error goes on; a run folder holding the finished run (a chunk stopped while finishing
    it) is finished without training. A SIGTERM or Ctrl-C while the chunk commits its checkpoint
    and row acts once they are written (:func:`~stnh_tf.training.callbacks.deferred_signals`).

    A row that could not be added (the ledger changed while the chunk ran and does not read) is
    kept in ``ledger.pending.json`` and added by the next chunk once the ledger reads (a finished
    part's record then written: :func:`~stnh_tf.training.ledger.add_ledger_row`).

    Raises:
      FileExistsError: the stage is finished (``stage<k>.keras`` under ``root``), or another
        chunk holds ``root``'s lock: nothing is trained or written. ``ValueError``: the ledger
        is broken (:func:`read_ledger`), before anything is copied or trained; the chunk would
        start below the ledger's last step of the part (without ``step_back``), before training;
        as :func:`sync_in`
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
            if not os.path.exists(record):  # the chunk that finished it stopped before it
                finish_record(cfg, root, key, printer)
            also = f" and {record}" if os.path.exists(record) else ""
            raise FileExistsError(f"{what} is finished: {finished} exists; it is not trained "
                                  f"again (move it{also} away to train it anew).")
        try:
            read_ledger(root)
        except ValueError as e:
            raise ValueError(f"{e} No chunk was started: mend it first (git checkout), so that "
                             "the chunk's row can be added.") from None
        drop_unfinished_rows(root)
        if added := add_pending_rows(root):
            printer(f"{added} ledger row(s) kept while the ledger did not read added to it")
        return _run_chunk(cfg, root, key, time_limit_s, device, printer, commit, part,
                          step_back)


def _run_chunk(cfg, root, key, time_limit_s, device, printer, commit, part, step_back) -> dict:
    """:func:`run_chunk`'s chunk, under ``root``'s lock, of the checked part ``key``."""
    import keras

    from stnh_tf.training import loop

    finished, resume, name = finished_model(root, key), resume_dir(root, key), part_name(key)
    seen, rows = photographs(cfg), [r for r in read_ledger(root) if row_part(r) == name]
    anew = bool(rows and rows[-1].get("done"))
    if anew:
        rows = []  # a part trained anew after it was finished (its model moved away)
    check_photographs([r.get("photographs") for r in rows], seen, name, cfg, printer)
    copied = sync_in(resume, cfg.model_dir, cfg)
    if copied is not None:
        printer(f"resuming from the committed checkpoint at step {copied} ({resume})")
    ckpt = os.path.join(cfg.model_dir, run_dir.CHECKPOINT_DIR)
    start_step = max(_step(ckpt), 0)
    recorded = recorded_step(read_ledger(root), name)
    if recorded is not None and start_step < recorded and not step_back:
        raise ValueError(
            f"the ledger's last row of {name} ends at step {recorded}, but the newest checkpoint "
            f"({resume}, {ckpt}) is of step {start_step}: the steps between are not here. Nothing "
            f"was trained: put the committed checkpoint back (git checkout {resume}), or pass "
            f"--step_back to train on from step {start_step} (those rows are then superseded).")
    if recorded is not None and start_step > recorded:
        printer(f"the run folder's checkpoint of step {start_step} is past the ledger's last row "
                f"({recorded}: a chunk that ended without its row); going on from it")

    t0 = time.time()

    def row(to_step, done, wall_this_run, **extra):
        return {"stage": cfg.stage, **({"part": name} if part is not None else {}),
                "from_step": start_step, "to_step": to_step, "done": bool(done),
                "device": device, "backend": keras.backend.backend(),
                "steps_per_s": round((to_step - start_step) / max(wall_this_run, 1e-9), 3),
                "wall_s": round(time.time() - t0, 1), "date": datetime.date.today().isoformat(),
                **({"commit": commit} if commit else {}), "machine": machine_info(),
                **({"photographs": seen} if seen else {}), **extra}

    final = os.path.join(cfg.model_dir, run_dir.FINAL_MODEL)
    if os.path.exists(final) and start_step >= cfg.train_steps and anew:
        raise ValueError(f"{name} is to be trained anew (its finished model was moved away), but "
                         f"the run folder {cfg.model_dir} holds the finished run of step "
                         f"{start_step}: move that folder away too. Nothing was trained.")
    if os.path.exists(final) and start_step >= cfg.train_steps:
        # a chunk that trained to the end was stopped before it finished the part
        printer(f"{final} is the finished run (step {start_step}): finishing it, no training")
        result = {"final_step": start_step, "wall_s_this_run": 0.0,
                  "note": "finished a run trained to its end by a chunk stopped before its row"}
    else:
        clock = TrainingClock()  # (an error's row: steps/s over training, not pair making)
        try:
            result = loop.train(cfg, printer=printer, time_limit_s=time_limit_s,
                                extra_callbacks=[clock])
        except BaseException as e:  # what it trained is committed all the same
            error = f"{type(e).__name__}: {e}"[:300]
            _commit_stopped(cfg.model_dir, resume, root, start_step, printer,
                            lambda step: row(step, False, time.time() - (clock.began or t0),
                                             error=error))
            raise
    done = result["final_step"] >= cfg.train_steps and os.path.exists(final)
    with deferred_signals():  # a SIGTERM or Ctrl-C now acts once the commit is written
        out = row(result["final_step"], done, result["wall_s_this_run"],
                  **({"note": result["note"]} if "note" in result else {}))
        if not done:
            try:
                sync_out(cfg.model_dir, resume)
            except BaseException as e:  # the row kept, for the steps the run folder holds
                keep_pending(root, {**out, "committed": False,
                                    "error": f"{type(e).__name__}: {e}"[:300]})
                raise
            add_ledger_row(root, out)
            return out
        # the finishing row first, where the next chunk finds it should this one stop (a kill,
        # a full disk) between the model's write and the record's (part_records.finish_record)
        note = keep_pending(root, out)
        try:
            strip_optimizer(final, finished)
        except BaseException as e:  # no finished model: not a finishing row, but the steps
            drop_unfinished_rows(root)  # trained are committed with a row of their own
            error = f"{type(e).__name__}: {e}"[:300]
            _commit_stopped(cfg.model_dir, resume, root, start_step, printer,
                            lambda step: row(step, False, result["wall_s_this_run"],
                                             error=error))
            raise
        try:
            add_pending_rows(root)
        except ValueError as e:
            raise ValueError(f"{e} {note}") from None
        stage_record(root, key, run_dir.read_run_config(
            os.path.join(cfg.model_dir, run_dir.CONFIG_FILE)))
        shutil.rmtree(resume, ignore_errors=True)
    return out


def _commit_stopped(model_dir, resume, root, start_step, printer, make_row) -> None:
    """Where a chunk's training raised after it saved a checkpoint past ``start_step``: commit
    that checkpoint (:func:`sync_out`) and its ledger row (``make_row(step)``, with the error),
    so that the steps trained are not lost with the run folder. A failure here is printed, not
    raised (the training's error is the one that counts)."""
    try:
        # (the run folder's lock: not a checkpoint another process is writing)
        with run_dir.RunLock(model_dir), deferred_signals():
            step = _step(os.path.join(model_dir, run_dir.CHECKPOINT_DIR))
            committed = _committed_step(resume)
            if step <= committed:
                printer(f"training stopped by an error; nothing new to commit ({resume} holds "
                        f"step {committed}, the run folder step {step})")
                return
            sync_out(model_dir, resume)
            if step > start_step:
                add_ledger_row(root, make_row(step))
            printer(f"training stopped by an error: its checkpoint of step {step} is committed "
                    f"in {resume}" + (" with its ledger row" if step > start_step else
                                      " (trained before this chunk, without a row)"))
    except Exception as e:  # noqa: BLE001
        printer(f"training stopped by an error, and its checkpoint could not be committed "
                f"({type(e).__name__}: {e}); it stays in {model_dir}")


MIN_NEXT_STAGE_S = 120.0
"""Seconds a chunk must have left, after finishing its stage, to start the next stage (whose
pairs are first re-made from the finished stages' predictions)."""


def run_stages(make_config, first: int, last: int, root: str, time_limit_s: float, device: str,
               printer=print, commit: str | None = None,
               min_next_s: float = MIN_NEXT_STAGE_S, clock=time.monotonic,
               step_back: bool = False) -> list:
    """:func:`run_chunk` of stage ``first`` (``make_config(k)``: stage k's configuration), then,
    where that chunk finished its stage and ``last`` is further on, the next stage's chunk in the
    time left, and so on: a stage's leftover minutes are spent on the next one. With
    ``time_limit_s`` 0 (no limit) each stage trains to its end. Returns the chunks' ledger rows.

    A stage is not started with less than ``min_next_s`` of ``time_limit_s`` left (``clock``:
    seconds, for the time spent). ``step_back``: as in :func:`run_chunk`, for stage ``first``.

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
        rows.append(run_chunk(make_config(stage), root, left, device, printer, commit,
                              step_back=step_back and not rows))
    return rows
