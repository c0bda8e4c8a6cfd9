"""STN-Homography models (Zhou & Li 2019, sections 3-5) as Functional Keras models.

* :func:`regression_network`: the paper's VGG-style regressor, ``[B,128,128,2] -> [B,8]``.
* :func:`build_stn_homography`: one stage, ``{"patch_a", "patch_b"} -> {"h_bar", "patch_a_warp"}``.
* :func:`build_sequence_stn_homography` (alias :data:`SequenceSTNHomography`): n stages chained by
  :class:`HomographyMerge`.
* :func:`build_homographynet`: DeTone et al.'s HomographyNet as they describe it (baseline);
  :func:`build_homographynet_gap`: the same 4-point regression on this project's backbone.

Inputs are float32 patches in ``[0, 1]``, ``[B, 128, 128, 1]``. ``h_bar`` is the normalized
``H_ba`` (patch_b -> patch_a, the paper's ``M``; see :mod:`stnh_tf.geometry`), and
``patch_a_warp(p) = patch_a(H_ba @ p)``, the image compared with patch_a_t by the L1 loss.
"""

from __future__ import annotations

import keras
import numpy as np
from keras import layers

from stnh_tf import geometry
from stnh_tf.modeling.layers import (HomographyMerge, OffsetsToHBar, PatchStandardization,
                                     SpatialTransformer, WarpValidity)

IDENTITY_H_BAR = np.array([1, 0, 0, 0, 1, 0, 0, 0], dtype=np.float32)
WARP_VALID = "patch_a_warp_valid"
"""The output a model trained with pairs without ground truth has beside ``patch_a_warp``
(``unlabeled_output=True``; ``patch_a_warp_valid_k`` per sequence stage): ``[B, S, S, 2]``,
``patch_a_warp`` and its validity mask, what :func:`stnh_tf.modeling.losses.photometric_l1_valid`
compares with patch_b."""
CONV_FILTERS = (64, 64, 64, 64, 128, 128, 128, 128)
BATCH_NORM_CHOICES = ("none", "conv")
HEAD_CHOICES = ("gap", "flatten")
INPUT_NORM_CHOICES = ("unit", "patch")
DEFAULT_BATCH_NORM = "none"
"""The paper's literal network (no BatchNorm): it trains stably at the paper's learning rate 0.05
with the identity-initialised output layer, and a training step costs about a quarter of the
BatchNorm variant's on a CPU (docs/training.md, "Batch normalization")."""


def regression_network(batch_norm: str = DEFAULT_BATCH_NORM, dropout: float = 0.5,
                       dense_units: int = 1024, outputs: int = 8, last_init: str = "identity",
                       size: int = geometry.PATCH_SIZE,
                       name: str = "regression", head: str = "gap",
                       conv_dropout: float = 0.0, input_norm: str = "unit") -> keras.Model:
    """The paper's regression network (and, with ``head="flatten"``, DeTone et al.'s).

    8 conv 3x3 layers (64, 64, 64, 64, 128, 128, 128, 128 filters, ReLU), 2x2 stride-2 max pooling
    after each of the first three pairs of convolutions, global average pooling, Dense 1024 + ReLU,
    Dropout, Dense 8 (768,904 parameters). Three pools, not four: the paper says both "a max
    pooling layer after every two convolutions" and "the output deep features of [the] last
    convolutional layer are followed by a global average pooling layer"; we follow the second.
    Three pools are also DeTone et al.'s HomographyNet layout, from which the paper's text is taken
    (its 3 pools end at 16x16x128), but DeTone flattens that map into the 1024-unit layer where
    the paper (and this default) averages it globally: here the global average runs over 16x16
    (128 -> 64 -> 32 -> 16).

    Args:
      batch_norm: ``"none"`` (default) is the paper's literal text and trains stably at the
        paper's learning rate 0.05; ``"conv"`` puts BatchNormalization after every convolution
        (bias off), about 4x slower per step on a CPU (see docs/training.md).
      dropout: rate of the dropout after the 1024-unit layer (layer ``dropout``).
      last_init: how the last layer starts: ``"identity"`` (default): zero kernel and the
        identity ``H_bar`` as bias (as Jaderberg et al. initialise a spatial transformer's
        localisation net), so an untrained stage predicts "no motion" rather than noise;
        ``"zeros"``: zero kernel and bias (4-point offsets of no motion); ``"glorot"``:
        Glorot-uniform kernel, zero bias.
      head: ``"gap"`` (default): global average pooling of conv8's ``[16, 16, 128]`` map (layer
        ``gap``, ``[B, 128]``); ``"flatten"``: the map flattened (layer ``flatten``,
        ``[B, 32768]``), DeTone et al.'s (33.6 M parameters in ``fc1``).
      conv_dropout: rate of a dropout after conv8's ReLU (layer ``dropout_conv``; 0: none, the
        paper's). DeTone et al. use 0.5.
      input_norm: ``"unit"`` (default): the pair scaled from ``[0, 1]`` to ``[-1, 1]`` (layer
        ``to_unit_range``); ``"patch"``: each patch standardized to zero mean and unit variance
        (:class:`PatchStandardization`, layer ``patch_standardization``), a deviation from the
        paper that makes the input blind to a brightness or contrast change between the patches.
    Input ``[B, size, size, 2]`` (patch_a, patch_b); output ``[B, outputs]`` float32.

    Raises:
      ValueError: an unknown ``batch_norm``, ``head``, ``input_norm`` or ``last_init``, or a
        dropout rate outside ``[0, 1)``.
    """
    if batch_norm not in BATCH_NORM_CHOICES:
        raise ValueError(f"batch_norm must be one of {BATCH_NORM_CHOICES}; "
                         f"received {batch_norm!r}.")
    if head not in HEAD_CHOICES:
        raise ValueError(f"head must be one of {HEAD_CHOICES}; received {head!r}.")
    if input_norm not in INPUT_NORM_CHOICES:
        raise ValueError(f"input_norm must be one of {INPUT_NORM_CHOICES}; received "
                         f"{input_norm!r}.")
    for label, rate in (("dropout", dropout), ("conv_dropout", conv_dropout)):
        if not 0.0 <= rate < 1.0:
            raise ValueError(f"{label} must be in [0, 1); received {rate}.")
    if (last_init not in ("identity", "zeros", "glorot")
            or (last_init == "identity" and outputs != 8)):
        raise ValueError(f"last_init must be 'identity' (8 outputs), 'zeros' or 'glorot'; received "
                         f"{last_init!r} with {outputs} outputs.")
    inputs = keras.Input((size, size, 2), name=f"{name}_pair")
    if input_norm == "patch":
        x = PatchStandardization(name="patch_standardization")(inputs)
    else:
        x = layers.Rescaling(2.0, offset=-1.0, name="to_unit_range")(inputs)  # [0,1] -> [-1,1]
    for i, filters in enumerate(CONV_FILTERS):
        use_bn = batch_norm == "conv"
        x = layers.Conv2D(filters, 3, padding="same", use_bias=not use_bn,
                          kernel_initializer="he_normal", name=f"conv{i + 1}")(x)
        if use_bn:
            x = layers.BatchNormalization(name=f"bn{i + 1}")(x)
        x = layers.ReLU(name=f"relu{i + 1}")(x)
        if i % 2 == 1 and i < len(CONV_FILTERS) - 1:
            x = layers.MaxPooling2D(2, strides=2, name=f"pool{i // 2 + 1}")(x)
    if conv_dropout:
        x = layers.Dropout(conv_dropout, name="dropout_conv")(x)
    if head == "gap":
        x = layers.GlobalAveragePooling2D(name="gap")(x)
    else:
        x = layers.Flatten(name="flatten")(x)
    x = layers.Dense(dense_units, activation="relu", kernel_initializer="he_normal", name="fc1")(x)
    x = layers.Dropout(dropout, name="dropout")(x)
    kernel_init, bias_init = {
        "identity": ("zeros", keras.initializers.Constant(IDENTITY_H_BAR.tolist())),
        "zeros": ("zeros", "zeros"), "glorot": ("glorot_uniform", "zeros")}[last_init]
    out = layers.Dense(outputs, kernel_initializer=kernel_init, bias_initializer=bias_init,
                       dtype="float32", name="fc2")(x)
    return keras.Model(inputs, out, name=name)


def _patch_inputs(size):
    patch_a = keras.Input((size, size, 1), name="patch_a")
    patch_b = keras.Input((size, size, 1), name="patch_b")
    return patch_a, patch_b


def _stage(patch_a_in, patch_b, regressor, stage_name):
    pair = layers.Concatenate(axis=-1, name=f"{stage_name}_pair")([patch_a_in, patch_b])
    return regressor(pair)


def _warp_valid(patch_a, h_bar, warp, name):
    """``[B, S, S, 2]``: ``warp`` and its :class:`WarpValidity` mask (layer ``{name}_mask``),
    concatenated in float32 (layer ``name``)."""
    mask = WarpValidity(name=f"{name}_mask")([patch_a, h_bar])
    return layers.Concatenate(axis=-1, name=name, dtype="float32")([warp, mask])


def build_stn_homography(batch_norm: str = DEFAULT_BATCH_NORM, dropout: float = 0.5,
                         size: int = geometry.PATCH_SIZE, name: str = "stn_homography",
                         input_norm: str = "unit", unlabeled_output: bool = False) -> keras.Model:
    """Single STN-Homography stage.

    Inputs ``{"patch_a", "patch_b"}`` (``[B, S, S, 1]`` float in [0, 1]); outputs
    ``{"h_bar": [B, 8] float32, "patch_a_warp": [B, S, S, 1]}`` where ``patch_a_warp`` is patch_a
    warped by the predicted ``H_ba`` (sampled at ``H_ba @ p``). ``batch_norm``, ``dropout`` and
    ``input_norm`` are :func:`regression_network`'s. ``unlabeled_output``: also
    :data:`WARP_VALID` ``[B, S, S, 2]`` (the warp and where it is defined), the output that
    trains the pairs without ground truth; the weights are the same either way.
    """
    patch_a, patch_b = _patch_inputs(size)
    regressor = regression_network(batch_norm=batch_norm, dropout=dropout, size=size,
                                   input_norm=input_norm)
    h_bar = _stage(patch_a, patch_b, regressor, "stage1")
    h_bar = layers.Identity(name="h_bar", dtype="float32")(h_bar)
    warp = SpatialTransformer(name="patch_a_warp", dtype="float32")([patch_a, h_bar])
    outputs = {"h_bar": h_bar, "patch_a_warp": warp}
    if unlabeled_output:
        outputs[WARP_VALID] = _warp_valid(patch_a, h_bar, warp, WARP_VALID)
    return keras.Model({"patch_a": patch_a, "patch_b": patch_b}, outputs, name=name)


def sequence_output_names(num_stages: int):
    """Output names of a sequence model: ``h_bar_k`` and ``patch_a_warp_k`` for k = 1..n."""
    return ([f"h_bar_{k}" for k in range(1, num_stages + 1)],
            [f"patch_a_warp_{k}" for k in range(1, num_stages + 1)])


def _check_num_stages(num_stages):
    if (isinstance(num_stages, bool) or not isinstance(num_stages, (int, np.integer))
            or num_stages < 1):
        raise ValueError(f"num_stages must be an integer >= 1; received {num_stages!r}.")
    return int(num_stages)


def sequence_stages(patch_a, patch_b, num_stages: int, regress,
                    unlabeled_output: bool = False) -> dict:
    """The wiring of Sequence STN-Homography (paper section 5; conventions section 3), on tensors.

    The single implementation used by :func:`build_sequence_stn_homography`; tests call it with
    an oracle ``regress`` to check the composition with the real layers.

    For k = 1..n: stage k stacks ``(warp_{k-1}, patch_b)`` (``warp_0`` = patch_a) into the pair
    ``[B, S, S, 2]`` (layer ``stage{k}_pair``), regresses the residual ``H_k'`` (patch_b ->
    patch_a_warp_{k-1}), merges ``H_k = H_{k-1} @ H_k'`` (:class:`HomographyMerge` ``merge_k``,
    rescaled to ``[2,2] = 1``; ``H_1 = H_1'``), and warps the **original** patch_a with ``H_k``:
    ``patch_a_warp_k(p) = patch_a(H_k @ p)`` (:class:`SpatialTransformer` ``patch_a_warp_k``).

    Args:
      patch_a, patch_b: symbolic ``[B, S, S, 1]`` tensors.
      num_stages: n >= 1.
      regress: ``regress(k, pair, h_prev) -> [B, 8]`` normalized ``H_k'``; ``pair`` is the stage's
        ``[B, S, S, 2]`` input, ``h_prev`` the merged ``[B, 8]`` ``H_{k-1}`` (``None`` for k = 1).
        A real stage uses only ``pair``.
      unlabeled_output: also ``patch_a_warp_valid_k`` ``[B, S, S, 2]`` for every k (the warp
        and where it is defined: :data:`WARP_VALID`).
    Returns:
      ``{"h_bar_k": [B, 8] float32, "patch_a_warp_k": [B, S, S, 1]}`` for k = 1..n.
    """
    num_stages = _check_num_stages(num_stages)
    outputs = {}
    warp, h_prev = patch_a, None
    for k in range(1, num_stages + 1):
        pair = layers.Concatenate(axis=-1, name=f"stage{k}_pair")([warp, patch_b])
        h_res = regress(k, pair, h_prev)
        h_k = h_res if h_prev is None else HomographyMerge(name=f"merge_{k}")([h_prev, h_res])
        h_k = layers.Identity(name=f"h_bar_{k}", dtype="float32")(h_k)
        warp = SpatialTransformer(name=f"patch_a_warp_{k}", dtype="float32")([patch_a, h_k])
        outputs[f"h_bar_{k}"] = h_k
        outputs[f"patch_a_warp_{k}"] = warp
        if unlabeled_output:
            outputs[f"{WARP_VALID}_{k}"] = _warp_valid(patch_a, h_k, warp, f"{WARP_VALID}_{k}")
        h_prev = h_k
    return outputs


def build_sequence_stn_homography(num_stages: int = 2, batch_norm: str = DEFAULT_BATCH_NORM,
                                  dropout: float = 0.5, size: int = geometry.PATCH_SIZE,
                                  name: str | None = None,
                                  regressor_factory=None, input_norm: str = "unit",
                                  unlabeled_output: bool = False) -> keras.Model:
    """Sequence STN-Homography (paper section 5), trained end to end. Also
    :data:`SequenceSTNHomography`.

    Stage 1 regresses ``H_1`` from (patch_a, patch_b); stage k regresses ``H_k'`` from
    (patch_a_warp_{k-1}, patch_b); :class:`HomographyMerge` forms ``H_k = H_{k-1} @ H_k'``; every
    stage warps the **original** patch_a with ``H_k`` (see :func:`sequence_stages`). Each stage has
    its own regression network (sub-model ``regression_k``, the layout
    :func:`stnh_tf.training.model_kinds.initialize_from` copies single-stage weights into).

    Inputs ``{"patch_a", "patch_b"}`` (``[B, S, S, 1]`` float in [0, 1]); outputs ``h_bar_k``
    ``[B, 8]`` float32 (normalized ``H_ba`` after k stages) and ``patch_a_warp_k`` ``[B, S, S, 1]``
    for every k (names from :func:`sequence_output_names`).

    Args:
      regressor_factory: optional ``factory(k) -> layer`` mapping the pair ``[B, S, S, 2]`` to
        ``[B, 8]`` (e.g. a small network in tests); default :func:`regression_network` named
        ``regression_k`` with ``batch_norm``, ``dropout`` and ``input_norm``.
      unlabeled_output: also ``patch_a_warp_valid_k`` (:func:`sequence_stages`).
    """
    num_stages = _check_num_stages(num_stages)
    if regressor_factory is None:
        def regressor_factory(k):
            return regression_network(batch_norm=batch_norm, dropout=dropout, size=size,
                                      name=f"regression_{k}", input_norm=input_norm)
    regressors = {k: regressor_factory(k) for k in range(1, num_stages + 1)}
    patch_a, patch_b = _patch_inputs(size)
    outputs = sequence_stages(patch_a, patch_b, num_stages,
                              lambda k, pair, h_prev: regressors[k](pair), unlabeled_output)
    return keras.Model({"patch_a": patch_a, "patch_b": patch_b}, outputs,
                       name=name or f"sequence_stn_homography_{num_stages}")


SequenceSTNHomography = build_sequence_stn_homography
"""Public name of the sequence model: ``SequenceSTNHomography(num_stages=2, ...)`` returns the
Functional model of :func:`build_sequence_stn_homography` (the same function)."""


def _four_point_model(regressor, size: int, name: str) -> keras.Model:
    """Wire a 4-point ``regressor`` (pair ``[B, S, S, 2]`` -> offsets / 32 ``[B, 8]``) into the
    baseline's model: outputs ``{"offsets", "h_bar", "patch_a_warp"}`` (see
    :func:`build_homographynet`)."""
    patch_a, patch_b = _patch_inputs(size)
    pair = layers.Concatenate(axis=-1, name="stage1_pair")([patch_a, patch_b])
    offsets = layers.Identity(name="offsets", dtype="float32")(regressor(pair))
    h_bar = OffsetsToHBar(size=size, name="h_bar")(offsets)
    warp = SpatialTransformer(name="patch_a_warp", dtype="float32")([patch_a, h_bar])
    return keras.Model({"patch_a": patch_a, "patch_b": patch_b},
                       {"offsets": offsets, "h_bar": h_bar, "patch_a_warp": warp}, name=name)


def build_homographynet(dropout: float = 0.5, size: int = geometry.PATCH_SIZE,
                        name: str = "homographynet") -> keras.Model:
    """HomographyNet as DeTone et al. (2016) describe it: the baseline of the paper's Fig. 4.

    Regressor (sub-model ``regression``): 8 conv 3x3 layers (64, 64, 64, 64, 128, 128, 128, 128
    filters), each followed by BatchNormalization (convolution bias off) and ReLU; 2x2 stride-2 max
    pooling after conv2, conv4 and conv6 (128 -> 64 -> 32 -> 16); dropout ``dropout`` after
    conv8; the ``[16, 16, 128]`` map flattened (32,768 values) into Dense 1024 + ReLU; dropout
    ``dropout``; Dense 8: the four corners' offsets ``H_ba @ c - c`` (pixels, corners of
    :func:`geometry.patch_corners`) divided by 32
    (:data:`~stnh_tf.modeling.layers.HOMOGRAPHYNET_SCALE`, the perturbation range, so targets
    lie in ``[-1, 1]``). 34,194,568 parameters (3,072 of them BatchNorm's moving
    statistics). As in every model here the input pair is scaled from ``[0, 1]`` to ``[-1, 1]``;
    kernels start He-normal (convolutions, ``fc1``) and ``fc2`` at zero kernel and bias, so an
    untrained network predicts no motion (DeTone et al. state no initialisation; why this one:
    docs/training.md).
    Trained with DeTone's schedule by default (:data:`stnh_tf.training.presets.MODEL_DEFAULTS`).

    Inputs ``{"patch_a", "patch_b"}`` (``[B, S, S, 1]`` float in [0, 1]); outputs
    ``{"offsets": [B, 8] (pixels / 32), "h_bar": [B, 8], "patch_a_warp": [B, S, S, 1]}``; only
    ``offsets`` is trained (L2 against the true offsets / 32), the others let it be evaluated
    through the same path as STN-Homography.
    """
    regressor = regression_network(batch_norm="conv", dropout=dropout, size=size,
                                   last_init="zeros", name="regression", head="flatten",
                                   conv_dropout=dropout)
    return _four_point_model(regressor, size, name)


def build_homographynet_gap(batch_norm: str = DEFAULT_BATCH_NORM, dropout: float = 0.5,
                            size: int = geometry.PATCH_SIZE,
                            name: str = "homographynet_gap") -> keras.Model:
    """DeTone et al.'s 4-point regression on this project's backbone (:func:`regression_network`:
    global average pooling, BatchNorm only with ``batch_norm="conv"``, one dropout): the variant
    that model kind ``"homographynet"`` built before it became :func:`build_homographynet`, kept
    for comparison and for the runs trained with it.

    Inputs and outputs as :func:`build_homographynet`.
    """
    regressor = regression_network(batch_norm=batch_norm, dropout=dropout, size=size,
                                   last_init="glorot", name="regression")
    return _four_point_model(regressor, size, name)
