"""A run's first training steps, one record each: why a run diverges in its first steps.

:func:`trace` trains a fresh model of a :class:`~stnh_tf.training.config.TrainConfig` for a few
steps on its own training stream, with its optimizer, schedule and losses (Keras' ``train_step``:
loss, gradients, ``optimizer.apply``), and records per step the loss terms, the global gradient
norm before any clip, each output's MACE and, for a sequence model, the smallest ``|[2,2]|`` of
each merge's product ``H_{k-1} @ H_k'`` before the merge rescales by it. Hand-written because
``fit`` reports neither a gradient norm nor a layer's inputs.
"""

from __future__ import annotations

import numpy as np

from stnh_tf import geometry
from stnh_tf.training.config import TrainConfig, dtype_policy

MERGE_PREFIX = "merge_"
"""The sequence model's merge layers: ``merge_k``
(:func:`stnh_tf.modeling.models.sequence_stages`)."""


def merge_denominators(h_prev, h_res) -> np.ndarray:
    """``|(H_prev @ H_res)[2,2]|`` ``[B]`` of a merge's inputs (each ``[B, 8]``, ``[2,2] = 1``):
    what :class:`~stnh_tf.modeling.layers.HomographyMerge` divides the product by."""
    prev = geometry.vector_to_matrix(np.asarray(h_prev, np.float64))
    res = geometry.vector_to_matrix(np.asarray(h_res, np.float64))
    return np.abs((prev @ res)[:, 2, 2])


def trace(cfg: TrainConfig, steps: int, printer=None) -> list:
    """Train ``cfg``'s model (fresh weights, ``keras.utils.set_random_seed(cfg.seed)``, then
    ``cfg.init_from``'s as :func:`~stnh_tf.training.loop.train` starts) for ``steps`` steps of
    its TFRecord stream and return one dict a step: ``step`` (1-based), ``learning_rate`` (the
    optimizer's for that update), ``loss`` (the weighted total ``fit`` minimises), ``terms`` (each
    output's loss, mean over the batch, sample weights not applied), ``grad_norm`` (global, before
    any clip), ``mace`` (px, each ``h_bar`` output) and ``merge_min_w`` (``{merge_k: min over the
    batch of`` :func:`merge_denominators` ``}``; empty for a single stage). ``printer`` gets each
    dict as it is made. Nothing is written. Eager steps on one process, the TensorFlow backend.

    Raises:
      ValueError: ``steps`` < 1, ``cfg``'s problems (:meth:`TrainConfig.validate`), pairs made
        from images (``image_dir``), several processes or another backend.
    """
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be an integer >= 1; received {steps!r}.")
    cfg.validate()
    if cfg.image_dir or cfg.num_processes > 1:
        raise ValueError("trace reads a TFRecord dataset (--data_dir) on one process; "
                         "--image_dir and several processes are not supported.")
    import keras
    import tensorflow as tf

    from stnh_tf.modeling import losses as losses_lib
    from stnh_tf.training import loop, model_kinds, streams

    if keras.backend.backend() != "tensorflow":
        raise ValueError(f"trace runs on the TensorFlow backend; this is "
                         f"{keras.backend.backend()!r}.")
    keras.mixed_precision.set_global_policy(dtype_policy(cfg.mixed_precision))
    try:
        keras.utils.set_random_seed(cfg.seed)
        model = loop.compile_model(model_kinds.build_model(cfg), cfg)
        if cfg.init_from:
            model_kinds.initialize_from(model, cfg.init_from)
        merges = [layer for layer in model.layers if layer.name.startswith(MERGE_PREFIX)]
        probe = keras.Model(model.inputs, [model.output, [m.input for m in merges]])
        mapper = model_kinds.targets_for(cfg)
        stream = streams.training_stream(cfg, "train", 0)
        stream = stream.map(mapper) if mapper is not None else stream
        loss_fns = {name: keras.losses.get(fn)
                    for name, fn in model_kinds.loss_spec(cfg)[0].items()}
        mace = losses_lib.MeanCornerError()
        records = []
        for step, (x, y, w) in enumerate(stream.take(steps), start=1):
            lr = float(model.optimizer.learning_rate)  # the schedule at this update
            with tf.GradientTape() as tape:
                y_pred, merge_inputs = probe(x, training=True)
                loss = model.compute_loss(x, y, y_pred, w, training=True)
            grads = tape.gradient(loss, model.trainable_variables)
            grad_norm = float(tf.linalg.global_norm(grads))
            model.optimizer.apply(grads, model.trainable_variables)
            terms, maces = {}, {}
            for name, fn in loss_fns.items():
                terms[name] = float(tf.reduce_mean(fn(y[name], y_pred[name])))
                if name.startswith("h_bar"):
                    mace.reset_state()
                    mace.update_state(y[name], y_pred[name])
                    maces[name] = float(mace.result())
            merge_min_w = {m.name: float(np.min(merge_denominators(*inputs)))
                           for m, inputs in zip(merges, merge_inputs)}
            record = {"step": step, "learning_rate": lr, "loss": float(loss), "terms": terms,
                      "grad_norm": grad_norm, "mace": maces, "merge_min_w": merge_min_w}
            records.append(record)
            if printer is not None:
                printer(record)
        return records
    finally:
        keras.mixed_precision.set_global_policy("float32")
