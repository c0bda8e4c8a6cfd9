"""One way to run a trained model: load it, find its final ``H_bar`` output, and call it through a
compiled forward pass that returns pixel homographies.

Every path that runs a model goes through here:
:class:`stnh_tf.inference.estimator.HomographyEstimator`, evaluation, stage-data generation
(``stnh_tf.data.stage_k``), in-memory stage pairs (:func:`stnh_tf.training.streams.stage_pairs`),
export verification and the latency benchmark.

Convention: inputs are float ``[B, S, S, 1]`` patches in [0, 1] (``S = 128``); the pixel
homography returned is ``H_ba`` in the patch frame (patch_b -> patch_a, :mod:`stnh_tf.geometry`),
float64 ``[B, 3, 3]``.

    >>> model = load_model("runs/stage1", compute_dtype="float32")        # doctest: +SKIP
    >>> predict = predictor(model)                                         # doctest: +SKIP
    >>> predict(patch_a, patch_b).shape                                    # doctest: +SKIP
    (B, 3, 3)
"""

from __future__ import annotations

import os
import zipfile

import numpy as np

from stnh_tf import geometry


COMPUTE_DTYPES = ("float32", "bfloat16", "float16")
"""The precisions :func:`load_model` can rebuild a mixed-precision model to compute in."""


def load_model(model_dir_or_file, compute_dtype=None):
    """Load a trained Keras model from a model directory (its ``model.keras``) or a file: a thin
    wrapper of ``keras.models.load_model(path, compile=False)`` (which opens the same files after
    ``import stnh_tf``), with the errors below and the choice of precision.

    ``compute_dtype="float32"`` rebuilds a model saved with a mixed-precision policy (e.g.
    ``mixed_bfloat16``, as the CPU-budget models were trained) so every layer computes in
    float32, with the same weights (mixed-precision variables are float32 already); default: as
    saved.

    Raises:
      FileNotFoundError: no such file.
      ValueError: a ``.keras`` file that is not a Keras model archive, or a ``compute_dtype``
        other than None and :data:`COMPUTE_DTYPES`.
    """
    if compute_dtype is not None and compute_dtype not in COMPUTE_DTYPES:
        raise ValueError(f"compute_dtype must be None (as saved) or one of {COMPUTE_DTYPES}; "
                         f"received {compute_dtype!r}.")
    import keras  # (its import registers this package's layers: stnh_tf/__init__.py)

    path = model_dir_or_file
    if os.path.isdir(path):
        path = os.path.join(path, "model.keras")
    if not os.path.exists(path):
        raise FileNotFoundError(f"no trained model at {model_dir_or_file} (looked for {path}).")
    if str(path).endswith(".keras") and not zipfile.is_zipfile(path):
        # Keras itself calls such a file "File not found".
        raise ValueError(f"{path} exists but is not a Keras model (a .keras file is a zip archive "
                         "written by model.save).")
    model = keras.models.load_model(path, compile=False)
    return with_compute_dtype(model, compute_dtype) if compute_dtype else model


def _dtype_policies(config):
    """Every ``DTypePolicy`` config dict inside a layer or model config."""
    if isinstance(config, dict):
        if config.get("class_name") == "DTypePolicy":
            yield config
        for value in config.values():
            yield from _dtype_policies(value)
    elif isinstance(config, list):
        for value in config:
            yield from _dtype_policies(value)


def compute_policy(model) -> str:
    """The dtype policy ``model`` computes in: the mixed policy of its layers (nested ones
    included) if they have one (e.g. ``"mixed_bfloat16"`` for a model trained in mixed precision,
    whose few float32 layers aside), else ``"float32"``."""
    names = {p.get("config", {}).get("name") for p in _dtype_policies(model.get_config())}
    mixed = sorted(n for n in names if str(n).startswith("mixed_"))
    return mixed[0] if mixed else "float32"


def with_compute_dtype(model, dtype: str):
    """``model`` with every mixed-precision layer's policy replaced by ``dtype`` (same weights);
    ``model`` itself if no layer has a mixed policy."""
    def rewrite(obj):
        if isinstance(obj, dict):
            if (obj.get("class_name") == "DTypePolicy"
                    and str(obj.get("config", {}).get("name", "")).startswith("mixed_")):
                return {**obj, "config": {**obj["config"], "name": dtype}}
            return {k: rewrite(v) for k, v in obj.items()}
        if isinstance(obj, list):
            return [rewrite(v) for v in obj]
        return obj

    config = model.get_config()
    new_config = rewrite(config)
    if new_config == config:
        return model
    rebuilt = model.__class__.from_config(new_config)
    rebuilt.set_weights(model.get_weights())
    return rebuilt


def h_bar_names(model) -> list:
    """The ``h_bar`` outputs of ``model`` in stage order: ``["h_bar"]`` or ``["h_bar_1", ...]``."""
    names = list(model.output_names) if hasattr(model, "output_names") else []
    seq = sorted((n for n in names if n.startswith("h_bar_")), key=lambda n: int(n.split("_")[-1]))
    return seq or ["h_bar"]


def final_h_bar_name(model) -> str:
    """The output holding a model's final ``H_bar``: ``h_bar`` or the last ``h_bar_k``."""
    return h_bar_names(model)[-1]


def compiled_forward(model, output=None):
    """A compiled forward pass ``(patch_a, patch_b) -> H_bar`` (NumPy in and out) for batches of
    any size, built once.

    Under the TensorFlow backend a ``tf.function`` whose input signature leaves the batch
    dimension unknown (a new batch size does not retrace); under JAX a ``jax.jit`` of
    ``model.stateless_call`` (one trace per batch size); otherwise ``predict_on_batch``.

    Args:
      model: a Keras model with inputs ``patch_a`` and ``patch_b`` ``[B, S, S, 1]``.
      output: the name of an ``h_bar`` output (default: the final one, :func:`final_h_bar_name`),
        or ``"all"``: a dict of every ``h_bar*`` output.
    Returns:
      ``f(patch_a, patch_b)``: float32 ``[B, 8]`` normalized ``H_bar`` (a dict of them for
      ``"all"``).
    """
    import keras

    names = h_bar_names(model) if output == "all" else [output or final_h_bar_name(model)]

    def pick(out):
        return {n: out[n] for n in names} if output == "all" else out[names[0]]

    def to_numpy(out):
        return ({k: np.asarray(v) for k, v in out.items()} if output == "all"
                else np.asarray(out))

    if keras.backend.backend() == "tensorflow":
        import tensorflow as tf

        size = model.inputs[0].shape[1]
        spec = tf.TensorSpec([None, size, size, 1], tf.float32)

        @tf.function(input_signature=[spec, spec])
        def fn(a, b):
            return pick(model({"patch_a": a, "patch_b": b}, training=False))

        return lambda a, b: to_numpy(fn(np.asarray(a, np.float32), np.asarray(b, np.float32)))
    if keras.backend.backend() == "jax":
        import jax

        @jax.jit
        def jfn(trainable, non_trainable, a, b):
            out, _ = model.stateless_call(trainable, non_trainable, {"patch_a": a, "patch_b": b},
                                          training=False)
            return pick(out)

        def run(a, b):  # reads the variables at call time, so later weight changes are seen
            return to_numpy(jfn([v.value for v in model.trainable_variables],
                                [v.value for v in model.non_trainable_variables],
                                np.asarray(a, np.float32), np.asarray(b, np.float32)))
        return run
    return lambda a, b: to_numpy(pick(model.predict_on_batch(
        {"patch_a": np.asarray(a, np.float32), "patch_b": np.asarray(b, np.float32)})))


def batched(forward, batch_size: int = 64):
    """``forward`` (:func:`compiled_forward`) applied in chunks of ``batch_size`` pairs, the
    results concatenated (per key for ``output="all"``)."""
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1; received {batch_size}.")

    def run(patch_a, patch_b):
        chunks = [forward(patch_a[i:i + batch_size], patch_b[i:i + batch_size])
                  for i in range(0, len(patch_a), batch_size)]
        if isinstance(chunks[0], dict):
            return {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}
        return np.concatenate(chunks)

    return run


def predictor(model, batch_size: int = 64, output=None):
    """``predict(patch_a, patch_b, batch_size=batch_size) -> H_ba``: the model's pixel
    homography, float64 ``[B, 3, 3]`` (``[2, 2] = 1``), for float ``[B, S, S, 1]`` patches in
    [0, 1], run in chunks of ``batch_size`` through one :func:`compiled_forward` (``output`` as
    there, one name), built once. It is a :data:`stnh_tf.hierarchy.PredictFn`."""
    forward = compiled_forward(model, output)
    size = model.inputs[0].shape[1]

    def predict(patch_a, patch_b, batch_size: int = batch_size):
        return geometry.h_bar_to_pixel(batched(forward, batch_size)(patch_a, patch_b), size)

    return predict
