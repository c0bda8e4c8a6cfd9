"""The named presets of a training run's fields (:class:`stnh_tf.training.config.TrainConfig`):
the recipes (``--recipe``) and the model kinds' defaults, which the training binaries apply
beneath the flags given explicitly (:func:`preset_fields`), and the model kinds they are keyed
by. Standard library only."""

from __future__ import annotations

MODEL_KINDS = ("stn", "sequence", "homographynet", "homographynet_gap")
# The kinds that regress DeTone et al.'s 4-point offsets (output "offsets", one L2 loss):
# "homographynet" is DeTone's network (models.build_homographynet), "homographynet_gap" the same
# regression on this project's backbone (models.build_homographynet_gap).
FOUR_POINT_KINDS = ("homographynet", "homographynet_gap")

# Defaults that depend on the model kind: what ``preset_fields`` (and so the training binaries)
# set beneath a recipe's preset and the flags given explicitly. TrainConfig's own defaults do not
# change with the model.
MODEL_DEFAULTS = {
    # The paper trains its sequence model for "total training steps of 90000" (section 5),
    # warm-up included, where each hierarchical stage trains 1,000 + 90,000.
    "sequence": {"train_steps": 90_000},
    # DeTone et al.'s network and recipe: BatchNorm after every convolution; SGD momentum 0.9,
    # batch 64, learning rate 0.005 divided by 10 every 30,000 of their 90,000 iterations (the
    # step schedule divides after every third of train_steps, whatever it is), no warm-up.
    "homographynet": {"batch_norm": "conv", "learning_rate": 0.005, "lr_schedule": "step",
                      "warmup_steps": 0, "train_steps": 90_000},
}

# Named presets of TrainConfig fields. "paper" is the paper's recipe (the defaults); "fast" is a
# deviation chosen for accuracy per CPU step (BENCHMARKS.md, "A faster recipe").
RECIPES = {
    "paper": {},
    "fast": {"optimizer": "adamw", "learning_rate": 1e-3, "weight_decay": 1e-4,
             "warmup_steps": 100, "lr_schedule": "cosine", "l2_reduction": "sum",
             "input_norm": "patch"},
}
# Recipe fields that only the STN kinds use: a preset leaves them out for the 4-point kinds
# (one L2 loss on offsets, input scaled to [-1, 1]).
STN_ONLY_FIELDS = ("l2_reduction", "input_norm")


def preset_fields(recipe: str, model: str) -> dict:
    """The TrainConfig fields that ``recipe`` (a key of :data:`RECIPES`) and ``model`` (a key of
    :data:`MODEL_KINDS`) preset: :data:`MODEL_DEFAULTS` of the model, then the recipe's preset
    over them (so ``--recipe=fast`` replaces HomographyNet's step schedule by its own), less
    :data:`STN_ONLY_FIELDS` for the 4-point kinds. The training binaries apply these to every
    field not given explicitly.

    Raises:
      ValueError: an unknown recipe or model.

    >>> preset_fields("fast", "homographynet")["lr_schedule"], preset_fields("paper", "stn")
    ('cosine', {})
    """
    if recipe not in RECIPES:
        raise ValueError(f"recipe must be one of {sorted(RECIPES)}; received {recipe!r}.")
    if model not in MODEL_KINDS:
        raise ValueError(f"model must be one of {MODEL_KINDS}; received {model!r}.")
    recipe_fields = {k: v for k, v in RECIPES[recipe].items()
                     if model not in FOUR_POINT_KINDS or k not in STN_ONLY_FIELDS}
    return {**MODEL_DEFAULTS.get(model, {}), **recipe_fields}
