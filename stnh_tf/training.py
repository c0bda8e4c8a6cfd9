"""Stage and sequence training: one implementation of the paper's recipe for every model kind.

``train(config)`` builds the model named by the config (single STN-Homography stage, sequence
model, or the HomographyNet baseline), compiles it with the paper's optimizer and losses, and fits
it on the TFRecord dataset in ``config.data_dir`` with:

* SGD, momentum 0.9, batch 64; learning rate rising linearly 0 -> 0.05 over ``warmup_steps``, then
  cosine decay to 0 over the remaining ``train_steps - warmup_steps`` (Keras' ``CosineDecay`` with
  ``warmup_target``): the paper's 1,000 + 90,000 steps by default. ``lr_schedule="step"`` is
  DeTone et al.'s schedule instead (the learning rate divided by 10 after each third of the
  steps), which the binaries preset for ``--model=homographynet`` (:data:`stnh_tf.train_config.MODEL_DEFAULTS`).
* Atomic periodic checkpoints (model + optimizer + RNG state) every ``checkpoint_every`` steps; a
  killed run restarted with the same command resumes at the last checkpoint, repositions the data
  stream at that step, and follows the same schedule to the same final step.
* TensorBoard logs (both loss terms, learning rate, validation MACE) and console progress.
* A non-finite loss stops training with an error naming the step and the last good checkpoint.
* ``strategy="mirrored"`` runs under ``tf.distribute.MirroredStrategy``.

Two data sources, same losses and schedule: the TFRecords in ``data_dir`` (TensorFlow backend), or
``image_dir``: stage-1 pairs generated on the fly from a folder of images by
:class:`stnh_tf.data.PairStream` (NumPy/OpenCV in worker processes; any Keras backend, e.g. JAX on
a GPU machine without TensorFlow). ``image_dir`` with ``samples_per_image=N`` and ``seed=S`` gives
exactly the pairs ``data_prep.make_dataset --samples_per_image=N --seed=S`` writes (shuffled
differently); ``fresh_pairs`` draws new pairs every data epoch instead. With ``in_memory`` the set
is generated once (:func:`stage_pairs`), and stage k > 1 trains from the folder too: its pairs are
made in memory from the predictions of the ``prev_stages`` models, as make_stage_dataset makes
them.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import logging
import math
import os
import shutil
import time
from typing import Callable

import keras
import numpy as np

from stnh_tf import losses as losses_lib
from stnh_tf import models
from stnh_tf.paths import atomic_write_json, fsync_replace, inside, read_json
from stnh_tf.train_config import (FOUR_POINT_KINDS, OPTIMIZER_NAMES, RESUME_FREE_FIELDS,
                                  TrainConfig)


def _sgd(cfg, schedule, **common):
    return keras.optimizers.SGD(learning_rate=schedule, momentum=cfg.momentum, **common)


def _adam(cfg, schedule, **common):
    return keras.optimizers.Adam(learning_rate=schedule, **common)


def _adamw(cfg, schedule, **common):
    return keras.optimizers.AdamW(learning_rate=schedule, **common)


# The optimizers by name: ``f(cfg, schedule, weight_decay=..., global_clipnorm=...)``.
OPTIMIZERS = {"sgd": _sgd, "adam": _adam, "adamw": _adamw}
assert sorted(OPTIMIZERS) == sorted(OPTIMIZER_NAMES)

FINAL_MODEL = "model.keras"
CONFIG_FILE = "config.json"
RESULT_FILE = "result.json"
LOGS_DIR = "logs"
# Written into config.json with the fields: what makes a folder a training run (read_run_config).
CONFIG_MARKER = {"format": "stnh_tf.train_config", "format_version": 1}
CHECKPOINT_DIR = "checkpoint"
CHECKPOINT_WEIGHTS = "ckpt.weights.h5"  # legacy single-file name, still read
CHECKPOINT_WEIGHTS_PATTERN = "ckpt-{step:08d}.weights.h5"
CHECKPOINT_STATE = "state.json"
# What a run writes in model_dir besides config.json: all that --overwrite deletes (remove_run).
RUN_ENTRIES = (FINAL_MODEL, RESULT_FILE, CHECKPOINT_DIR, LOGS_DIR)
# The fields by which a config.json written before CONFIG_MARKER is recognised as a run's.
_LEGACY_CONFIG_KEYS = frozenset({"model", "model_dir", "stage", "train_steps", "warmup_steps",
                                 "batch_size", "checkpoint_every", "seed"})

_log = logging.getLogger(__name__)


class TrainingDiverged(RuntimeError):
    """Raised when the loss becomes non-finite."""


# ------------------------------------------------------------------------------------------------
# Pieces
# ------------------------------------------------------------------------------------------------
def step_boundaries(train_steps: int) -> list:
    """The last steps (0-based) of the first and second thirds of ``train_steps``:
    ``[T // 3 - 1, 2 T // 3 - 1]`` (``[29999, 59999]`` for DeTone et al.'s 90,000 iterations)."""
    return [train_steps // 3 - 1, 2 * train_steps // 3 - 1]


def learning_rate_schedule(cfg: TrainConfig):
    """The learning rate as a function of the 0-based step (Keras evaluates it at
    ``optimizer.iterations`` before each update, so update ``i`` uses ``lr(i)``).

    * ``lr_schedule="cosine"`` (the paper's): linear warm-up from 0 to ``learning_rate`` over
      ``warmup_steps``, then cosine decay to 0 over ``train_steps - warmup_steps`` (Keras' own
      ``CosineDecay``).
    * ``lr_schedule="step"`` (DeTone et al.'s): ``learning_rate`` for the first third of
      ``train_steps``, a tenth of it for the second, a hundredth for the last (Keras'
      ``PiecewiseConstantDecay`` at :func:`step_boundaries`; as Caffe's "step" policy,
      ``lr * 0.1 ** floor(i / (T / 3))``, for ``T`` a multiple of 3). No warm-up.
    """
    if cfg.lr_schedule == "step":
        lr = cfg.learning_rate
        return keras.optimizers.schedules.PiecewiseConstantDecay(
            step_boundaries(cfg.train_steps), [lr, lr / 10.0, lr / 100.0])
    return keras.optimizers.schedules.CosineDecay(
        initial_learning_rate=0.0 if cfg.warmup_steps else cfg.learning_rate,
        decay_steps=max(cfg.train_steps - cfg.warmup_steps, 1),
        alpha=0.0,
        warmup_target=cfg.learning_rate if cfg.warmup_steps else None,
        warmup_steps=cfg.warmup_steps,
    )


def build_model(cfg: TrainConfig) -> keras.Model:
    if cfg.model == "stn":
        return models.build_stn_homography(batch_norm=cfg.batch_norm, dropout=cfg.dropout)
    if cfg.model == "homographynet":  # DeTone's network: BatchNorm always, dropout twice
        return models.build_homographynet(dropout=cfg.dropout)
    if cfg.model == "homographynet_gap":
        return models.build_homographynet_gap(batch_norm=cfg.batch_norm, dropout=cfg.dropout)
    return models.build_sequence_stn_homography(cfg.num_stages, batch_norm=cfg.batch_norm,
                                                dropout=cfg.dropout)


def l2_term_weight(cfg: TrainConfig) -> float:
    """The loss weight of :func:`stnh_tf.losses.h_bar_l2` (a mean over H_bar's 8 entries):
    ``l2_weight``, times 8 with ``l2_reduction="sum"`` (a sum over the 8 entries)."""
    return cfg.l2_weight * (8.0 if cfg.l2_reduction == "sum" else 1.0)


def loss_spec(cfg: TrainConfig):
    """(losses, loss_weights, metrics) dicts keyed by the model's output names. Raises
    ``ValueError`` for loss settings the model kind cannot use (:meth:`TrainConfig.check_losses`)."""
    cfg.check_losses()
    l2 = l2_term_weight(cfg)
    if cfg.model == "stn":
        return ({"h_bar": losses_lib.h_bar_l2, "patch_a_warp": losses_lib.photometric_l1},
                {"h_bar": l2, "patch_a_warp": cfg.l1_weight},
                {"h_bar": [losses_lib.MeanCornerError()]})
    if cfg.model in FOUR_POINT_KINDS:
        return ({"offsets": "mse"}, {"offsets": 1.0}, {"h_bar": [losses_lib.MeanCornerError()]})
    weights = list(cfg.stage_loss_weights) or [1.0] * cfg.num_stages
    losses, loss_weights, metrics = {}, {}, {}
    h_names, w_names = models.sequence_output_names(cfg.num_stages)
    for k, (hn, wn) in enumerate(zip(h_names, w_names)):
        losses[hn], loss_weights[hn] = losses_lib.h_bar_l2, l2 * weights[k]
        losses[wn], loss_weights[wn] = losses_lib.photometric_l1, cfg.l1_weight * weights[k]
        metrics[hn] = [losses_lib.MeanCornerError()]
    return losses, loss_weights, metrics


def _homographynet_targets(x, y, w):
    from stnh_tf import geometry

    h = geometry.denormalize_homography(geometry.vector_to_matrix(y["h_bar"]))
    offsets = keras.ops.reshape(geometry.homography_to_offsets(h), (-1, 8))
    offsets = offsets / models.HOMOGRAPHYNET_SCALE
    # patch_a_warp carries no loss (HomographyNet has no photometric term) but Keras matches the
    # targets to every output.
    return (x, {"offsets": offsets, "h_bar": y["h_bar"], "patch_a_warp": y["patch_a_warp"]},
            {"offsets": w["h_bar"], "h_bar": w["h_bar"], "patch_a_warp": w["patch_a_warp"]})


def _sequence_targets(x, y, w, num_stages):
    ys, ws = {}, {}
    for hn, wn in zip(*models.sequence_output_names(num_stages)):
        ys[hn], ys[wn] = y["h_bar"], y["patch_a_warp"]
        ws[hn], ws[wn] = w["h_bar"], w["patch_a_warp"]
    return x, ys, ws


def targets_for(cfg: TrainConfig) -> Callable | None:
    """Map the dataset's ``(x, y, sample_weight)`` (keys ``h_bar``, ``patch_a_warp``) onto the
    model's output names: tensors inside ``tf.data`` or NumPy batches in a ``PyDataset``. The
    mapper is picklable (generator worker processes may be spawned)."""
    if cfg.model == "stn":
        return None
    if cfg.model in FOUR_POINT_KINDS:
        return _homographynet_targets
    return functools.partial(_sequence_targets, num_stages=cfg.num_stages)


def build_optimizer(cfg: TrainConfig) -> keras.optimizers.Optimizer:
    """``cfg.optimizer`` (:data:`OPTIMIZERS`) on :func:`learning_rate_schedule`, with
    ``cfg.weight_decay`` (decoupled; Keras' ``weight_decay``) and ``cfg.clipnorm`` (Keras'
    ``global_clipnorm``). ``optimizer="adam"`` with a weight decay equals ``"adamw"``."""
    common = {"weight_decay": cfg.weight_decay or None,
              "global_clipnorm": cfg.clipnorm or None}
    if cfg.optimizer == "adamw":
        common["weight_decay"] = cfg.weight_decay  # AdamW's own default is 0.004, not 0
    return OPTIMIZERS[cfg.optimizer](cfg, learning_rate_schedule(cfg), **common)


def compile_model(model, cfg: TrainConfig):
    losses, loss_weights, metrics = loss_spec(cfg)
    optimizer = build_optimizer(cfg)
    model.compile(optimizer=optimizer, loss=losses, loss_weights=loss_weights,
                  weighted_metrics=metrics)
    return model


# ------------------------------------------------------------------------------------------------
# Callbacks
# ------------------------------------------------------------------------------------------------
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
        self.model.save_weights(tmp)
        fsync_replace(tmp, os.path.join(self.directory, name))
        atomic_write_json(self.state_path, {"step": step, "epoch": epoch + 1, "time": time.time(),
                                             "weights": name,
                                             "seed_states": _seed_states(self.model),
                                             "logs": {k: float(v) for k, v in (logs or {}).items()}})
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


def load_checkpoint(model, directory) -> int:
    """Restore the latest checkpoint in ``directory`` into a compiled ``model``; returns its step
    (0 if there is none)."""
    weights = checkpoint_weights_path(directory)
    state_path = os.path.join(directory, CHECKPOINT_STATE)
    if weights is None:
        return 0
    state = read_checkpoint_state(directory)
    model.optimizer.build(model.trainable_variables)
    model.load_weights(weights)
    _restore_seed_states(model, state.get("seed_states", []))
    step = int(keras.ops.convert_to_numpy(model.optimizer.iterations))
    if step != state["step"]:
        raise RuntimeError(f"checkpoint {weights} holds step {step} but {state_path} says "
                           f"{state['step']}.")
    return step


class NonFiniteGuard(keras.callbacks.Callback):
    """Stops training at the first non-finite loss and remembers the step."""

    def __init__(self):
        super().__init__()
        self.bad_step = None

    def on_train_batch_end(self, batch, logs=None):
        loss = (logs or {}).get("loss")
        if loss is not None and not math.isfinite(float(loss)):
            self.bad_step = int(keras.ops.convert_to_numpy(self.model.optimizer.iterations))
            self.model.stop_training = True


class ProgressLogger(keras.callbacks.Callback):
    """One console line every ``every`` steps: step, losses, learning rate, steps/s."""

    def __init__(self, every, total, printer=print):
        super().__init__()
        self.every, self.total, self.printer = max(int(every), 1), total, printer
        self._t0 = self._s0 = None

    def on_train_batch_end(self, batch, logs=None):
        step = int(keras.ops.convert_to_numpy(self.model.optimizer.iterations))
        if self._t0 is None:
            self._t0, self._s0 = time.time(), step
        if step % self.every and step != self.total:
            return
        rate = (step - self._s0) / max(time.time() - self._t0, 1e-9)
        lr = float(keras.ops.convert_to_numpy(self.model.optimizer.learning_rate))
        parts = " ".join(f"{k}={float(v):.5g}" for k, v in sorted((logs or {}).items()))
        self.printer(f"step {step}/{self.total} lr={lr:.5g} {parts} ({rate:.2f} steps/s)")

    def on_epoch_end(self, epoch, logs=None):
        vals = {k: v for k, v in (logs or {}).items() if k.startswith("val_")}
        if vals:
            step = int(keras.ops.convert_to_numpy(self.model.optimizer.iterations))
            self.printer(f"step {step} validation " +
                         " ".join(f"{k}={float(v):.5g}" for k, v in sorted(vals.items())))


# ------------------------------------------------------------------------------------------------
# The run
# ------------------------------------------------------------------------------------------------
def read_run_config(config_path: str) -> dict:
    """The saved fields of the training run whose ``config.json`` is ``config_path``.

    A run's ``config.json`` holds :data:`CONFIG_MARKER` (``format`` and ``format_version``) with
    the :class:`TrainConfig` fields (:func:`prepare_model_dir` writes it); one written before the
    marker existed is recognised by holding every field of :data:`_LEGACY_CONFIG_KEYS`.

    Raises:
      ValueError: naming the file, when it is not valid JSON, not a JSON object, or not a training
        run's configuration (its folder is then not a run: nothing is resumed or deleted there).
    """
    doc = read_json(config_path, "training configuration")
    if isinstance(doc, dict) and doc.get("format") == CONFIG_MARKER["format"]:
        if doc.get("format_version") != CONFIG_MARKER["format_version"]:
            raise ValueError(f"{config_path!r} has format_version {doc.get('format_version')!r}; "
                             f"this version of stnh_tf reads version "
                             f"{CONFIG_MARKER['format_version']}.")
    elif not (isinstance(doc, dict) and "format" not in doc and _LEGACY_CONFIG_KEYS <= set(doc)):
        raise ValueError(f"{config_path!r} is not the configuration of a stnh-tf training run (no "
                         f"\"format\": \"{CONFIG_MARKER['format']}\"); its folder is neither "
                         "resumed nor deleted, with or without --overwrite: choose another "
                         "--model_dir, or move the folder away.")
    return {k: v for k, v in doc.items() if k not in CONFIG_MARKER}


def _config_diff(cfg: TrainConfig, config_path: str) -> dict:
    """``{field: (old, new)}`` for the fields that differ from a saved run's and matter
    (``ValueError`` if ``config_path`` is not a run's: :func:`read_run_config`)."""
    if not os.path.exists(config_path):
        return {}
    old = read_run_config(config_path)
    new = cfg.to_json()
    # A field the saved run predates had its default value then (e.g. optimizer="sgd").
    old = {**TrainConfig().to_json(), **old}
    diff = {k: (old.get(k), new[k]) for k in new
            if k not in RESUME_FREE_FIELDS and old.get(k) != new[k]}
    # The folders may move between a run and its resumption, but not the kind of source: TFRecords
    # and generated pairs come in different orders.
    kinds = tuple("data_dir" if c.get("data_dir") else "image_dir" for c in (old, new))
    if kinds[0] != kinds[1]:
        diff["source"] = kinds
    return diff


def prepare_model_dir(cfg: TrainConfig, overwrite: bool = False) -> bool:
    """Make ``model_dir`` ready for training and write its ``config.json`` (with
    :data:`CONFIG_MARKER`). Returns True when this starts a new run there (there was no
    ``config.json``), False when it resumes one.

    ``model_dir`` must be missing, empty, or a training run (its ``config.json`` is one of ours:
    :func:`read_run_config`); any other folder is refused (``FileExistsError``/``ValueError``),
    with or without ``overwrite``. A finished run is refused without ``overwrite``, and so is an
    unfinished run of another configuration. ``overwrite`` deletes, from a finished run or a run
    of another configuration, only what a run writes (:func:`remove_run`; other files in the
    folder stay); an unfinished run of the same configuration is resumed even then, so that
    re-running an interrupted ``--overwrite`` command continues it instead of wiping its
    checkpoints. :func:`train` runs every check of the flags and data (:func:`check_start`)
    before this."""
    final = os.path.join(cfg.model_dir, FINAL_MODEL)
    config_path = os.path.join(cfg.model_dir, CONFIG_FILE)
    if os.path.exists(cfg.model_dir) and not os.path.isdir(cfg.model_dir):
        raise NotADirectoryError(f"model_dir {cfg.model_dir} exists and is not a folder.")
    if os.path.isdir(cfg.model_dir) and os.listdir(cfg.model_dir) \
            and not os.path.isfile(config_path):
        raise FileExistsError(f"model_dir {cfg.model_dir} is not empty and holds no training run "
                              f"(no {CONFIG_FILE}); it is not trained into or deleted, with or "
                              "without --overwrite: choose a new or empty folder.")
    diff = _config_diff(cfg, config_path)
    if os.path.exists(final) and not overwrite:
        raise FileExistsError(f"{cfg.model_dir} holds a finished model ({final}); pass --overwrite "
                              "to train it again.")
    if overwrite and (os.path.exists(final) or diff):
        remove_run(cfg.model_dir)
        diff = {}
    os.makedirs(cfg.model_dir, exist_ok=True)
    if not os.access(cfg.model_dir, os.W_OK):
        raise PermissionError(f"model_dir {cfg.model_dir} is not writable.")
    if diff:
        raise ValueError(f"{cfg.model_dir} holds an unfinished run with a different configuration "
                         f"{diff} (old, new); use the same flags to resume, or --overwrite.")
    new_run = not os.path.exists(config_path)
    atomic_write_json(config_path, {**cfg.to_json(), **CONFIG_MARKER})
    return new_run


def remove_run(model_dir: str) -> None:
    """Delete what a training run writes in ``model_dir`` (:data:`RUN_ENTRIES` and its temporary
    files; ``config.json`` last, so that a deletion cut short still leaves a run) and nothing
    else."""
    names = os.listdir(model_dir)
    temporary = sorted(n for n in names if n.startswith("tmp-") and n.endswith(FINAL_MODEL)
                       or ".json.tmp-" in n)
    for name in [*RUN_ENTRIES, *temporary, CONFIG_FILE]:
        path = os.path.join(model_dir, name)
        if os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path)
        elif os.path.lexists(path):
            os.remove(path)


def _undo_new_run(model_dir: str, made_dir: bool) -> None:
    """After a failed start of a new run: unless a checkpoint was committed (then the same
    command resumes it), remove what the start wrote (:func:`remove_run`), and ``model_dir``
    itself if the start created it, so that the folder is as it was and a corrected command
    starts cleanly."""
    if os.path.exists(os.path.join(model_dir, CHECKPOINT_DIR, CHECKPOINT_STATE)) \
            or not os.path.isdir(model_dir):
        return
    remove_run(model_dir)
    if made_dir and not os.listdir(model_dir):
        os.rmdir(model_dir)


def check_start(cfg: TrainConfig) -> None:
    """Every check of ``cfg``'s flags and data that can fail before training, run by
    :func:`train` before ``model_dir`` is touched, so that a bad flag never costs a finished run
    under ``--overwrite`` nor leaves files behind: the fields (:meth:`TrainConfig.validate`),
    the losses (:func:`loss_spec`), the backend's strategy; the dataset (a ``train`` split of
    this stage holding at least one batch, its shards and the validation split's present with
    their recorded sizes) or the image folders (at least one batch of pairs); the models that
    ``init_from`` and ``prev_stages`` name.

    Raises:
      ValueError / OSError (``FileNotFoundError``, ``data.ShardError``): naming the flag, folder
        or file.
    """
    from stnh_tf import data, sources

    cfg.validate()
    loss_spec(cfg)
    if keras.backend.backend() != "tensorflow":
        _strategy(cfg)
    if cfg.image_dir:
        data.PairBatches(sources.split_folders(cfg.image_dir), cfg.batch_size,
                         samples_per_image=cfg.samples_per_image, cache_images=False)
        if cfg.val_samples and cfg.val_image_dir:
            data.PairBatches(sources.split_folders(cfg.val_image_dir), cfg.batch_size,
                             shuffle=False, drop_remainder=False, cache_images=False)
    else:
        check_dataset(cfg.data_dir, "train", cfg.stage)
        data.load_split(cfg.data_dir, "train", cfg.batch_size, shuffle=False, repeat=False)
        if cfg.val_samples and has_split(cfg.data_dir, cfg.val_split):
            data.shard_paths(cfg.data_dir, cfg.val_split)
    for d in (*cfg.init_from, *cfg.prev_stages):
        path = os.path.join(d, FINAL_MODEL) if os.path.isdir(d) else d
        if not os.path.isfile(path):
            raise FileNotFoundError(f"no trained model at {d} (looked for {path}); init_from and "
                                    "prev_stages name finished training runs.")


def _strategy(cfg):
    """The tf.distribute strategy (None on other backends, which run on their default device)."""
    if keras.backend.backend() != "tensorflow":
        if cfg.strategy != "default":
            raise ValueError(f"strategy={cfg.strategy!r} needs the TensorFlow backend; this is "
                             f"{keras.backend.backend()!r}.")
        return None
    import tensorflow as tf

    if cfg.strategy == "mirrored":
        return tf.distribute.MirroredStrategy()
    return tf.distribute.get_strategy()


def _strategy_scope(cfg):
    strategy = _strategy(cfg)
    return strategy.scope() if strategy is not None else contextlib.nullcontext()


def tensorboard_available() -> bool:
    """Keras' TensorBoard callback writes through TensorFlow's summary ops."""
    return importlib.util.find_spec("tensorflow") is not None


def initialize_sequence_from(model, stage_dirs):
    """Copy the regression weights of trained single-stage models into a sequence model's stages."""
    for k, d in enumerate(stage_dirs, start=1):
        src = keras.models.load_model(os.path.join(d, FINAL_MODEL), compile=False)
        if sorted(src.output_names) != ["h_bar", "patch_a_warp"]:
            raise ValueError(f"{d} is not a single-stage STN-Homography model (its outputs are "
                             f"{sorted(src.output_names)}); init_from takes train_stage "
                             "--model=stn runs.")
        regression = src.get_layer("regression")
        model.get_layer(f"regression_{k}").set_weights(regression.get_weights())


# ------------------------------------------------------------------------------------------------
# Data streams (on top of stnh_tf.data)
# ------------------------------------------------------------------------------------------------
def check_dataset(data_dir: str, split: str, stage: int) -> dict:
    """Metadata of ``data_dir`` after checking it holds ``split`` for hierarchical ``stage``.

    Raises ``FileNotFoundError`` / ``ValueError`` with a message naming the directory when the
    dataset is missing, lacks the split, or was built for another stage (a stage-k model must be
    trained on the stage-k data that ``data_prep.make_stage_dataset`` writes).
    """
    from stnh_tf import data

    meta = data.read_metadata(data_dir)
    splits = meta.get("splits", {})
    if split not in splits:
        raise ValueError(f"dataset {data_dir} has no {split!r} split (it has {sorted(splits)}); "
                         f"generate it with data_prep.make_dataset --split={split}.")
    found = int(meta.get("stage", 1))
    if found != stage:
        hint = ("data_prep.make_dataset" if stage == 1 else
                f"data_prep.make_stage_dataset --stage={stage}")
        raise ValueError(f"dataset {data_dir} holds stage-{found} data but stage {stage} was asked "
                         f"for; build the stage-{stage} data with {hint}.")
    return meta


def has_split(data_dir: str, split: str) -> bool:
    """Whether ``data_dir`` holds a complete ``split`` (:func:`stnh_tf.data.has_split`)."""
    from stnh_tf import data

    return data.has_split(data_dir, split)


def training_stream(cfg: TrainConfig, split: str = "train", start_step: int = 0):
    """The endless, seeded training stream positioned at ``start_step``.

    The order of batches is a pure function of ``cfg.seed`` (seeded shuffle, deterministic
    interleave), so a resumed run skips the batches it has already consumed and sees exactly the
    batches an uninterrupted run would have seen.
    """
    from stnh_tf import data

    return data.load_split(cfg.data_dir, split, cfg.batch_size, shuffle=True, seed=cfg.seed,
                           repeat=True, shuffle_buffer=cfg.shuffle_buffer, cycle_length=64,
                           skip_batches=start_step)


def stage_pairs(cfg: TrainConfig, batches) -> dict:
    """``batches``' pairs (``stnh_tf.data.PairBatches``, epoch 0) for stage ``cfg.stage``, in
    the compact form (:func:`stnh_tf.batches.stack_samples`), generated with ``cfg.workers``
    processes. Stage 1: as generated; stage k > 1: re-made in memory from the predictions of
    ``cfg.prev_stages`` (:func:`stnh_tf.hierarchy.next_stage_arrays`, the paper's offline
    re-generation without TFRecords)."""
    from stnh_tf import data, hierarchy, runner

    if cfg.stage == 1:
        return data.materialize(batches, cfg.workers)
    arrays = data.materialize(batches, cfg.workers, context=True)
    stages = [runner.predictor(runner.load_model(d), batch_size=256) for d in cfg.prev_stages]
    pairs, rejected = hierarchy.next_stage_arrays(arrays, stages)
    _log.info("stage-%d pairs from %d previous stages; degenerate-rule cases %s", cfg.stage,
              len(stages), rejected)
    pairs.pop("h_prev")
    return pairs


def generated_stream(cfg: TrainConfig, split: str = "train", start_step: int = 0):
    """The endless stream of pairs generated from ``cfg.image_dir`` (mapped onto the model's
    outputs), positioned at ``start_step`` (:class:`stnh_tf.data.PairStream`, or with
    ``in_memory`` :class:`stnh_tf.data.ArrayStream` over :func:`stage_pairs`)."""
    from stnh_tf import data, sources

    del split
    if cfg.in_memory:
        if cfg.fresh_pairs:
            raise ValueError("in_memory holds one fixed set of pairs; it excludes fresh_pairs.")
        batches = data.PairBatches(sources.split_folders(cfg.image_dir), cfg.batch_size,
                                   samples_per_image=cfg.samples_per_image, seed=cfg.seed,
                                   photometric=cfg.photometric)
        return data.ArrayStream(stage_pairs(cfg, batches), batches, start_step=start_step,
                                mapper=targets_for(cfg))
    return data.PairStream(sources.split_folders(cfg.image_dir), cfg.batch_size,
                           samples_per_image=cfg.samples_per_image, seed=cfg.seed,
                           start_step=start_step, fresh_pairs=cfg.fresh_pairs,
                           mapper=targets_for(cfg), workers=cfg.workers,
                           photometric=cfg.photometric)


def generated_validation(cfg: TrainConfig):
    """The first :func:`validation_count` of the fixed pairs from ``cfg.val_image_dir`` (seed
    ``cfg.val_seed``, three per image in image order: with seed 1, make_dataset's test pairs), for
    stage ``cfg.stage``, made once in memory."""
    from stnh_tf import data, sources

    per_image = 3
    batches = data.PairBatches(sources.split_folders(cfg.val_image_dir), cfg.batch_size,
                               samples_per_image=per_image,
                               seed=cfg.val_seed, shuffle=False, drop_remainder=False,
                               max_images=-(-cfg.val_samples // per_image))
    n = validation_count(cfg, batches.num_samples)
    arrays = {k: v[:n] for k, v in stage_pairs(cfg, batches).items()}
    return data.ArraySequence(arrays, cfg.batch_size, mapper=targets_for(cfg))


def validation_count(cfg: TrainConfig, available: int) -> int:
    """Pairs per validation: ``cfg.val_samples``, at most the ``available`` ones."""
    return min(int(cfg.val_samples), int(available))


def validation_stream(cfg: TrainConfig, split: str):
    """The first :func:`validation_count` pairs of ``split`` (unshuffled, fixed), batched.
    Returns ``(dataset, batches)``."""
    from stnh_tf import data

    available = data.split_info(cfg.data_dir, split).get("num_samples", cfg.val_samples)
    n = validation_count(cfg, available)
    ds = data.load_split(cfg.data_dir, split, cfg.batch_size, shuffle=False, repeat=False,
                         drop_remainder=False)
    return ds.unbatch().take(n).batch(cfg.batch_size), -(-n // cfg.batch_size)


# CPU flags of native bfloat16 arithmetic: x86 AVX-512 BF16 and AMX, Arm BF16.
BFLOAT16_CPU_FLAGS = frozenset({"avx512_bf16", "amx_bf16", "bf16"})


def cpu_has_native_bfloat16(cpuinfo: str = "/proc/cpuinfo") -> bool | None:
    """Whether the CPU lists a bfloat16 instruction flag (:data:`BFLOAT16_CPU_FLAGS`) in
    ``cpuinfo`` (its ``flags`` lines on x86, ``Features`` on Arm); ``None`` if it cannot be read."""
    try:
        with open(cpuinfo) as f:
            text = f.read()
    except OSError:
        return None
    flags = set()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip().lower() in ("flags", "features"):
            flags.update(value.split())
    return bool(flags & BFLOAT16_CPU_FLAGS) if flags else None


def accelerator_present() -> bool:
    """Whether the Keras backend computes on a GPU/TPU rather than the CPU."""
    backend = keras.backend.backend()
    if backend == "tensorflow":
        import tensorflow as tf

        return bool(tf.config.list_physical_devices("GPU") or tf.config.list_physical_devices("TPU"))
    if backend == "jax":
        import jax

        return jax.default_backend() != "cpu"
    if backend == "torch":
        import torch

        return bool(torch.cuda.is_available())
    return False


def mixed_precision_warning(cfg: TrainConfig, cpuinfo: str = "/proc/cpuinfo") -> str | None:
    """A warning when ``cfg`` asks for mixed bfloat16 on a CPU that has no bfloat16 instructions:
    there it is emulated and a training step is many times slower than in float32 (measured on an
    AMD EPYC without AVX-512: BENCHMARKS.md), while the project's earlier CPU machine (AVX-512/AMX)
    ran bfloat16 steps 3.6x faster than float32. ``None`` on an accelerator, with float32, or where
    the CPU flags cannot be read."""
    if not cfg.mixed_precision or accelerator_present():
        return None
    if cpu_has_native_bfloat16(cpuinfo) is not False:
        return None
    return ("mixed_precision is on, but this CPU has no bfloat16 instructions (none of "
            f"{sorted(BFLOAT16_CPU_FLAGS)} in {cpuinfo}): bfloat16 is emulated and training is "
            "many times slower than in float32 here; consider --nomixed_precision.")


def _raise_shard_error(cfg: TrainConfig, error: BaseException) -> None:
    """For a ``DataLossError`` met while training on ``cfg.data_dir``: raise ``data.ShardError``
    naming the corrupted shard, found by reading the splits in use with CRC checks
    (:func:`stnh_tf.data.verify_split`, what evaluation's reader reports). Any other error:
    return (the caller re-raises it)."""
    import tensorflow as tf

    from stnh_tf import data

    if not isinstance(error, tf.errors.DataLossError):
        return
    splits = ["train"]
    if cfg.val_samples and has_split(cfg.data_dir, cfg.val_split):
        splits.append(cfg.val_split)
    for split in splits:
        try:
            data.verify_split(cfg.data_dir, split)
        except data.ShardError as bad:
            raise data.ShardError(f"training stopped on a corrupted record: {bad}") from None
    raise data.ShardError(f"training stopped on a corrupted record of {cfg.data_dir} (splits "
                          f"{splits}; every shard reads back whole now): {error}") from error


def train(cfg: TrainConfig, overwrite: bool = False, printer=print, stream_fn=None,
          extra_callbacks=()):
    """Train (or resume) the model described by ``cfg``. Returns a dict of final results.

    ``stream_fn(cfg, split, start_step)`` may replace the TFRecord stream (tests, generators);
    ``extra_callbacks`` run after the built-in ones (checkpointing comes first).

    Every check of the flags and data (:func:`check_start`) runs before ``model_dir`` is touched
    (:func:`prepare_model_dir`); if a new run then fails before its first checkpoint, what it
    wrote is removed again. A corrupted shard met while training raises ``data.ShardError``
    naming the file.
    """
    check_start(cfg)
    warning = mixed_precision_warning(cfg)
    if warning:
        _log.warning(warning)
        printer(f"warning: {warning}")
    generated = bool(cfg.image_dir)
    stream_fn = stream_fn or (generated_stream if generated else training_stream)
    made_dir = not os.path.exists(cfg.model_dir)
    new_run = prepare_model_dir(cfg, overwrite=overwrite)
    keras.utils.set_random_seed(cfg.seed)
    keras.mixed_precision.set_global_policy("mixed_bfloat16" if cfg.mixed_precision else "float32")
    train_ds = None
    try:
        with _strategy_scope(cfg):
            model = build_model(cfg)
            compile_model(model, cfg)
            ckpt_dir = os.path.join(cfg.model_dir, CHECKPOINT_DIR)
            start_step = load_checkpoint(model, ckpt_dir)
            if start_step == 0 and cfg.init_from:
                initialize_sequence_from(model, cfg.init_from)
        if start_step:
            printer(f"resuming {cfg.model_dir} from step {start_step}")
        if start_step >= cfg.train_steps:
            printer("checkpoint already at the final step")
        train_ds = stream_fn(cfg, "train", start_step)
        val_ds = val_steps = None
        if generated:
            if cfg.val_samples and cfg.val_image_dir:
                val_ds = generated_validation(cfg)
                val_steps = len(val_ds)
        else:
            mapper = targets_for(cfg)
            if cfg.val_samples and has_split(cfg.data_dir, cfg.val_split):
                val_ds, val_steps = validation_stream(cfg, cfg.val_split)
            if mapper is not None:
                train_ds = train_ds.map(mapper)
                val_ds = val_ds.map(mapper) if val_ds is not None else None
        guard = NonFiniteGuard()
        callbacks = [guard, AtomicCheckpoint(ckpt_dir, guard),
                     ProgressLogger(cfg.log_every, cfg.train_steps, printer)]
        if tensorboard_available():
            callbacks.append(keras.callbacks.TensorBoard(os.path.join(cfg.model_dir, LOGS_DIR),
                                                         update_freq=cfg.log_every,
                                                         write_graph=False))
        else:
            printer("TensorFlow is not installed: no TensorBoard logs (console progress only)")
        callbacks.extend(extra_callbacks)
        epochs = cfg.train_steps // cfg.checkpoint_every
        t0 = time.time()
        try:
            history = model.fit(train_ds, epochs=epochs,
                                initial_epoch=start_step // cfg.checkpoint_every,
                                steps_per_epoch=cfg.checkpoint_every, validation_data=val_ds,
                                validation_steps=val_steps, callbacks=callbacks, verbose=0)
        except Exception as e:
            if not generated:
                _raise_shard_error(cfg, e)
            raise
        if guard.bad_step is not None:
            last = checkpoint_weights_path(ckpt_dir)
            last_step = read_checkpoint_state(ckpt_dir)["step"] if last is not None else 0
            raise TrainingDiverged(
                f"non-finite loss at step {guard.bad_step}; last good checkpoint: "
                f"{last or '(none)'} (step {last_step}). Resuming with the same flags repeats the "
                "same batches and diverges again: check the data, or train anew with a lower "
                "--learning_rate (a new --model_dir, or --overwrite).")
        final_path = os.path.join(cfg.model_dir, FINAL_MODEL)
        tmp = os.path.join(cfg.model_dir, f"tmp-{os.getpid()}-{FINAL_MODEL}")
        model.save(tmp)
        fsync_replace(tmp, final_path)
        result = {"final_step": int(keras.ops.convert_to_numpy(model.optimizer.iterations)),
                  "wall_s_this_run": time.time() - t0,
                  "history": {k: [float(x) for x in v] for k, v in history.history.items()}}
        atomic_write_json(os.path.join(cfg.model_dir, RESULT_FILE), result)
        return result
    except BaseException:
        if new_run:
            _undo_new_run(cfg.model_dir, made_dir)
        raise
    finally:
        keras.mixed_precision.set_global_policy("float32")
        if hasattr(train_ds, "close"):  # a PairStream's generator processes
            train_ds.close()
