"""Training flags shared by ``train_stage`` and ``train_sequence`` (one definition, two binaries)."""

from absl import flags

from stnh_tf import training
from stnh_tf.training import TrainConfig

_D = TrainConfig()


def define_training_flags():
    flags.DEFINE_string("data_dir", "", "TFRecord dataset directory (from data_prep).")
    flags.DEFINE_list("image_dir", [], "Instead of --data_dir: folders of images (comma-separated); "
                      "pairs are generated on the fly (any Keras backend, e.g. KERAS_BACKEND=jax).")
    flags.DEFINE_list("val_image_dir", [], "With --image_dir: folders of images for the validation "
                      "pairs (comma-separated).")
    flags.DEFINE_bool("photometric", _D.photometric, "With --image_dir: independent brightness, "
                      "contrast, gamma and noise changes of patch_b in the training pairs (not the "
                      "paper's; the validation pairs stay unchanged).")
    flags.DEFINE_integer("samples_per_image", _D.samples_per_image,
                         "With --image_dir: squares per image per data epoch (as make_dataset).")
    flags.DEFINE_bool("fresh_pairs", _D.fresh_pairs, "With --image_dir: new pairs every data epoch "
                      "(else the fixed set make_dataset would write, reshuffled).")
    flags.DEFINE_integer("workers", _D.workers, "With --image_dir: pair-generator processes.")
    flags.DEFINE_bool("in_memory", _D.in_memory, "With --image_dir (fixed pairs): generate the set "
                      "once with the workers, then train from memory (uint8, 48 KB a pair).")
    flags.DEFINE_list("prev_stages", [], "With --image_dir --in_memory --stage=k>1: model dirs "
                      "of stages 1..k-1, whose predictions make the stage-k pairs in memory.")
    flags.DEFINE_string("model_dir", None, "Output directory (config, checkpoints, logs, model).",
                        required=True)
    flags.DEFINE_integer("train_steps", _D.train_steps, "Total steps, warm-up included "
                         "(unless given: 90,000 for the sequence model, the paper's, and for "
                         "--model=homographynet, DeTone et al.'s).")
    flags.DEFINE_integer("warmup_steps", _D.warmup_steps, "Linear warm-up steps (0 -> learning_rate).")
    flags.DEFINE_integer("batch_size", _D.batch_size, "Global batch size.")
    flags.DEFINE_float("learning_rate", _D.learning_rate, "Peak learning rate after warm-up "
                       "(--model=homographynet: 0.005 unless given, DeTone et al.'s).")
    flags.DEFINE_enum("lr_schedule", _D.lr_schedule, list(training.LR_SCHEDULES),
                      "cosine (the paper's: warm-up, then cosine decay to 0) or step (DeTone et "
                      "al.'s: /10 after each third of --train_steps, no warm-up; the default of "
                      "--model=homographynet).")
    flags.DEFINE_float("momentum", _D.momentum, "SGD momentum.")
    flags.DEFINE_enum("recipe", _D.recipe, sorted(training.RECIPES), "Preset of the recipe flags: "
                      "paper (the paper's, default) or fast (a deviation: "
                      + ", ".join(f"{k}={v}" for k, v in training.RECIPES["fast"].items())
                      + "); flags given explicitly override the preset.")
    flags.DEFINE_enum("optimizer", _D.optimizer, sorted(training.OPTIMIZERS),
                      "sgd (paper, with --momentum), adam or adamw.")
    flags.DEFINE_float("weight_decay", _D.weight_decay, "Decoupled weight decay (0: none).")
    flags.DEFINE_float("clipnorm", _D.clipnorm, "Clip the global gradient norm (0: off).")
    flags.DEFINE_float("l2_weight", _D.l2_weight, "Weight of the L2 loss on H_bar.")
    flags.DEFINE_enum("l2_reduction", _D.l2_reduction, list(training.L2_REDUCTIONS),
                      "L2 over H_bar's 8 entries: mean (default) or sum (8 x mean).")
    flags.DEFINE_float("l1_weight", _D.l1_weight, "Weight of the L1 photometric loss.")
    flags.DEFINE_enum("batch_norm", _D.batch_norm, ["none", "conv"],
                      "none (paper's literal network, default) or BatchNorm after every conv.")
    flags.DEFINE_float("dropout", _D.dropout, "Dropout after the 1024-unit layer.")
    flags.DEFINE_integer("seed", _D.seed, "Seed for initialisation, dropout and data order.")
    flags.DEFINE_integer("shuffle_buffer", _D.shuffle_buffer, "Training shuffle buffer (records).")
    flags.DEFINE_bool("mixed_precision", _D.mixed_precision, "Keras mixed_bfloat16 policy (fast on "
                      "GPUs and CPUs with AVX-512 BF16/AMX; emulated, so slow, on other CPUs).")
    flags.DEFINE_integer("checkpoint_every", _D.checkpoint_every, "Steps between checkpoints.")
    flags.DEFINE_integer("log_every", _D.log_every, "Steps between progress lines / TB points.")
    flags.DEFINE_string("val_split", _D.val_split, "Split for the validation MACE (monitoring only).")
    flags.DEFINE_integer("val_samples", _D.val_samples, "Validation pairs per checkpoint (0: off).")
    flags.DEFINE_enum("strategy", _D.strategy, ["default", "mirrored"], "tf.distribute strategy.")
    flags.DEFINE_bool("overwrite", False, "Delete and retrain a model_dir that holds a finished "
                      "run or a run of other flags (an unfinished run of the same flags is resumed). "
                      "Only what a run wrote is deleted, and only after every flag and the data "
                      "are checked; a folder that is not a training run is never touched.")


def config_from_flags(**overrides) -> TrainConfig:
    """The TrainConfig of the flags: the preset of ``--recipe`` and of the model kind in
    ``overrides`` (:func:`stnh_tf.training.preset_fields`: e.g. DeTone's schedule for
    ``model="homographynet"``, 90,000 steps for ``"sequence"``), then every flag given
    explicitly, then ``overrides``."""
    f = flags.FLAGS
    model = overrides.get("model", TrainConfig.model)
    preset = {k: v for k, v in training.preset_fields(f.recipe, model).items()
              if not f[k].present}
    cfg = TrainConfig(
        data_dir=f.data_dir, model_dir=f.model_dir, train_steps=f.train_steps,
        warmup_steps=f.warmup_steps, batch_size=f.batch_size, learning_rate=f.learning_rate,
        momentum=f.momentum, l2_weight=f.l2_weight, l1_weight=f.l1_weight,
        batch_norm=f.batch_norm, dropout=f.dropout, seed=f.seed, shuffle_buffer=f.shuffle_buffer,
        mixed_precision=f.mixed_precision, checkpoint_every=f.checkpoint_every,
        log_every=f.log_every, val_split=f.val_split, val_samples=f.val_samples,
        strategy=f.strategy, image_dir=",".join(f.image_dir),
        val_image_dir=",".join(f.val_image_dir), samples_per_image=f.samples_per_image,
        fresh_pairs=f.fresh_pairs, workers=f.workers, in_memory=f.in_memory,
        prev_stages=tuple(f.prev_stages), optimizer=f.optimizer, weight_decay=f.weight_decay,
        clipnorm=f.clipnorm, l2_reduction=f.l2_reduction, photometric=f.photometric,
        recipe=f.recipe, lr_schedule=f.lr_schedule)
    for k, v in {**preset, **overrides}.items():
        setattr(cfg, k, v)
    return cfg


def run_training(cfg, binary: str) -> None:
    """Train (or resume) ``cfg``; user errors exit with ``{binary}: message``, not a traceback."""
    from absl import logging

    from stnh_tf import training

    try:
        result = training.train(cfg, overwrite=flags.FLAGS.overwrite, printer=logging.info)
    except (ValueError, OSError, training.TrainingDiverged) as e:
        raise SystemExit(f"{binary}: {e}") from None
    logging.info("finished at step %d", result["final_step"])
