"""Training flags of ``train_stage`` and ``train_sequence``, generated from the fields of
:class:`stnh_tf.training.config.TrainConfig` (name, type, default, help and choices defined once
there), plus ``--overwrite``."""

import dataclasses

from absl import flags

from experiments import common
from stnh_tf.paths import check_apart
from stnh_tf.training import config as train_config
from stnh_tf.training import presets, worker_log
from stnh_tf.training.config import TrainConfig


def training_fields(scope: str):
    """The TrainConfig fields that are flags of the binary ``scope`` (``train_config.STAGE`` or
    ``train_config.SEQUENCE``): the shared ones and the binary's own."""
    return [f for f in dataclasses.fields(TrainConfig)
            if f.metadata["scope"] in (train_config.SHARED, scope)]


def _define(field, flag_values, choices=None):
    meta, default = field.metadata, field.default
    args = dict(name=field.name, help=meta["help"], flag_values=flag_values)
    if meta["required"]:
        flags.DEFINE_string(default=None, required=True, **args)
    elif meta["comma_list"] or isinstance(default, tuple):
        flags.DEFINE_list(default=list(default.split(",") if default else default), **args)
    elif isinstance(default, bool):
        flags.DEFINE_bool(default=default, **args)
    elif isinstance(default, int):
        flags.DEFINE_integer(default=default, **args)
    elif isinstance(default, float):
        flags.DEFINE_float(default=default, **args)
    elif choices or meta["choices"]:
        flags.DEFINE_enum(default=default, enum_values=list(choices or meta["choices"]), **args)
    else:
        flags.DEFINE_string(default=default, **args)


def define_training_flags(scope: str, choices=None, flag_values=flags.FLAGS,
                          run_flags: bool = True):
    """Define a flag for every field of :func:`training_fields` (``scope``) and, with
    ``run_flags``, ``--overwrite`` and ``--time_limit_s`` (what a training run needs).
    ``choices`` narrows enum fields for this binary (``{"model": (...)}``)."""
    choices = choices or {}
    for field in training_fields(scope):
        _define(field, flag_values, choices.get(field.name))
    if not run_flags:
        return
    flags.DEFINE_bool("overwrite", False, "Delete and retrain a model_dir that holds a finished "
                      "run or a run of other flags (an unfinished run of the same flags is "
                      "resumed). Only what a run wrote is deleted, and only after every flag and "
                      "the data are checked; a folder that is not a training run is never "
                      "touched.", flag_values=flag_values)
    flags.DEFINE_float("time_limit_s", 0.0, "Stop within one step of this many seconds, saving a "
                       "checkpoint of that step, and leave the run unfinished: the same command "
                       "resumes it from there (0: no limit; for runs trained in chunks).",
                       flag_values=flag_values)
    flags.register_validator("time_limit_s", check_time_limit, flag_values=flag_values)


def check_time_limit(value) -> bool:
    """absl validator of ``--time_limit_s`` (:func:`stnh_tf.training.config.time_limit_problems`):
    refused at parsing, with the flag named, before anything starts."""
    problems = train_config.time_limit_problems(value)
    if problems:
        raise flags.ValidationError(problems[0])
    return True


def config_from_flags(scope: str, flag_values=flags.FLAGS, **overrides) -> TrainConfig:
    """The TrainConfig of the parsed flags of :func:`define_training_flags` (``scope``): the
    preset of ``--recipe`` and of the model kind (:func:`stnh_tf.training.presets.preset_fields`:
    e.g. DeTone's schedule for ``model="homographynet"``, 90,000 steps for ``"sequence"``), then
    every flag given explicitly, then ``overrides``.

    Raises:
      ValueError: a list element that is not of its field's type (e.g. a non-float stage loss
        weight).
    """
    f = flag_values
    values = {}
    for field in training_fields(scope):
        value = f[field.name].value
        if field.metadata["comma_list"]:
            value = ",".join(value)
        elif isinstance(field.default, tuple):
            item = field.metadata["item"]
            try:
                value = tuple(item(v) for v in value)
            except ValueError:
                raise ValueError(f"{field.name} takes {item.__name__} values; received "
                                 f"{value}.") from None
        values[field.name] = value
    cfg = TrainConfig(**values)
    model = overrides.get("model", cfg.model)
    preset = {k: v for k, v in presets.preset_fields(f.recipe, model).items()
              if not f[k].present}
    for k, v in {**preset, **overrides}.items():
        setattr(cfg, k, v)
    return cfg


TRAINING_INPUTS = ("data_dir", "image_dir", "val_image_dir", "unlabeled_image_dir",
                   "unlabeled_pairs_dir", "init_from", "prev_stages")
"""The TrainConfig fields that name what a run reads (folders, or runs it starts from)."""


def training_inputs(cfg) -> dict:
    """``{"--field": [paths]}`` of :data:`TRAINING_INPUTS` in ``cfg`` (comma-separated strings
    split), for :func:`stnh_tf.paths.check_apart`."""
    return {f"--{name}": value.split(",") if isinstance(value, str) else list(value)
            for name in TRAINING_INPUTS for value in [getattr(cfg, name)]}


def run_training(cfg, binary: str, flag_values=None) -> None:
    """Train (or resume) ``cfg`` (the parsed ``flag_values`` give ``--overwrite`` and
    ``--time_limit_s``; default: ``flags.FLAGS`` as it is at the call), after logging
    :func:`schedule_line`; user errors exit with ``{binary}: message``, not a traceback."""
    from absl import logging

    f = flags.FLAGS if flag_values is None else flag_values
    worker_log.prefix_logs(cfg.num_processes, cfg.process_id)  # [worker k/N] on every line
    logging.info(schedule_line(cfg, f["train_steps"].present))  # before TensorFlow starts
    from stnh_tf.training import loop as training

    with common.user_errors(binary, (ValueError, OSError, training.TrainingDiverged)):
        check_apart({"--model_dir": cfg.model_dir}, training_inputs(cfg))
        result = training.train(cfg, overwrite=f.overwrite, printer=logging.info,
                                time_limit_s=f.time_limit_s or None)
    logging.info(final_line(result, cfg.train_steps))
    if result.get("stopped_by") not in (None, "time limit"):  # a signal: not what was asked
        raise SystemExit(f"{binary}: {final_line(result, cfg.train_steps)}")


SMOKE_FLAGS = ("--train_steps=20 --warmup_steps=2 --checkpoint_every=10 --batch_size=4 "
               "--learning_rate=0.005")
"""The flags of a smoke run of a training binary (docs/quickstart.md, docs/training.md)."""


def schedule_line(cfg, given: bool) -> str:
    """The first line a training binary logs: the steps it trains to, and, when ``--train_steps``
    was not ``given``, that this is the paper's schedule (or DeTone et al.'s), many hours on a
    CPU, with the flags of a smoke run instead (:data:`SMOKE_FLAGS`).

    >>> print(schedule_line(TrainConfig(train_steps=20), given=True))
    training to step 20 (--train_steps)
    >>> print(schedule_line(TrainConfig(), given=False))  # doctest: +ELLIPSIS
    training to step 91,000: the paper's schedule, the default of --train_steps: hours to days ...
    """
    if given:
        return f"training to step {cfg.train_steps:,} (--train_steps)"
    schedule = {"sequence": "the paper's schedule of the sequence model",
                "homographynet": "DeTone et al.'s schedule"}.get(cfg.model, "the paper's schedule")
    return (f"training to step {cfg.train_steps:,}: {schedule}, the default of --train_steps: "
            "hours to days on a CPU (each progress line gives the steps/s and the time left); "
            f"a smoke run instead: {SMOKE_FLAGS} (docs/quickstart.md)")


def final_line(result: dict, train_steps: int) -> str:
    """The last log line of a training binary, from :func:`stnh_tf.training.loop.train`'s result:
    finished, or stopped (by the time limit, or a signal) before ``train_steps``.

    >>> final_line({"final_step": 6}, 6)
    'finished at step 6'
    >>> final_line({"final_step": 2, "stopped_by": "time limit"}, 6)
    'stopped by the time limit at step 2 of 6, not finished: the same command resumes it'
    """
    by = result.get("stopped_by")
    if by is None:
        return f"finished at step {result['final_step']}"
    return (f"stopped by {'the time limit' if by == 'time limit' else by} at step "
            f"{result['final_step']} of {train_steps}, not finished: the same command resumes it")


# ------------------------------------------------------------------------------------------------
# The estimator's options as flags
# ------------------------------------------------------------------------------------------------
# One help line per EstimateOptions field that a binary may take as a flag; the choices and the
# defaults come from stnh_tf.inference.options, so the binaries cannot disagree on them.
ESTIMATE_FLAG_HELP = {
    "search": "Where the estimate aligns a pair poorly: ecc (start ECC from the best translations "
              "of it, keep a near-perfect result; a deviation) or none (the network's estimate).",
    "refine": "After the network: none (the paper), ecc (ECC alignment started from the "
              "estimate; a deviation) or images (ecc, then ECC over the whole images in "
              "estimate_images; a deviation).",
    "tta": "Test-time augmentation: none (the paper), flips or dihedral (also estimate the pair "
           "mirrored and rotated, keep the best aligned estimate; a deviation).",
    "retry_tta": "Estimate again with this test-time augmentation only the pairs flagged "
                 "implausible: none, flips or dihedral (a deviation).",
    "gate_stages": "In a hierarchy on bare patches, keep a later stage's update only where it "
                   "does not lower the alignment (a deviation).",
    "fill": "In a hierarchy on bare patches, what later stages see beyond the patch: reflect (a "
            "deviation) or zeros.",
    "verify": "Before flagging: none, or ecc (flag an estimate that ECC started from it moves by "
              "more than Thresholds.max_verify_move; a deviation).",
    "coarse": "estimate_images only: none, or rotations (try a poorly aligned pair again from "
              "coarse rotations and zooms, for motions beyond the trained range; a deviation).",
    "features": "estimate_images only: none, fallback (where the network's estimate aligns "
                "poorly, also start from SIFT + MAGSAC matches, refined by the network; a "
                "deviation) or always (that start for every pair, kept where it aligns better).",
}


def _estimate_choices(name):
    from stnh_tf import geometry
    from stnh_tf.inference import options

    return {"search": options.SEARCHES, "refine": options.REFINES, "tta": tuple(options.TTAS),
            "retry_tta": tuple(options.TTAS), "fill": geometry.FILLS,
            "verify": options.VERIFIES, "coarse": tuple(options.COARSES),
            "features": options.FEATURES}.get(name)


_FLAG_DEFAULTS = {}
"""The ``defaults`` each ``FlagValues`` (by id) got from :func:`define_estimate_flags`."""


THRESHOLDS_HELP = ("Thresholds fields to change, as name=value (e.g. resolution_sigma=0: the "
                   "whole-image refinement without its one resolution); the others keep the "
                   "options' own.")


def define_estimate_flags(names=("search", "refine", "tta", "retry_tta"), defaults=None,
                          flag_values=flags.FLAGS, thresholds: bool = False):
    """Define a flag for each :class:`~stnh_tf.inference.options.EstimateOptions` field of
    ``names`` (keys of :data:`ESTIMATE_FLAG_HELP`), its default taken from ``defaults`` (an
    ``EstimateOptions``; ``None``: ``EstimateOptions()``), and with ``thresholds``
    ``--thresholds=name=value,...`` (:data:`THRESHOLDS_HELP`). :func:`options_from_flags` reads
    them.
    """
    from stnh_tf.inference.options import EstimateOptions

    defaults = EstimateOptions() if defaults is None else defaults
    _FLAG_DEFAULTS[id(flag_values)] = defaults
    if thresholds:
        flags.DEFINE_list("thresholds", [], THRESHOLDS_HELP, flag_values=flag_values)
    for name in names:
        default, help_text = getattr(defaults, name), ESTIMATE_FLAG_HELP[name]
        if isinstance(default, bool):
            flags.DEFINE_bool(name, default, help_text, flag_values=flag_values)
        else:
            flags.DEFINE_enum(name, default, list(_estimate_choices(name)), help_text,
                              flag_values=flag_values)


def options_from_flags(defaults=None, flag_values=flags.FLAGS):
    """The :class:`~stnh_tf.inference.options.EstimateOptions` of the parsed flags of
    :func:`define_estimate_flags`: ``defaults`` (``None``: those the flags were defined with)
    with every field that is a defined flag replaced by the flag's value."""
    from stnh_tf.inference.options import EstimateOptions

    if defaults is None:
        defaults = _FLAG_DEFAULTS.get(id(flag_values)) or EstimateOptions()
    options = dataclasses.replace(defaults, **{name: flag_values[name].value
                                               for name in ESTIMATE_FLAG_HELP
                                               if name in flag_values})
    if "thresholds" in flag_values and flag_values["thresholds"].value:
        options = dataclasses.replace(options, thresholds=thresholds_from_flag(
            flag_values["thresholds"].value, options.thresholds))
    return options


def thresholds_from_flag(items, base):
    """``base`` (a :class:`~stnh_tf.inference.options.Thresholds`) with the ``name=value`` items
    of ``--thresholds`` applied, each value of its field's type (an int field takes an int).

    Raises:
      ValueError: an item without ``=``, an unknown field, a value of the wrong
        type, or one the field refuses (``Thresholds``' own check).

    >>> from stnh_tf.inference.options import Thresholds
    >>> thresholds_from_flag(["resolution_sigma=0", "corner_std_tile=4"], Thresholds()).corner_std_tile
    4
    """
    from stnh_tf.inference.options import WHOLE_NUMBER_TYPES

    fields = {f.name: int if f.type in WHOLE_NUMBER_TYPES else float
              for f in dataclasses.fields(base)}
    changes = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or name not in fields:
            raise ValueError(f"--thresholds takes name=value items of Thresholds' number fields "
                             f"({', '.join(fields)}); received {item!r}.")
        kind = fields[name]
        try:
            changes[name] = kind(text)
        except ValueError:
            raise ValueError(f"--thresholds: {name} takes "
                             f"{'a whole number' if kind is int else 'a number'}; received "
                             f"{text!r}.") from None
    return dataclasses.replace(base, **changes)


MAX_IMAGES_HELP = ("Use only the first N photographs of the folder's sorted listing (several "
                   "folders: folder after folder), the same ones on every machine (0: all).")


def define_max_images(flag_values=flags.FLAGS, help_text: str = MAX_IMAGES_HELP):
    """``--max_images`` (an integer >= 0; 0: every photograph) of a binary that reads a
    photograph folder: :func:`stnh_tf.data.sources.scan_image_folders`' ``max_images``. The
    training binaries take it from :class:`~stnh_tf.training.config.TrainConfig` instead."""
    flags.DEFINE_integer("max_images", 0, help_text, lower_bound=0, flag_values=flag_values)


def define_seed(help_text: str, flag_values=flags.FLAGS):
    """``--seed`` (an integer >= 0, default 0) of a binary: absl refuses a negative value at
    parsing, naming the flag (``flag --seed=-1: -1 is not a non-negative integer``), before
    NumPy's ``default_rng`` refuses it in its own words or anything is written."""
    flags.DEFINE_integer("seed", 0, help_text, lower_bound=0, flag_values=flag_values)


def define_json_out(flag_values=flags.FLAGS):
    """``--json_out``: where a binary also writes the JSON it prints
    (:func:`experiments.common.emit_json`), checked when the flags are read
    (:func:`stnh_tf.evaluation.summaries.check_json_out`: only an earlier result of the same
    binary is replaced; a missing folder is made where the JSON is written)."""
    flags.DEFINE_string("json_out", None, "Also write the JSON here ('-': standard output "
                        "only); an existing file must be an earlier result of this binary.",
                        flag_values=flag_values)

    def check(value):
        from stnh_tf.evaluation import summaries

        try:
            summaries.check_json_out(value, make_folder=False)  # (the binary's own checks next)
        except OSError as e:
            raise flags.ValidationError(str(e)) from None
        return True

    flags.register_validator("json_out", check, flag_values=flag_values)
