"""A training run's checkpoints, in its folder's ``checkpoint/``
(:data:`stnh_tf.training.run_dir.CHECKPOINT_DIR`): written atomically at every epoch end
(:class:`AtomicCheckpoint`: ``ckpt-<step>.weights.h5`` committed by ``state.json``,
:data:`~stnh_tf.training.run_dir.CHECKPOINT_STATE`), found (:func:`find_checkpoint`), checked
without a model (:func:`check_weights_file`), restored (:func:`load_checkpoint`) and copied
into another folder (:func:`copy_checkpoint`). The Keras
side of the run's folder: :mod:`stnh_tf.training.run_dir` itself needs no backend."""

from __future__ import annotations

import logging
import os
import re
import shutil
import tempfile
import time

import keras
import numpy as np

from stnh_tf.paths import atomic_write_json, fsync_replace, inside, read_json
from stnh_tf.training import file_parts
from stnh_tf.training.run_dir import CHECKPOINT_STATE

CHECKPOINT_WEIGHTS = "ckpt.weights.h5"  # legacy single-file name, still read
CHECKPOINT_WEIGHTS_PATTERN = "ckpt-{step:08d}.weights.h5"
_WEIGHTS_NAME = re.compile(r"ckpt-(\d{8,})\.weights\.h5")  # CHECKPOINT_WEIGHTS_PATTERN's names
_log = logging.getLogger(__name__)


def _seed_variables(model):
    """The model's random-seed state variables (dropout), in model order."""
    return [v for v in model.variables if "seed_generator_state" in v.path]


def _seed_states(model):
    # A list in model order: variable paths ("seed_generator_3/...") depend on how many seed
    # generators the process created before, so they cannot identify the state across processes.
    return [np.asarray(keras.ops.convert_to_numpy(v)).tolist() for v in _seed_variables(model)]


def _restore_seed_states(model, states):
    variables = _seed_variables(model)
    if isinstance(states, dict):  # checkpoints written before states were kept in order
        states = list(states.values())
    if len(states) != len(variables):
        raise RuntimeError(f"checkpoint holds {len(states)} random-seed states; the model has "
                           f"{len(variables)}.")
    for v, state in zip(variables, states):
        v.assign(np.asarray(state, dtype=keras.backend.standardize_dtype(v.dtype)))


class AtomicCheckpoint(keras.callbacks.Callback):
    """Saves weights + optimizer state (and dropout RNG state) at every epoch end, atomically.

    The weights go to a new file per step (``ckpt-<step>.weights.h5``, written under a temporary
    name, fsynced, renamed); ``state.json``, written the same way, names that file and is the
    commit point; only then are older weight files removed. A kill -9 at any moment leaves
    ``state.json`` naming a complete file of the step it records."""

    def __init__(self, directory, guard=None):
        super().__init__()
        self.directory = directory
        self.guard = guard
        os.makedirs(directory, exist_ok=True)

    @property
    def state_path(self):
        return os.path.join(self.directory, CHECKPOINT_STATE)

    def on_epoch_end(self, epoch, logs=None):
        if self.guard is not None and self.guard.bad_step is not None:
            return
        step = int(keras.ops.convert_to_numpy(self.model.optimizer.iterations))
        name = CHECKPOINT_WEIGHTS_PATTERN.format(step=step)
        tmp = os.path.join(self.directory, f"tmp-{os.getpid()}.weights.h5")
        try:
            self.model.save_weights(tmp)
            fsync_replace(tmp, os.path.join(self.directory, name))
        except BaseException:  # (a full disk: no partial file left to fill it further)
            if os.path.exists(tmp):
                os.remove(tmp)
            raise
        atomic_write_json(self.state_path, {"step": step, "epoch": epoch + 1, "time": time.time(),
                                             "weights": name,
                                             "seed_states": _seed_states(self.model),
                                             "logs": {k: float(v)
                                                      for k, v in (logs or {}).items()}})
        for old in os.listdir(self.directory):  # superseded (or never committed) weight files
            if old != name and old.endswith(".weights.h5") and not old.startswith("tmp-"):
                os.remove(os.path.join(self.directory, old))


def read_checkpoint_state(directory) -> dict | None:
    """The committed ``state.json`` of the checkpoint folder ``directory`` (None if there is none).

    Raises ``ValueError`` naming the file if it is not valid JSON, not a JSON object, or records
    no integer ``step``."""
    state_path = os.path.join(directory, CHECKPOINT_STATE)
    if not os.path.exists(state_path):
        return None
    state = read_json(state_path, "checkpoint state")
    if not isinstance(state, dict) or isinstance(state.get("step"), bool) \
            or not isinstance(state.get("step"), int):
        raise ValueError(f"checkpoint state {state_path!r} is not a checkpoint's state (a JSON "
                         "object with an integer 'step').")
    return state


def checkpoint_weights_path(directory) -> str | None:
    """The weights file the committed ``state.json`` of ``directory`` names (None if none). The
    name must be a file inside ``directory`` (:func:`stnh_tf.paths.inside`; else
    ``ValueError``)."""
    state = read_checkpoint_state(directory)
    if state is None:
        return None
    path = inside(directory, state.get("weights", CHECKPOINT_WEIGHTS),
                  f"{os.path.join(directory, CHECKPOINT_STATE)!r}, its 'weights'")
    return path if os.path.isfile(path) else None


def find_checkpoint(directory) -> tuple | None:
    """``(weights_path, step, state)`` of the checkpoint in ``directory`` to resume from (None if
    there is none): the file the committed ``state.json`` names, with its step and state; or,
    without a ``state.json`` (deleted, or a kill between a first checkpoint's two files), the
    newest complete ``ckpt-<step>.weights.h5``, its step read from its name, and ``state`` None.

    Raises:
      FileNotFoundError: ``state.json`` names a file that is missing (both named; a restart from
        step 0 would replace the checkpoint). ``ValueError``: as :func:`read_checkpoint_state`.
    """
    state = read_checkpoint_state(directory)
    if state is not None:
        state_path = os.path.join(directory, CHECKPOINT_STATE)
        path = inside(directory, state.get("weights", CHECKPOINT_WEIGHTS),
                      f"{state_path!r}, its 'weights'")
        if not os.path.isfile(path):
            raise FileNotFoundError(
                f"checkpoint state {state_path} names {path}, which is missing: not restarting "
                "from step 0 over it; put the file back, or move the folder away to train anew.")
        return path, state["step"], state
    found = sorted((int(m.group(1)), m.group(0)) for m in map(
        _WEIGHTS_NAME.fullmatch, os.listdir(directory) if os.path.isdir(directory) else ()) if m)
    return (os.path.join(directory, found[-1][1]), found[-1][0], None) if found else None


def load_checkpoint(model, directory) -> int:
    """Restore the checkpoint of ``directory`` (:func:`find_checkpoint`) into a compiled
    ``model``; returns its step (0 if there is none). One found without ``state.json`` is
    resumed with a logged warning (its dropout random state starts afresh).

    Raises:
      ValueError: naming the weights file, when it cannot be read (truncated, not HDF5, another
        model's) or holds another step than its state (or name) says; nothing is deleted.
      FileNotFoundError: as :func:`find_checkpoint`.
    """
    found = find_checkpoint(directory)
    if found is None:
        return 0
    weights, want, state = found
    state_path = os.path.join(directory, CHECKPOINT_STATE)
    model.optimizer.build(model.trainable_variables)
    try:
        model.load_weights(weights)
    except (OSError, ValueError, KeyError) as e:
        raise ValueError(f"cannot load the checkpoint {weights} ({type(e).__name__}: {e}); it is "
                         "kept: put a complete copy back, or move the folder away to train "
                         "anew.") from None
    if state is None or "seed_states" not in state:  # (none, or one copy_checkpoint made)
        _log.warning("%s %s: resuming from %s, step %d (the dropout random state starts "
                     "afresh).", state_path, "is missing" if state is None else
                     "records no random states", weights, want)
    else:
        _restore_seed_states(model, state["seed_states"])
    step = int(keras.ops.convert_to_numpy(model.optimizer.iterations))
    if step != want:
        raise ValueError(f"checkpoint {weights} holds step {step} but "
                         f"{state_path if state else 'its name'} says {want}.")
    return step


def check_weights_file(path: str, step: int) -> None:
    """That the checkpoint weights file ``path`` reads whole, without a model: an HDF5 file
    (h5py, which Keras saves them with) whose every dataset reads, with at least one, and whose
    optimizer step count (``optimizer/vars/0``, where it holds a scalar integer there) is
    ``step``, the step its state names. Reads only.

    Raises:
      ValueError: naming ``path`` and what is wrong (truncated, not HDF5, empty, another step).
    """
    import h5py

    try:
        with h5py.File(path, "r") as f:
            datasets = []
            f.visititems(lambda _, item: datasets.append(item[()])
                         if isinstance(item, h5py.Dataset) else None)
            held = f.get("optimizer/vars/0")
            held = int(held[()]) if isinstance(held, h5py.Dataset) and held.shape == () \
                and held.dtype.kind in "iu" else None
    except (OSError, ValueError, KeyError, RuntimeError) as e:
        raise ValueError(f"the checkpoint {path} cannot be read ({type(e).__name__}: "
                         f"{str(e).splitlines()[0] if str(e) else ''})") from None
    if not datasets:
        raise ValueError(f"the checkpoint {path} holds no weights")
    if held is not None and held != step:
        raise ValueError(f"the checkpoint {path} holds step {held}, not step {step} as its "
                         "state says")


def _weights_files(folder: str, name: str) -> list:
    """The files of ``folder`` that keep the checkpoint weights ``name`` (whole, its parts, their
    manifest, a copy cut short)."""
    return [f for f in os.listdir(folder) if f == name or f.startswith(f"{name}.")]


def copy_checkpoint(src_dir, dst_dir, extra_files=(), max_bytes=None) -> int:
    """Copy the checkpoint of ``src_dir`` (the weights :func:`find_checkpoint` finds and the
    state naming them) and ``extra_files`` into ``dst_dir``, updated in place so that a kill at
    any moment leaves its ``state.json`` naming complete weights: each extra file written
    beside its place and renamed; the weights under their step's name (with ``max_bytes``,
    those over it as parts, :func:`stnh_tf.training.file_parts.write_parts`; whole ones written
    beside, fsynced and renamed), unless ``dst_dir`` holds them already; ``state.json`` last
    (``src_dir``'s; without one, the one there for the same weights, else one naming them), the
    commit point as in :class:`AtomicCheckpoint`; then other weights removed. Returns the
    checkpoint's step.

    Raises:
      ValueError: ``dst_dir``'s state names other weights of the same name and step (two runs
        that trained the same steps): nothing is replaced.
    """
    weights, step, state = find_checkpoint(src_dir)
    name, pid = os.path.basename(weights), os.getpid()
    os.makedirs(dst_dir, exist_ok=True)
    try:
        held = read_checkpoint_state(dst_dir)
    except ValueError:  # a broken state: replaced below
        held = None
    named = bool(held) and held.get("weights") == name
    same = named and _same_weights(weights, dst_dir)
    if named and not same and held.get("step") == step:
        raise ValueError(f"{dst_dir} holds other weights of step {step} ({name}) than "
                         f"{weights}: not replaced (two runs trained the same steps).")
    for path in extra_files:
        tmp = os.path.join(dst_dir, f"{os.path.basename(path)}.tmp-{pid}")
        shutil.copy2(path, tmp)
        os.replace(tmp, os.path.join(dst_dir, os.path.basename(path)))
    if not same:
        for f in _weights_files(dst_dir, name):  # a copy cut short, which no state names
            if f != name:
                os.remove(os.path.join(dst_dir, f))
        size = max_bytes or max(os.path.getsize(weights), 1)
        if os.path.getsize(weights) <= size:  # whole: written beside, then renamed
            shutil.copy2(weights, os.path.join(dst_dir, f"{name}.tmp-{pid}"))
            fsync_replace(os.path.join(dst_dir, f"{name}.tmp-{pid}"), os.path.join(dst_dir, name))
        else:
            file_parts.write_parts(weights, os.path.join(dst_dir, name), size)
    if state is None:
        state = held if same else {"step": int(step), "weights": name}
    atomic_write_json(os.path.join(dst_dir, CHECKPOINT_STATE), state)
    kept = set(_weights_files(dst_dir, name))
    for f in os.listdir(dst_dir):  # the weights of other steps, and copies cut short
        if f.startswith("ckpt") and ".weights.h5" in f and f not in kept or ".tmp-" in f:
            os.remove(os.path.join(dst_dir, f))
    return int(step)


def _same_weights(weights: str, folder: str) -> bool:
    """Whether ``folder`` holds the file ``weights`` under its name, whole or in parts, with the
    same bytes (the parts checked against their manifest)."""
    kept = os.path.join(folder, os.path.basename(weights))
    with tempfile.TemporaryDirectory() as tmp:
        try:
            if file_parts.in_parts(kept):
                file_parts.read_whole(kept, os.path.join(tmp, "whole"))
                kept = os.path.join(tmp, "whole")
            with open(kept, "rb") as a, open(weights, "rb") as b:
                return a.read() == b.read()
        except (OSError, ValueError):
            return False
