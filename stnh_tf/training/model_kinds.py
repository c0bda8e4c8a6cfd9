"""The model kinds a run can train, each defined once: how to build it, its losses and metrics,
and how the dataset's targets map onto its outputs (:data:`KINDS`, keyed like
:data:`stnh_tf.training.presets.MODEL_KINDS`, which the binaries' ``--model`` flag offers).

A run with pairs without ground truth (:func:`has_unlabeled_pairs`) builds its STN
model with the output :data:`~stnh_tf.modeling.models.WARP_VALID` and trains each pair on its own
target (:func:`_unlabeled_targets`): a labeled pair (``h_mask`` 1) on the paper's L2 and L1
losses against ``H_bar`` and ``patch_a_t``, exactly as in a fully labeled run; a pair without
(``h_mask`` 0) on :func:`~stnh_tf.modeling.losses.photometric_l1_valid` against ``patch_b``
alone, with nothing made from its ``H``. A fully labeled run builds and trains the paper's model
unchanged.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable

import keras

from stnh_tf.modeling import losses as losses_lib
from stnh_tf.modeling import models, runner
from stnh_tf.modeling.layers import HOMOGRAPHYNET_SCALE
from stnh_tf.training.config import TrainConfig
from stnh_tf.training.presets import MODEL_KINDS

def has_unlabeled_pairs(cfg: TrainConfig) -> bool:
    """Whether the run trains pairs without ground truth (``h_mask`` 0): ``label_fraction`` < 1
    without ``drop_unlabeled``, ``unlabeled_image_dir`` or ``unlabeled_pairs_dir``. Such a run's
    STN model has the output :data:`~stnh_tf.modeling.models.WARP_VALID` that trains them; a run
    without trains the paper's model.

    >>> has_unlabeled_pairs(TrainConfig(label_fraction=0.1))
    True
    >>> has_unlabeled_pairs(TrainConfig(label_fraction=0.1, drop_unlabeled=True))
    False
    """
    return bool((cfg.label_fraction < 1 and not cfg.drop_unlabeled) or cfg.unlabeled_image_dir
                or cfg.unlabeled_pairs_dir)


def l2_term_weight(cfg: TrainConfig) -> float:
    """The loss weight of :func:`stnh_tf.modeling.losses.h_bar_l2` (a mean over H_bar's 8 entries):
    ``l2_weight``, times 8 with ``l2_reduction="sum"`` (a sum over the 8 entries)."""
    return cfg.l2_weight * (8.0 if cfg.l2_reduction == "sum" else 1.0)


# -- pairs without ground truth ---------------------------------------------------------------
def _unlabeled_targets(x, y, w):
    """The dataset's ``(x, y, w)`` (keys ``h_bar``, ``patch_a_warp``; ``w["h_bar"]`` is
    ``h_mask``) onto a model with :data:`~stnh_tf.modeling.models.WARP_VALID` (NumPy or
    TensorFlow arrays): ``h_bar`` and ``patch_a_warp`` (``patch_a_t``) keep their targets with
    weight ``h_mask`` (a labeled pair's are the paper's, times 1; an unlabeled pair's
    ``patch_a_t`` is zeroed, its ``H_bar`` already is, and both weigh 0); ``WARP_VALID`` gets
    ``patch_b`` with weight ``1 - h_mask``. So an unlabeled pair's loss reads nothing made from
    its ``H``."""
    h_mask = w["h_bar"]
    y = {"h_bar": y["h_bar"], "patch_a_warp": y["patch_a_warp"] * h_mask[:, None, None, None],
         models.WARP_VALID: x["patch_b"]}
    w = {"h_bar": h_mask, "patch_a_warp": h_mask, models.WARP_VALID: 1.0 - h_mask}
    return x, y, w


# -- stn: the paper's single stage -------------------------------------------------------------
def _stn_losses(cfg):
    losses = {"h_bar": losses_lib.h_bar_l2, "patch_a_warp": losses_lib.photometric_l1}
    weights = {"h_bar": l2_term_weight(cfg), "patch_a_warp": cfg.l1_weight}
    if has_unlabeled_pairs(cfg):
        losses[models.WARP_VALID] = losses_lib.photometric_l1_valid
        weights[models.WARP_VALID] = cfg.l1_weight
    return losses, weights, {"h_bar": [losses_lib.MeanCornerError()]}


# -- sequence: stages chained by the merge layer, every stage supervised -----------------------
def _sequence_losses(cfg):
    l2 = l2_term_weight(cfg)
    weights = list(cfg.stage_loss_weights) or [1.0] * cfg.num_stages
    losses, loss_weights, metrics = {}, {}, {}
    h_names, w_names = models.sequence_output_names(cfg.num_stages)
    for k, (hn, wn) in enumerate(zip(h_names, w_names)):
        losses[hn], loss_weights[hn] = losses_lib.h_bar_l2, l2 * weights[k]
        losses[wn], loss_weights[wn] = losses_lib.photometric_l1, cfg.l1_weight * weights[k]
        metrics[hn] = [losses_lib.MeanCornerError()]
        if has_unlabeled_pairs(cfg):
            vn = f"{models.WARP_VALID}_{k + 1}"
            losses[vn] = losses_lib.photometric_l1_valid
            loss_weights[vn] = cfg.l1_weight * weights[k]
    return losses, loss_weights, metrics


def _sequence_targets(x, y, w, num_stages, unlabeled=False):
    """Every stage's outputs get the dataset's targets (``h_bar_k``, ``patch_a_warp_k``; with
    ``unlabeled``, :func:`_unlabeled_targets`' ``patch_a_warp_valid_k`` too)."""
    if unlabeled:
        x, y, w = _unlabeled_targets(x, y, w)
    ys, ws = {}, {}
    for hn, wn in zip(*models.sequence_output_names(num_stages)):
        ys[hn], ys[wn] = y["h_bar"], y["patch_a_warp"]
        ws[hn], ws[wn] = w["h_bar"], w["patch_a_warp"]
    if unlabeled:
        for k in range(1, num_stages + 1):
            ys[f"{models.WARP_VALID}_{k}"] = y[models.WARP_VALID]
            ws[f"{models.WARP_VALID}_{k}"] = w[models.WARP_VALID]
    return x, ys, ws


# -- homographynet, homographynet_gap: DeTone et al.'s 4-point offsets, one L2 loss ------------
def _four_point_losses(cfg):
    return ({"offsets": "mse"}, {"offsets": 1.0}, {"h_bar": [losses_lib.MeanCornerError()]})


def _homographynet_targets(x, y, w):
    from stnh_tf import geometry

    h = geometry.denormalize_homography(geometry.vector_to_matrix(y["h_bar"]))
    offsets = keras.ops.reshape(geometry.homography_to_offsets(h), (-1, 8))
    offsets = offsets / HOMOGRAPHYNET_SCALE
    # patch_a_warp carries no loss (HomographyNet has no photometric term) but Keras matches the
    # targets to every output.
    return (x, {"offsets": offsets, "h_bar": y["h_bar"], "patch_a_warp": y["patch_a_warp"]},
            {"offsets": w["h_bar"], "h_bar": w["h_bar"], "patch_a_warp": w["patch_a_warp"]})


@dataclasses.dataclass(frozen=True)
class ModelKind:
    """One model kind: ``build(cfg) -> keras.Model``; ``losses(cfg) -> (losses, loss_weights,
    metrics)`` keyed by output names; ``targets(cfg) -> mapper | None`` from the dataset's
    ``(x, y, sample_weight)`` (keys ``h_bar``, ``patch_a_warp``) to the model's outputs (None:
    the dataset's keys already are the outputs; mappers are picklable, for worker processes)."""

    build: Callable
    losses: Callable
    targets: Callable


KINDS = {
    "stn": ModelKind(
        build=lambda cfg: models.build_stn_homography(
            batch_norm=cfg.batch_norm, dropout=cfg.dropout, input_norm=cfg.input_norm,
            unlabeled_output=has_unlabeled_pairs(cfg)),
        losses=_stn_losses,
        targets=lambda cfg: _unlabeled_targets if has_unlabeled_pairs(cfg) else None),
    "sequence": ModelKind(
        build=lambda cfg: models.build_sequence_stn_homography(
            cfg.num_stages, batch_norm=cfg.batch_norm, dropout=cfg.dropout,
            input_norm=cfg.input_norm, unlabeled_output=has_unlabeled_pairs(cfg)),
        losses=_sequence_losses,
        targets=lambda cfg: functools.partial(_sequence_targets, num_stages=cfg.num_stages,
                                              unlabeled=has_unlabeled_pairs(cfg))),
    # DeTone's network: BatchNorm always, dropout twice.
    "homographynet": ModelKind(
        build=lambda cfg: models.build_homographynet(dropout=cfg.dropout),
        losses=_four_point_losses, targets=lambda cfg: _homographynet_targets),
    "homographynet_gap": ModelKind(
        build=lambda cfg: models.build_homographynet_gap(batch_norm=cfg.batch_norm,
                                                         dropout=cfg.dropout),
        losses=_four_point_losses, targets=lambda cfg: _homographynet_targets),
}
if tuple(KINDS) != MODEL_KINDS:
    raise ImportError(f"model_kinds.KINDS {tuple(KINDS)} must list presets.MODEL_KINDS "
                      f"{MODEL_KINDS} in order.")


def build_model(cfg: TrainConfig) -> keras.Model:
    """The untrained model of ``cfg.model``."""
    return KINDS[cfg.model].build(cfg)


def loss_spec(cfg: TrainConfig):
    """(losses, loss_weights, metrics) dicts keyed by the model's output names. Raises
    ``ValueError`` for loss settings the model kind cannot use
    (:meth:`TrainConfig.check_losses`)."""
    cfg.check_losses()
    return KINDS[cfg.model].losses(cfg)


def targets_for(cfg: TrainConfig) -> Callable | None:
    """The mapper of the dataset's targets onto ``cfg.model``'s outputs (:class:`ModelKind`)."""
    return KINDS[cfg.model].targets(cfg)


def initialize_from(model, stage_dirs):
    """Copy the regression weights of trained single-stage STN models (``stage_dirs``: model dirs
    holding ``model.keras``, or ``.keras`` files) into ``model``: a sequence model's
    ``regression_k`` from dir k, or a single stage's ``regression`` from its one dir.

    Raises:
      ValueError: a dir holds another model kind, a single stage is given other than one dir, or
        the regression networks differ in their layers (batch_norm, input_norm).
    """
    single = "regression" in [layer.name for layer in model.layers]
    if single and len(stage_dirs) != 1:
        raise ValueError(f"a single stage is initialised from one model dir; received "
                         f"{len(stage_dirs)}.")
    for k, d in enumerate(stage_dirs, start=1):
        src = runner.load_model(d)
        # (a run with unlabeled pairs adds models.WARP_VALID, "patch_a_warp_valid")
        if sorted(set(src.output_names) - {"patch_a_warp_valid"}) != ["h_bar", "patch_a_warp"]:
            raise ValueError(f"{d} is not a single-stage STN-Homography model (its outputs are "
                             f"{sorted(src.output_names)}); init_from takes train_stage "
                             "--model=stn runs.")
        regression = src.get_layer("regression")
        target = model.get_layer("regression" if single else f"regression_{k}")
        src_layers, dst_layers = ([layer.name for layer in net.layers
                                   if not isinstance(layer, keras.layers.InputLayer)]
                                  for net in (regression, target))
        if src_layers != dst_layers:
            raise ValueError(f"{d}'s regression network has layers {src_layers}, this model's "
                             f"{dst_layers}: init_from needs the same batch_norm and input_norm.")
        target.set_weights(regression.get_weights())
