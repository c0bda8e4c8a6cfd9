"""A training run's folder: the files a run writes, and the rules by which a run is started,
resumed or overwritten there. Needs no deep-learning backend (the checkpoints' Keras side:
:mod:`stnh_tf.training.checkpoints`).

Layout of ``model_dir``: ``config.json`` (the :class:`~stnh_tf.training.config.TrainConfig` with
:data:`CONFIG_MARKER` and :data:`MODEL_DIGESTS`: :func:`config_document`), ``checkpoint/``
(``ckpt-<step>.weights.h5`` committed by ``state.json``: :mod:`stnh_tf.training.checkpoints`),
``logs/`` (TensorBoard), for an in-memory stage-k run ``stage_estimates_<split>.npz``
(:mod:`stnh_tf.training.stage_estimates`), and when finished ``model.keras`` and ``result.json``; while a run
trains, its lock (:class:`RunLock`, ``.stnh_tf_run.lock``).
"""

from __future__ import annotations

import dataclasses
import numbers
import os
import shutil

from stnh_tf.paths import atomic_write_json, file_sha256, read_json
from stnh_tf.training.config import MODEL_FILE_FIELDS, RESUME_FREE_FIELDS, TrainConfig
from stnh_tf.training.presets import MODEL_KINDS
from stnh_tf.training.run_lock import LOCK_FILE, RunLock  # noqa: F401 (the run's lock)

FINAL_MODEL = "model.keras"
CONFIG_FILE = "config.json"
RESULT_FILE = "result.json"
LOGS_DIR = "logs"
# Written into config.json with the fields: what makes a folder a training run (read_run_config).
CONFIG_MARKER = {"format": "stnh_tf.train_config", "format_version": 1}
# Written into config.json beside the fields: {field: [sha256 of each model file it names]} for
# the fields of MODEL_FILE_FIELDS (config_document), what a resumption compares them by.
MODEL_DIGESTS = "model_sha256"
# Written into config.json with the fields: {source field: sha256} of the data the run trains on,
# wherever it lies (data_digests); a resumption compares the sources both sides record.
DATA_DIGESTS = "data_sha256"
# The format of the record beside a chunked run's finished stage (stnh_tf.training.chunks).
STAGE_RECORD_FORMAT = "stnh_tf.chunked_stage"
CHECKPOINT_DIR = "checkpoint"  # its files: stnh_tf.training.checkpoints, committed by:
CHECKPOINT_STATE = "state.json"
# The finished stages' estimates of an in-memory stage-k run's pairs, per split
# (stnh_tf.training.stage_estimates).
ESTIMATES_FILES = {"train": "stage_estimates_train.npz", "val": "stage_estimates_val.npz"}
# What a run writes in model_dir besides config.json: all that --overwrite replaces (set_aside).
RUN_ENTRIES = (FINAL_MODEL, RESULT_FILE, CHECKPOINT_DIR, LOGS_DIR, *ESTIMATES_FILES.values())
# The fields by which a config.json written before CONFIG_MARKER is recognised as a run's (with
# their values: _legacy_config_problem).
_LEGACY_CONFIG_KEYS = frozenset({"model", "model_dir", "stage", "train_steps", "warmup_steps",
                                 "batch_size", "checkpoint_every", "seed"})
# The smallest value of the integer ones among them (as TrainConfig.validate has always checked).
_LEGACY_MINIMUMS = {"stage": 1, "train_steps": 1, "warmup_steps": 0, "batch_size": 1,
                    "checkpoint_every": 1, "seed": 0}


def _typed(value, field) -> bool:
    """Whether ``value`` (read from JSON) has the type of the TrainConfig ``field``."""
    def of(kind, v):
        if kind == "bool" or kind is bool:
            return isinstance(v, bool)
        if kind == "int" or kind is int:
            return isinstance(v, numbers.Integral) and not isinstance(v, bool)
        if kind == "float" or kind is float:
            return isinstance(v, numbers.Real) and not isinstance(v, bool)
        return isinstance(v, str)

    if field.type == "tuple":
        return isinstance(value, list) and all(of(field.metadata.get("item", str), v)
                                               for v in value)
    return of(field.type, value)


def _legacy_config_problem(doc: dict) -> str | None:
    """Why ``doc``, a ``config.json`` without :data:`CONFIG_MARKER`, is not one this project wrote
    before the marker existed (None if it is): it holds every field of
    :data:`_LEGACY_CONFIG_KEYS` and nothing but :class:`TrainConfig` fields, ``model`` is one of
    :data:`~stnh_tf.training.presets.MODEL_KINDS`, the integers of :data:`_LEGACY_MINIMUMS` are at
    least their minimum, and every value has its field's type."""
    fields = {f.name: f for f in dataclasses.fields(TrainConfig)}
    missing = sorted(_LEGACY_CONFIG_KEYS - set(doc))
    if missing:
        return f"it lacks the fields {missing}"
    unknown = sorted(set(doc) - set(fields))
    if unknown:
        return f"{unknown[:5]} are not fields of a training configuration"
    for name, value in doc.items():
        if not _typed(value, fields[name]):
            return f"its {name} is {value!r}, not of the type {fields[name].type}"
    if doc["model"] not in MODEL_KINDS:
        return f"its model {doc['model']!r} is not one of {list(MODEL_KINDS)}"
    for name, low in _LEGACY_MINIMUMS.items():
        if doc[name] < low:
            return f"its {name} is {doc[name]!r}, below {low}"
    return None


def read_run_config(config_path: str, digests: bool = False) -> dict:
    """The saved fields of the training run whose ``config.json`` is ``config_path`` (with
    ``digests``, and the model files' and the data's digests it records: :data:`MODEL_DIGESTS`,
    :data:`DATA_DIGESTS`).

    A run's ``config.json`` holds :data:`CONFIG_MARKER` (``format`` and ``format_version``) with
    the :class:`TrainConfig` fields (:func:`prepare_model_dir` writes it); one written before the
    marker existed is recognised by its fields and their values (every field of
    :data:`_LEGACY_CONFIG_KEYS`, only TrainConfig fields, each of its type, ``model`` one of
    this project's kinds, ``stage`` an integer >= 1...: :func:`_legacy_config_problem`), so that
    someone else's ``config.json`` with the same generic keys is not taken for a run.

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
    else:
        if not isinstance(doc, dict):
            why = f"it holds a JSON {type(doc).__name__}, not an object"
        elif "format" in doc:
            why = f"its format is {doc['format']!r}"
        else:
            why = _legacy_config_problem(doc)
        if why is not None:
            raise ValueError(
                f"{config_path!r} is not the configuration of a stnh-tf training run (no "
                f"\"format\": \"{CONFIG_MARKER['format']}\", and not one written before that "
                f"marker: {why}); its folder is neither resumed nor deleted, with or without "
                "--overwrite: choose another --model_dir, or move the folder away.")
    return {k: v for k, v in doc.items()
            if k not in CONFIG_MARKER and (digests or k not in (MODEL_DIGESTS, DATA_DIGESTS))}


def model_file(path: str) -> str:
    """The model file of a finished training run named by ``path``: the run folder's
    ``model.keras``, or ``path`` itself (a ``.keras`` file)."""
    return os.path.join(path, FINAL_MODEL) if os.path.isdir(path) else path


def model_digests(fields: dict) -> dict:
    """``{field: [sha256 or None, ...]}``: for each field of :data:`MODEL_FILE_FIELDS` in
    ``fields`` (a configuration's, as :meth:`TrainConfig.to_json`), the digest of each model
    file it names (:func:`model_file`, :func:`stnh_tf.paths.file_sha256`), None where there is no such file
    here."""
    return {name: [file_sha256(model_file(p))
                   if isinstance(p, str) and os.path.isfile(model_file(p)) else None
                   for p in fields.get(name) or ()] for name in MODEL_FILE_FIELDS}


def data_digests(fields: dict) -> dict:
    """``{field: sha256 or None}`` of the training data each source field of ``fields`` (a
    configuration's, as :meth:`TrainConfig.to_json`) names, wherever the data lie: ``data_dir``
    by its ``train`` split's shards as its ``metadata.json`` lists them (names, bytes, pairs,
    and the sha256 of each shard's first and last 64 KiB: records are of one size, so the
    sizes alone do not tell two datasets apart) with the split's seed and protocol;
    ``image_dir`` (its first ``max_images``), ``unlabeled_image_dir`` and
    ``unlabeled_pairs_dir`` by their listing's ids and sizes
    (:func:`stnh_tf.training.ledger.listing_digest`); ``None`` where they cannot be read here."""
    from stnh_tf.data import tfrecords
    from stnh_tf.training import ledger

    out = {}
    if fields.get("data_dir"):
        out["data_dir"] = tfrecords.split_digest(fields["data_dir"], "train")
    for name in ("image_dir", "unlabeled_image_dir", "unlabeled_pairs_dir"):
        if fields.get(name):
            found = ledger.listing_digest(fields[name],
                                          fields.get("max_images", 0) if name == "image_dir" else 0)
            out[name] = found and found["sha256"]
    return out


def config_document(cfg: TrainConfig) -> dict:
    """What a run's ``config.json`` holds (:func:`prepare_model_dir` writes it): ``cfg``'s
    fields, :data:`CONFIG_MARKER`, the digests of the model files it names
    (:data:`MODEL_DIGESTS`: :func:`model_digests`) and of its training data
    (:data:`DATA_DIGESTS`: :func:`data_digests`)."""
    fields = cfg.to_json()
    return {**fields, **CONFIG_MARKER, MODEL_DIGESTS: model_digests(fields),
            DATA_DIGESTS: data_digests(fields)}


def _resume_form(doc: dict) -> dict:
    """What of a run's configuration ``doc`` (a ``config.json``'s fields with its
    :data:`MODEL_DIGESTS`, or :func:`config_document`'s) a resumption must repeat, wherever the
    run folder, the photographs and the checkout are: every field but
    :data:`~stnh_tf.training.config.RESUME_FREE_FIELDS` (a field the run predates at its default
    value then, e.g. optimizer="sgd"); each model file of the fields of
    :data:`~stnh_tf.training.config.MODEL_FILE_FIELDS` by its content, ``sha256:<hex>`` (as
    ``doc`` records it, else as the file named is here), or, where neither says, by its path;
    and the kind of source (``source``: TFRecords and generated pairs come in different
    orders); ``val_split`` only for TFRecords, the one source reading it (an ``image_dir`` run
    saved under its former default, ``"test"``, resumes under ``"val"``)."""
    fields = {**TrainConfig().to_json(),
              **{k: v for k, v in doc.items()
                 if k not in (MODEL_DIGESTS, DATA_DIGESTS) and k not in CONFIG_MARKER}}
    recorded, here = doc.get(MODEL_DIGESTS), model_digests(fields)
    form = {k: v for k, v in fields.items() if k not in RESUME_FREE_FIELDS}
    for name in MODEL_FILE_FIELDS:
        paths = fields[name]
        if not isinstance(paths, list):  # (not a configuration this project wrote)
            continue
        saved = recorded.get(name) if isinstance(recorded, dict) else None
        if not isinstance(saved, list) or len(saved) != len(paths):
            saved = [None] * len(paths)
        form[name] = [f"sha256:{a or b}" if (a or b) else path
                      for path, a, b in zip(paths, saved, here[name])]
    form["source"] = "data_dir" if fields.get("data_dir") else "image_dir"
    if form["source"] == "image_dir":
        form.pop("val_split", None)
    return form


def _config_diff(new: TrainConfig | str, config_path: str) -> dict:
    """``{field: (old, new)}`` for what differs between the saved run whose ``config.json`` is
    ``config_path`` and ``new`` (a configuration, or another run's ``config.json``) and matters
    (:func:`_resume_form`). ``ValueError`` where a ``config.json`` is not a run's
    (:func:`read_run_config`)."""
    if not os.path.exists(config_path):
        return {}
    old_doc = read_run_config(config_path, digests=True)
    new_doc = (_keep_recorded(config_document(new), old_doc) if isinstance(new, TrainConfig)
               else read_run_config(new, digests=True))
    old, new = _resume_form(old_doc), _resume_form(new_doc)
    diff = {k: (old.get(k), v) for k, v in new.items() if old.get(k) != v}
    was, now = (d.get(DATA_DIGESTS) for d in (old_doc, new_doc))
    if isinstance(was, dict) and isinstance(now, dict):  # both record the data: the same data
        for name in sorted(was.keys() | now.keys()):  # (a source dropped or added: other data)
            pair = tuple(d[name] and f"sha256:{d[name][:12]}" if name in d else "none"
                         for d in (was, now))
            if None not in pair and pair[0] != pair[1]:  # (None: not readable where recorded)
                diff[f"{name} (its data)"] = pair
    return diff


def _keep_recorded(doc: dict, old_doc: dict) -> dict:
    """``doc`` (:func:`config_document`) with the digests the run's ``old_doc`` recorded for the
    ``init_from`` files that are not here: a resume never reads them (only a fresh start copies
    their weights), so a run resumes where they are gone (a file there with other content is
    still another configuration)."""
    saved, here = old_doc.get(MODEL_DIGESTS), doc[MODEL_DIGESTS]["init_from"]
    saved = saved.get("init_from") if isinstance(saved, dict) else None
    if not isinstance(saved, list) or len(saved) != len(here) \
            or old_doc.get("init_from") != doc.get("init_from"):
        return doc
    kept = [h if h is not None else s for h, s in zip(here, saved)]
    return {**doc, MODEL_DIGESTS: {**doc[MODEL_DIGESTS], "init_from": kept}}


def finished(model_dir: str, train_steps: int) -> bool:
    """Whether ``model_dir`` holds a finished run: its model and its ``result.json``, or the
    model without the record but with a checkpoint short of ``train_steps`` (as before). A
    model whose record a full disk or a kill lost (written last), its checkpoint at the last
    step, is not: the same command finishes it again from that checkpoint (nothing trained)."""
    if not os.path.exists(os.path.join(model_dir, FINAL_MODEL)):
        return False
    if os.path.exists(os.path.join(model_dir, RESULT_FILE)):
        return True
    try:
        state = read_json(os.path.join(model_dir, CHECKPOINT_DIR, CHECKPOINT_STATE))
        return not (isinstance(state, dict) and isinstance(state.get("step"), int)
                    and state["step"] >= train_steps)
    except (OSError, ValueError):
        return True


def previous_run_line(model_dir: str) -> str:
    """What to say where a run that ``--overwrite`` started fails after its first checkpoint:
    where the run it replaced is kept, and how to have it back."""
    aside = os.path.join(model_dir, PREVIOUS_RUN)
    return (f"the run --overwrite replaced is kept in {aside} (its model included) until this "
            f"one finishes: to have it back, move this run's files out of {model_dir} "
            f"({', '.join(n for n in _run_names(model_dir))}) and {aside}'s files up into it.")


def _check_run_folder(model_dir: str) -> None:
    """``model_dir`` is missing, empty (but for its lock) or holds a ``config.json``; else
    ``NotADirectoryError`` / ``FileExistsError`` naming it."""
    if os.path.exists(model_dir) and not os.path.isdir(model_dir):
        raise NotADirectoryError(f"model_dir {model_dir} exists and is not a folder.")
    if os.path.isdir(model_dir) and set(os.listdir(model_dir)) - {LOCK_FILE} \
            and not os.path.isfile(os.path.join(model_dir, CONFIG_FILE)):
        raise FileExistsError(f"model_dir {model_dir} is not empty and holds no training run "
                              f"(no {CONFIG_FILE}); it is not trained into or deleted, with or "
                              "without --overwrite: choose a new or empty folder.")


def check_same_run(model_dir: str, config_path: str, cfg: TrainConfig | None = None) -> None:
    """Before the checkpoint of the run whose ``config.json`` is ``config_path`` (a copy kept
    elsewhere: :func:`stnh_tf.training.chunks.sync_in`) is put into ``model_dir``: that folder
    is missing, empty or a run, and its ``config.json`` (where it has one) is of the same run as
    ``config_path`` and as ``cfg`` where given (no difference that matters: as
    :func:`prepare_model_dir` compares them). Reads only.

    Raises:
      ValueError: naming the configuration that differs and the fields (or one that is not a
        run's); ``FileExistsError`` / ``NotADirectoryError``: as :func:`prepare_model_dir`.
    """
    _check_run_folder(model_dir)
    own = os.path.join(model_dir, CONFIG_FILE)
    if cfg is None:
        if not (os.path.exists(config_path) and os.path.exists(own)):
            return  # nothing to compare
        new, what = config_path, config_path
    else:
        new, what = cfg, "this run's flags"
    for path in (config_path, own):
        diff = _config_diff(new, path)
        if diff:
            raise ValueError(f"{path} is the configuration of another run than {what}: {diff} "
                             f"(old, new); nothing was copied into {model_dir}: use the same "
                             "flags, or another folder.")


def prepare_model_dir(cfg: TrainConfig, overwrite: bool = False) -> bool:
    """Make ``model_dir`` ready for training and write its ``config.json``
    (:func:`config_document`). Returns True when this starts a new run there (there was no
    ``config.json``), False when it resumes one.

    ``model_dir`` must be missing, empty, or a training run (its ``config.json`` is one of ours:
    :func:`read_run_config`); any other folder is refused (``FileExistsError``/``ValueError``),
    with or without ``overwrite``. A finished run is refused without ``overwrite``, and so is an
    unfinished run of another configuration. ``overwrite`` moves, from a finished run or a run
    of another configuration, only what a run writes aside (:func:`set_aside`; other files in
    the folder stay): :func:`train` puts it back where the new run fails before its first
    checkpoint and deletes it once a training call ends well; an unfinished run of the same configuration is resumed even then, so that
    re-running an interrupted ``--overwrite`` command continues it instead of wiping its
    checkpoints. :func:`train` runs every check of the flags and data (:func:`check_start`)
    before this."""
    final = os.path.join(cfg.model_dir, FINAL_MODEL)
    config_path = os.path.join(cfg.model_dir, CONFIG_FILE)
    if not os.path.exists(config_path) and os.path.isfile(
            os.path.join(cfg.model_dir, PREVIOUS_RUN, CONFIG_FILE)):
        _put_back(cfg.model_dir)  # (a kill between set_aside and the new config: the old run)
    _check_run_folder(cfg.model_dir)
    diff = _config_diff(cfg, config_path)
    done = finished(cfg.model_dir, cfg.train_steps)
    if done and not overwrite:
        raise FileExistsError(f"{cfg.model_dir} holds a finished model ({final}); pass --overwrite "
                              "to train it again.")
    if overwrite and (done or diff):
        if not os.access(cfg.model_dir, os.W_OK):
            raise PermissionError(f"model_dir {cfg.model_dir} is not writable.")
        set_aside(cfg.model_dir)
        diff = {}
    os.makedirs(cfg.model_dir, exist_ok=True)
    if not os.access(cfg.model_dir, os.W_OK):
        raise PermissionError(f"model_dir {cfg.model_dir} is not writable.")
    if diff:
        # val_split's default changed (issue 78): the old value resumes, --overwrite would not
        hint = (f" (--val_split={diff['val_split'][0]} resumes it: the default was "
                f"{diff['val_split'][0]!r} when it was saved)" if "val_split" in diff else "")
        raise ValueError(f"{cfg.model_dir} holds an unfinished run with a different configuration "
                         f"{diff} (old, new); use the same flags to resume{hint}, or --overwrite "
                         "(which deletes its checkpoints).")
    new_run = not os.path.exists(config_path)
    try:
        atomic_write_json(config_path, config_document(cfg) if new_run else _keep_recorded(
            config_document(cfg), read_run_config(config_path, digests=True)))
    except BaseException:
        if new_run:
            _put_back(cfg.model_dir)  # (the run --overwrite set aside)
        raise
    return new_run


def remove_run(model_dir: str) -> None:
    """Delete what a training run writes in ``model_dir`` (:data:`RUN_ENTRIES` and its temporary
    files; ``config.json`` last, so that a deletion cut short still leaves a run) and nothing
    else."""
    for name in _run_names(model_dir):
        path = os.path.join(model_dir, name)
        if os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path)
        elif os.path.lexists(path):
            os.remove(path)


PREVIOUS_RUN = ".previous_run"
"""The folder inside ``model_dir`` that ``--overwrite`` moves the run it replaces into
(:func:`set_aside`)."""


def _run_names(model_dir: str) -> list:
    """What a run wrote in ``model_dir`` that is there: :data:`RUN_ENTRIES`, its temporary
    files and ``config.json`` last."""
    names = os.listdir(model_dir)
    temporary = sorted(n for n in names if n.startswith("tmp-") and n.endswith(FINAL_MODEL)
                       or ".json.tmp-" in n)
    return [n for n in [*RUN_ENTRIES, *temporary, CONFIG_FILE] if n in names]


def set_aside(model_dir: str) -> None:
    """Move what a run wrote in ``model_dir`` into its :data:`PREVIOUS_RUN` folder
    (``config.json`` last), for ``--overwrite``: :func:`undo_new_run` puts it back where the new
    run fails before its first checkpoint, :func:`discard_previous_run` deletes it. Where that
    folder already holds a whole run (a run set aside before, whose replacement has not ended
    well yet), what ``model_dir`` holds is that replacement's and is deleted instead; where it
    holds part of one (a move cut short), the rest is moved in; where the replacement finished
    (its model written, the older run not yet discarded), the older run goes and the
    replacement is set aside: the newest finished run is the one kept."""
    aside = os.path.join(model_dir, PREVIOUS_RUN)
    if os.path.isfile(os.path.join(aside, CONFIG_FILE)):
        if not os.path.exists(os.path.join(model_dir, FINAL_MODEL)):
            remove_run(model_dir)
            return
        shutil.rmtree(aside)
    os.makedirs(aside, exist_ok=True)
    for name in _run_names(model_dir):
        os.replace(os.path.join(model_dir, name), os.path.join(aside, name))


def discard_previous_run(model_dir: str) -> None:
    """Delete the run :func:`set_aside` kept, once the run replacing it has ended well."""
    shutil.rmtree(os.path.join(model_dir, PREVIOUS_RUN), ignore_errors=True)


def undo_new_run(model_dir: str, made_dir: bool) -> None:
    """After a failed start of a new run: unless a checkpoint was committed (then the same
    command resumes it), remove what the start wrote (:func:`remove_run`), put back the run
    ``--overwrite`` set aside (:func:`set_aside`), and remove ``model_dir`` itself if the start
    created it, so that the folder is as it was and a corrected command starts cleanly."""
    if os.path.exists(os.path.join(model_dir, CHECKPOINT_DIR, CHECKPOINT_STATE)) \
            or not os.path.isdir(model_dir):
        return
    remove_run(model_dir)
    _put_back(model_dir)
    if made_dir and not os.listdir(model_dir):
        os.rmdir(model_dir)


def _put_back(model_dir: str) -> None:
    """Move the run :func:`set_aside` kept back into ``model_dir`` (which holds no run)."""
    aside = os.path.join(model_dir, PREVIOUS_RUN)
    if os.path.isdir(aside):
        for name in _run_names(aside):
            os.replace(os.path.join(aside, name), os.path.join(model_dir, name))
        shutil.rmtree(aside, ignore_errors=True)
