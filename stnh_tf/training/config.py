"""The configuration of a training run, defined once: :class:`TrainConfig` and its validation
(the named presets of its fields, recipes and model-kind defaults: :mod:`stnh_tf.training.presets`).

Every field carries its command-line help in its metadata, and the training binaries generate
their flags from the fields (:mod:`experiments.flags_common`), so a new field cannot be forgotten
by a binary. Standard library only (no Keras): reading a configuration needs no backend.

    >>> from stnh_tf.training.presets import preset_fields
    >>> cfg = TrainConfig(image_dir="photos", model_dir="runs/s1", **preset_fields("fast", "stn"))
    >>> cfg.validate()
    >>> cfg.optimizer, cfg.learning_rate
    ('adamw', 0.001)
"""

from __future__ import annotations

import dataclasses
import math
import numbers

from stnh_tf.training.presets import FOUR_POINT_KINDS, MODEL_KINDS, RECIPES

OPTIMIZER_NAMES = ("adam", "adamw", "sgd")
L2_REDUCTIONS = ("mean", "sum")
LR_SCHEDULES = ("cosine", "step")
BATCH_NORMS = ("none", "conv")
INPUT_NORMS = ("unit", "patch")
STRATEGIES = ("default", "mirrored", "data_parallel")

# Which binaries take a field as a flag (experiments.flags_common.define_training_flags).
SHARED, STAGE, SEQUENCE = "shared", "stage", "sequence"


def dtype_policy(mixed_precision: bool) -> str:
    """The Keras dtype policy a run computes in: ``"mixed_bfloat16"`` with ``mixed_precision``,
    else ``"float32"``."""
    return "mixed_bfloat16" if mixed_precision else "float32"


def _field(default, help: str, *, scope: str = SHARED, choices=None, comma_list: bool = False,
           item=str, required: bool = False):
    """A TrainConfig field with its flag: ``help`` text, the binaries that take it (``scope``),
    ``choices`` (an enum flag), ``comma_list`` (a str field given as a list flag, stored joined
    by commas), ``item`` (the element type of a tuple field), ``required`` (no default flag)."""
    return dataclasses.field(default=default, metadata=dict(
        help=help, scope=scope, choices=choices, comma_list=comma_list, item=item,
        required=required))


@dataclasses.dataclass
class TrainConfig:
    """Everything a training run depends on (written to ``model_dir/config.json``); the paper's
    recipe by default. Field help is in each field's metadata (``--help`` of the binaries)."""

    data_dir: str = _field("", "TFRecord dataset directory (from data_prep): train split, and the "
                           "validation split.")
    model_dir: str = _field("", "Output directory (config, checkpoints, logs, model).",
                            required=True)
    model: str = _field("stn", "Model kind: stn (the paper's stage), homographynet (DeTone et "
                        "al.'s network; unless given: --batch_norm=conv, their recipe "
                        "--lr_schedule=step --learning_rate=0.005 --warmup_steps=0 "
                        "--train_steps=90000) or homographynet_gap (its 4-point regression on "
                        "this project's backbone, the paper's recipe).", scope=STAGE,
                        choices=MODEL_KINDS)
    stage: int = _field(1, "Hierarchical stage; the dataset's metadata must say the same.",
                        scope=STAGE)
    num_stages: int = _field(2, "Number of sequence stages.", scope=SEQUENCE)
    train_steps: int = _field(91_000, "Total optimizer steps, warm-up included (unless given: "
                              "90,000 for the sequence model, the paper's, and for "
                              "--model=homographynet, DeTone et al.'s).")
    warmup_steps: int = _field(1_000, "Linear warm-up steps (0 -> learning_rate).")
    batch_size: int = _field(64, "Global batch size.")
    learning_rate: float = _field(0.05, "Peak learning rate after warm-up "
                                  "(--model=homographynet: 0.005 unless given, DeTone et al.'s).")
    lr_schedule: str = _field("cosine", "cosine (the paper's: warm-up, then cosine decay to 0) or "
                              "step (DeTone et al.'s: /10 after each third of --train_steps, no "
                              "warm-up; the default of --model=homographynet).",
                              choices=LR_SCHEDULES)
    momentum: float = _field(0.9, "SGD momentum (sgd only).")
    optimizer: str = _field("sgd", "sgd (the paper's, with --momentum), adam or adamw.",
                            choices=OPTIMIZER_NAMES)
    weight_decay: float = _field(0.0, "Decoupled weight decay (Keras' weight_decay; 0: none).")
    clipnorm: float = _field(0.0, "Clip the global gradient norm to this (0: off).")
    l2_weight: float = _field(1.0, "Weight of the L2 loss on H_bar.")
    l2_reduction: str = _field("mean", "L2 over H_bar's 8 entries: mean (default) or sum "
                               "(8 x mean).", choices=L2_REDUCTIONS)
    l1_weight: float = _field(1.0, "Weight of the L1 photometric loss.")
    stage_loss_weights: tuple = _field((), "Comma list of num_stages floats multiplying each "
                                       "sequence stage's L2 and L1 losses (default: all 1).",
                                       scope=SEQUENCE, item=float)
    batch_norm: str = _field("none", "none (the paper's literal network, default) or BatchNorm "
                             "after every conv.", choices=BATCH_NORMS)
    input_norm: str = _field("unit", "The regressor's input: unit (the pair scaled to [-1, 1], "
                             "default) or patch (each patch standardized to zero mean, unit "
                             "variance: blind to brightness/contrast; a deviation; stn and "
                             "sequence models).", choices=INPUT_NORMS)
    dropout: float = _field(0.5, "Dropout after the 1024-unit layer.")
    seed: int = _field(0, "Seed for initialisation, dropout and data order.")
    shuffle_buffer: int = _field(10_000, "Training shuffle buffer (records, ~86 KB each; shards "
                                 "hold an image's samples together, so a large buffer matters).")
    mixed_precision: bool = _field(False, "Keras mixed_bfloat16 policy (fast on GPUs and CPUs "
                                   "with AVX-512 BF16/AMX; emulated, so slow, on other CPUs).")
    checkpoint_every: int = _field(500, "Steps between checkpoints (one Keras epoch).")
    log_every: int = _field(50, "Steps between progress lines / TensorBoard points.")
    steps_per_execution: int = _field(1, "Training steps per call of the compiled step "
                                      "(Keras' steps_per_execution): callbacks run once per call, "
                                      "so the accelerator is not waited for every step; the "
                                      "updates are the same. Must divide checkpoint_every and "
                                      "log_every.")
    val_split: str = _field("val", "Split for the validation MACE (monitoring only; none where "
                            "data_dir lacks val): val, held out of train (docs/data.md).")
    val_samples: int = _field(1024, "Validation pairs per checkpoint (0: off).")
    strategy: str = _field("default", "default (one device), mirrored (TensorFlow backend: "
                           "tf.distribute.MirroredStrategy over this machine's devices) or "
                           "data_parallel (JAX backend: keras.distribution.DataParallel over "
                           "every device of every process; several hosts or local workers with "
                           "--num_processes: docs/scale.md).", choices=STRATEGIES)
    coordinator_address: str = _field("", "With --strategy=data_parallel --num_processes=N > 1: "
                                      "host:port of process 0 (the chief, the only one writing "
                                      "--model_dir), the same on every process.")
    num_processes: int = _field(1, "With --strategy=data_parallel: processes training together "
                                "(hosts or local workers); --batch_size is their global batch.")
    process_id: int = _field(0, "With --num_processes=N: this process's number, 0..N-1 (0: the "
                             "chief).")
    init_from: tuple = _field((), "Comma list of finished train_stage --model=stn runs (dirs "
                              "holding model.keras, or .keras files), applied on a fresh start "
                              "only: train_stage takes one, whose regression network initialises "
                              "the stage (training on under a new schedule); train_sequence takes "
                              "at most num_stages, dir k initialising stage k.")
    image_dir: str = _field("", "Instead of --data_dir: folders of images (comma-separated); "
                            "pairs are generated on the fly (any Keras backend, e.g. "
                            "KERAS_BACKEND=jax).", comma_list=True)
    val_image_dir: str = _field("", "With --image_dir: folders of images for the validation pairs "
                                "(comma-separated; none: no validation).", comma_list=True)
    samples_per_image: int = _field(3, "With --image_dir: squares per image per data epoch (as "
                                    "make_dataset).")
    max_images: int = _field(0, "With --image_dir: train on the first N images of the folders' "
                             "sorted listing only, the same ones on every machine (0: all; as "
                             "make_dataset --max_images).")
    fresh_pairs: bool = _field(False, "With --image_dir: new pairs every data epoch (else the "
                               "fixed set make_dataset would write, reshuffled).")
    val_seed: int = _field(1, "With --image_dir: seed of the validation pairs (1: make_dataset's "
                           "test split).")
    workers: int = _field(0, "With --image_dir: pair-generator processes (0: in-process).")
    in_memory: bool = _field(False, "With --image_dir (fixed pairs): generate the set once with "
                             "the workers, then train from memory (uint8, 48 KB a pair).")
    prev_stages: tuple = _field((), "With --image_dir --in_memory --stage=k>1: model dirs of "
                                "stages 1..k-1, whose predictions make the stage-k pairs in "
                                "memory.")
    photometric: bool = _field(False, "With --image_dir: independent brightness, contrast, gamma "
                               "and noise changes of patch_b in the training pairs "
                               "(pairs.PhotometricChange; not the paper's; the validation pairs "
                               "stay unchanged).")
    label_fraction: float = _field(1.0, "Share of the training pairs that keep their ground-truth "
                                   "H_bar: pair i keeps it iff a hash of (seed, i) falls below "
                                   "the share (stnh_tf.data.labels: the same pairs on resume, "
                                   "from TFRecords or generated pairs); the others get h_mask 0 "
                                   "and H_bar zeroed, and train on the L1 photometric loss against "
                                   "patch_b alone (the paper's semi-supervised training). 1: all.")
    drop_unlabeled: bool = _field(False, "Train on the labeled pairs alone (the others left out): "
                                  "with --label_fraction=F, F of the data, fully supervised.")
    unlabeled_image_dir: str = _field("", "With --image_dir: folders of images (comma-separated) "
                                      "whose pairs (--samples_per_image each) are mixed into "
                                      "training without labels: h_mask 0, H_bar zeroed, the L1 "
                                      "photometric loss against patch_b alone.", comma_list=True)
    unlabeled_pairs_dir: str = _field("", "Folders of real image pairs without any H (NAME_a.EXT "
                                      "beside NAME_b.EXT; sub-folders of video frames), mixed "
                                      "into every batch without labels (docs/training.md).",
                                      comma_list=True)
    recipe: str = _field("paper", "Preset of the recipe flags: paper (the paper's, default) or "
                         "fast (a deviation: " + ", ".join(f"{k}={v}" for k, v in
                                                           RECIPES["fast"].items())
                         + "); flags given explicitly override the preset.",
                         choices=tuple(sorted(RECIPES)))

    def validate(self, time_limit_s=None):
        """Raise ``ValueError`` naming every field and value training cannot use, all of them in
        one message (:meth:`problems`): checked here, in one place, before anything is written;
        with ``time_limit_s`` (not a field: a run's chunks may have different limits) checked
        too (:func:`time_limit_problems`)."""
        problems = self.problems() + time_limit_problems(time_limit_s)
        if len(problems) == 1:
            raise ValueError(problems[0])
        if problems:
            raise ValueError(f"{len(problems)} problems: "
                             + " ".join(f"({i}) {p}" for i, p in enumerate(problems, 1)))

    def problems(self) -> list:
        """Every problem :meth:`validate` reports, as messages naming the field and value."""
        out = []
        for group in (self._choice_problems, self._source_problems, self._model_problems,
                      self._number_problems, self._loss_problems, self._folder_problems,
                      self._label_problems, self._distribution_problems):
            try:
                out.extend(group())
            except (TypeError, ValueError) as e:  # a value of the wrong type, met in a group
                out.append(f"{type(e).__name__}: {e}")
        return out

    def _choice_problems(self):
        for f in dataclasses.fields(self):
            choices = f.metadata.get("choices")
            if choices and getattr(self, f.name) not in choices:
                yield (f"{f.name} must be one of {sorted(choices)}; received "
                       f"{getattr(self, f.name)!r}.")

    def _source_problems(self):
        if not self.model_dir:
            yield ("model_dir is required.")
        if bool(self.data_dir) == bool(self.image_dir):
            yield ("give exactly one of data_dir (TFRecords) and image_dir (pairs "
                   f"generated on the fly); received data_dir={self.data_dir!r}, "
                   f"image_dir={self.image_dir!r}.")
        if self.image_dir and self.stage != 1 and (len(self.prev_stages) != self.stage - 1
                                                   or not self.in_memory or self.model != "stn"):
            yield (f"stage {self.stage} from image_dir needs in_memory, model 'stn' and "
                   f"the {self.stage - 1} previous stages' model dirs in prev_stages "
                   f"(received {len(self.prev_stages)}): their predictions make the "
                   "stage's pairs in memory. Or train on stage-k TFRecords "
                   "(data_prep.make_stage_dataset) with data_dir.")
        if self.prev_stages and (not self.image_dir or self.stage == 1):
            yield ("prev_stages is for stage k > 1 trained from image_dir; stage-k "
                   "TFRecords already hold the previous stages' predictions.")

    def _model_problems(self):
        if self.model == "sequence" and self.num_stages < 1:
            yield (f"num_stages must be >= 1; received {self.num_stages}.")
        if self.model != "sequence" and self.init_from and (len(self.init_from) != 1
                                                            or self.model != "stn"):
            yield (f"init_from of a single stage takes one stn run and model 'stn'; "
                   f"received {len(self.init_from)} dirs, model {self.model!r}.")
        if self.model == "sequence" and self.init_from and len(self.init_from) > self.num_stages:
            yield (f"init_from names {len(self.init_from)} models for {self.num_stages} "
                   "stages.")
        if self.lr_schedule == "step" and self.warmup_steps:
            yield (f"lr_schedule 'step' (DeTone et al.'s) has no warm-up; received "
                   f"warmup_steps={self.warmup_steps} (give 0, or lr_schedule 'cosine').")
        if self.model == "homographynet" and self.batch_norm != "conv":
            yield ("model 'homographynet' is DeTone et al.'s network, with BatchNorm "
                   f"after every convolution: batch_norm must be 'conv' (received "
                   f"{self.batch_norm!r}); model 'homographynet_gap' is the 4-point "
                   "regression on this project's backbone, with or without it.")
        if self.model in FOUR_POINT_KINDS and self.input_norm != "unit":
            yield (f"model={self.model!r} scales its input to [-1, 1]: input_norm must "
                   f"be 'unit' (received {self.input_norm!r}).")

    def _number_problems(self):
        wrong = [name for name, low in _INTEGER_MINIMUMS.items()
                 if isinstance(getattr(self, name), bool)
                 or not isinstance(getattr(self, name), numbers.Integral)
                 or getattr(self, name) < low]
        for name, low in _INTEGER_MINIMUMS.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
                yield (f"{name} must be an integer >= {low}; received {value!r}.")
        if wrong:  # the checks below need those integers
            return
        if self.train_steps <= 0 or self.warmup_steps < 0 or self.warmup_steps > self.train_steps:
            yield (f"need 0 <= warmup_steps <= train_steps, train_steps > 0; received "
                   f"warmup_steps={self.warmup_steps}, train_steps={self.train_steps}.")
        if not 0.0 <= self.dropout < 1.0:
            yield (f"dropout must be in [0, 1); received {self.dropout}.")
        if not 0.0 <= self.momentum <= 1.0:
            yield (f"momentum must be in [0, 1]; received {self.momentum}.")
        for name in ("l2_weight", "l1_weight"):
            value = getattr(self, name)
            if not (value >= 0 and math.isfinite(value)):
                yield (f"{name} must be a finite number >= 0; received {value}.")
        if self.l2_weight == 0 and self.l1_weight == 0:
            yield ("l2_weight and l1_weight are both 0: the loss would be 0 and nothing "
                   "would train; set at least one of them above 0.")
        if self.train_steps % self.checkpoint_every:
            yield (f"train_steps ({self.train_steps}) must be a multiple of "
                   f"checkpoint_every ({self.checkpoint_every}).")
        if self.stage < 1:
            yield (f"stage must be >= 1; received {self.stage}.")
        for name in ("checkpoint_every", "log_every"):
            if self.steps_per_execution >= 1 and getattr(self, name) % self.steps_per_execution:
                yield (f"steps_per_execution ({self.steps_per_execution}) must divide {name} "
                       f"({getattr(self, name)}).")
        if not (self.weight_decay >= 0 and math.isfinite(self.weight_decay)):
            yield (f"weight_decay must be a finite number >= 0; received "
                   f"{self.weight_decay}.")
        if not (self.clipnorm >= 0 and math.isfinite(self.clipnorm)):
            yield (f"clipnorm must be a finite number >= 0 (0: off); received "
                   f"{self.clipnorm}.")
        if not (self.learning_rate > 0 and math.isfinite(self.learning_rate)):
            yield (f"learning_rate must be a finite number > 0; received "
                   f"{self.learning_rate}.")

    def _folder_problems(self):
        for name in ("image_dir", "val_image_dir", "unlabeled_image_dir", "unlabeled_pairs_dir"):
            spec = getattr(self, name)
            if spec and not [f for f in spec.split(",") if f.strip()]:
                yield (f"{name} names no folder (received {spec!r}); give one or "
                       "more comma-separated folders.")
        if self.max_images and not self.image_dir:
            yield ("max_images limits the images of image_dir; TFRecords hold the pairs of the "
                   "images they were made from (data_prep.make_dataset --max_images).")
        if self.photometric and not self.image_dir:
            yield ("photometric changes pairs generated from image_dir; for TFRecords, "
                   "write them with data_prep.make_dataset --photometric.")
        if self.in_memory and self.fresh_pairs:
            yield ("in_memory holds one fixed set of pairs; it excludes fresh_pairs.")
        if self.data_dir and not self.image_dir:
            for f in dataclasses.fields(self):  # the fields whose help says "With --image_dir"
                value, low = getattr(self, f.name), _INTEGER_MINIMUMS.get(f.name)
                if (f.metadata["help"].startswith("With --image_dir") and f.name not in (
                        "max_images", "photometric", "prev_stages", "unlabeled_image_dir",
                        "workers", "in_memory")  # (speed alone: they change no result)
                        and value != f.default
                        and not (low is not None and isinstance(value, int) and value < low)):
                    yield (f"{f.name} applies to pairs generated from image_dir; with data_dir "
                           "the TFRecords fix the pairs (data_prep.make_dataset), and "
                           f"{f.name}={value!r} would be recorded but not used.")

    def _label_problems(self):
        fraction = self.label_fraction
        valid = (not isinstance(fraction, bool) and isinstance(fraction, numbers.Real)
                 and math.isfinite(fraction) and 0.0 <= fraction <= 1.0)
        if not valid:
            yield (f"label_fraction must be a number in [0, 1]; received {fraction!r}.")
        if self.unlabeled_image_dir and not self.image_dir:
            yield ("unlabeled_image_dir mixes pairs generated from its images into pairs "
                   "generated from image_dir; give image_dir (with TFRecords in data_dir, "
                   "label_fraction leaves a share of the pairs unlabeled).")
        if self.drop_unlabeled and self.unlabeled_image_dir:
            yield ("drop_unlabeled would leave out every pair of unlabeled_image_dir; give one "
                   "of them.")
        if not valid:
            return
        if self.drop_unlabeled and fraction == 0:
            yield "drop_unlabeled with label_fraction 0 leaves no pair to train on."
        unlabeled = ((fraction < 1 and not self.drop_unlabeled) or self.unlabeled_image_dir
                     or self.unlabeled_pairs_dir)
        if unlabeled and self.model in FOUR_POINT_KINDS:
            yield (f"model={self.model!r} has no photometric loss: its unlabeled pairs would "
                   "train nothing; give drop_unlabeled (label_fraction < 1) or an stn model.")
        elif unlabeled and self.l1_weight == 0:
            yield ("l1_weight is 0: the unlabeled pairs (label_fraction < 1, "
                   "unlabeled_image_dir, unlabeled_pairs_dir) would train nothing; give "
                   "l1_weight > 0 or drop_unlabeled.")

    def _distribution_problems(self):
        n, k = self.num_processes, self.process_id
        if not all(isinstance(v, numbers.Integral) and not isinstance(v, bool) for v in (n, k)):
            return  # (_number_problems names them)
        if n > 1 and self.strategy != "data_parallel":
            yield (f"num_processes={n} trains with strategy 'data_parallel' (received "
                   f"{self.strategy!r}).")
        if n >= 1 and not 0 <= k < n:
            yield f"process_id must be in [0, num_processes); received {k} of {n}."
        if n > 1 and not self.coordinator_address:
            yield ("num_processes > 1 needs coordinator_address (host:port of process 0, the "
                   "same on every process).")
        if n == 1 and self.coordinator_address:
            yield (f"coordinator_address ({self.coordinator_address!r}) joins several "
                   "processes: give num_processes > 1 too (else each trains alone), or leave it "
                   "empty.")
        if n > 1 and isinstance(self.batch_size, numbers.Integral) and self.batch_size % n:
            yield (f"batch_size ({self.batch_size}) is the global batch: it must be a multiple "
                   f"of num_processes ({n}).")
        if n > 1 and self.unlabeled_pairs_dir:  # (each process added the same rows, all of them)
            yield ("unlabeled_pairs_dir trains on one process only: its rows are not shared out "
                   f"between processes (num_processes={n}).")

    def check_losses(self):
        """Raise ``ValueError`` for loss settings the model kind cannot use (part of
        :meth:`validate`; also run when the losses are built)."""
        problems = list(self._loss_problems())
        if problems:
            raise ValueError(problems[0])

    def _loss_problems(self):
        if self.model in FOUR_POINT_KINDS and (self.l2_weight, self.l1_weight,
                                               self.l2_reduction) != (1.0, 1.0, "mean"):
            yield (f"model={self.model!r} trains its 4-point offsets with one L2 loss: "
                   "l2_weight/l1_weight/l2_reduction do not apply (received "
                   f"{self.l2_weight}, {self.l1_weight}, {self.l2_reduction!r}); leave "
                   "them at 1, 1, 'mean'.")
        weights = self.stage_loss_weights
        if weights and (self.model != "sequence" or len(weights) != self.num_stages):
            yield (f"stage_loss_weights needs {self.num_stages} values (one per "
                   f"sequence stage); received {list(weights)} for model "
                   f"{self.model!r}.")
        if any(not (isinstance(w, numbers.Real) and math.isfinite(w) and w >= 0)
               for w in weights):
            yield (f"stage_loss_weights must be finite and >= 0; received "
                   f"{list(weights)}.")

    def to_json(self):
        d = dataclasses.asdict(self)
        for f in _TUPLE_FIELDS:
            d[f] = list(d[f])
        return d

    @classmethod
    def from_json(cls, d):
        names = {f.name for f in dataclasses.fields(cls)}
        d = {k: v for k, v in d.items() if k in names}
        for f in _TUPLE_FIELDS:
            d[f] = tuple(d.get(f, ()))
        return cls(**d)


_TUPLE_FIELDS = tuple(f.name for f in dataclasses.fields(TrainConfig) if f.type == "tuple")

# The integer fields and their smallest allowed values (TrainConfig.validate).
_INTEGER_MINIMUMS = {"checkpoint_every": 1, "batch_size": 1, "shuffle_buffer": 1, "log_every": 1,
                     "samples_per_image": 1, "max_images": 0, "val_samples": 0, "workers": 0,
                     "seed": 0, "val_seed": 0, "num_processes": 1, "process_id": 0,
                     "steps_per_execution": 1}

# Fields that may differ between a run and its resumption without changing the result.
RESUME_FREE_FIELDS = frozenset({"log_every", "model_dir", "data_dir", "image_dir", "val_image_dir",
                                "workers", "in_memory", "unlabeled_image_dir",
                                "unlabeled_pairs_dir", "steps_per_execution",
                                "coordinator_address"})
# Fields naming finished models (run folders holding model.keras, or .keras files): a run and its
# resumption are compared by what those files hold, wherever the checkout that holds them is
# (stnh_tf.training.run_dir.config_document records their sha256 in config.json).
MODEL_FILE_FIELDS = ("init_from", "prev_stages")


def time_limit_problems(seconds) -> list:
    """The problems of a run's time limit (``loop.train(time_limit_s=...)``, ``--time_limit_s``):
    None or 0 is no limit; else a finite number of seconds > 0 (inf refused: 0 says "no limit").

    >>> time_limit_problems(0), time_limit_problems(None), time_limit_problems(480)
    ([], [], [])
    >>> time_limit_problems(float("nan"))
    ['time_limit_s must be a finite number of seconds > 0 (0: no limit); received nan.']
    """
    ok = seconds is None or (isinstance(seconds, numbers.Real) and not isinstance(seconds, bool)
                             and (seconds == 0 or (math.isfinite(seconds) and seconds > 0)))
    return [] if ok else [f"time_limit_s must be a finite number of seconds > 0 (0: no limit); "
                          f"received {seconds!r}."]
