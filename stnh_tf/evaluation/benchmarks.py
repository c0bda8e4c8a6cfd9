"""Benchmarks of the model side, library core of the ``experiments.benchmark_*`` binaries (each
binary's docstring says what it measures and how to run it), and the description of the machine
that every benchmark's JSON carries (:func:`stnh_tf.provenance.machine_info`).

* :func:`training_benchmark`: training-step time of STN-Homography beside the bare regression
  network, and batch-1 inference latency (``experiments.benchmark_training``);
* :func:`stn_benchmark`: the SpatialTransformer's forward and forward+backward time against
  ``cv2.warpPerspective`` (``experiments.benchmark_layers``);
* :func:`stream_benchmark`: pair generation alone and inside ``model.fit``
  (``experiments.benchmark_stream``);
* :func:`estimator_benchmark`: ``HomographyEstimator.estimate`` beside the latency benchmark's
  end-to-end hierarchy time (``experiments.benchmark_estimator``).

Each returns the binary's JSON object as a dict. Deep-learning libraries are imported lazily.
"""

from __future__ import annotations

import os
import statistics
import time

# The description of the machine (the NumPy core's), named here too for the benchmarks' callers.
from stnh_tf.provenance import git_commit, machine_info  # noqa: F401


# ------------------------------------------------------------------------------------------------
# Training step and batch-1 inference latency
# ------------------------------------------------------------------------------------------------
def _random_batch(batch_size, seed):
    import numpy as np

    rng = np.random.default_rng(seed)
    x = {"patch_a": rng.uniform(0, 1, (batch_size, 128, 128, 1)).astype("float32"),
         "patch_b": rng.uniform(0, 1, (batch_size, 128, 128, 1)).astype("float32")}
    h_bar = np.tile(np.array([1, 0, 0, 0, 1, 0, 0, 0], "float32"), (batch_size, 1))
    h_bar += rng.normal(0, 0.1, h_bar.shape).astype("float32")
    y = {"h_bar": h_bar, "patch_a_warp": x["patch_a"]}
    return x, y


class _StepTimer:
    def __init__(self):
        import keras

        class Timer(keras.callbacks.Callback):
            def __init__(s):
                super().__init__()
                s.times, s._t = [], None

            def on_train_batch_begin(s, batch, logs=None):
                s._t = time.perf_counter()

            def on_train_batch_end(s, batch, logs=None):
                s.times.append(time.perf_counter() - s._t)

        self.cb = Timer()


def time_training(kind, policy, jit, batch_size, steps, warmup, seed):
    """Median seconds of a training step of ``kind``: "stn", "stn_unlabeled" (the model of a run
    with unlabeled pairs, every pair of the batch unlabeled: h_mask 0), "bare"."""
    import keras
    import tensorflow as tf

    from stnh_tf.training import config as train_config
    from stnh_tf.training import loop as training
    from stnh_tf.training import model_kinds

    keras.mixed_precision.set_global_policy(policy)
    keras.utils.set_random_seed(seed)
    try:
        cfg = train_config.TrainConfig(data_dir="-", model_dir="-", train_steps=10_000,
                                       warmup_steps=100,
                                       label_fraction=0.5 if kind == "stn_unlabeled" else 1.0)
        model = model_kinds.build_model(cfg)
        x, y = _random_batch(batch_size, seed)
        if kind == "bare":
            reg = model.get_layer("regression")
            model = reg
            x = tf.concat([x["patch_a"], x["patch_b"]], axis=-1)
            y = y["h_bar"]
            from stnh_tf.modeling import losses

            model.compile(optimizer=keras.optimizers.SGD(training.learning_rate_schedule(cfg),
                                                         momentum=0.9),
                          loss=losses.h_bar_l2, jit_compile=jit)
            batch = (x, y)
        else:
            training.compile_model(model, cfg)
            model.jit_compile = jit
            h_mask = tf.fill([batch_size], 0.0 if kind == "stn_unlabeled" else 1.0)
            batch = (x, y, {"h_bar": h_mask, "patch_a_warp": tf.ones_like(h_mask)})  # data.batches
            mapper = model_kinds.targets_for(cfg)  # the run's (with unlabeled pairs: patch_b's)
            batch = mapper(*batch) if mapper is not None else batch
        ds = tf.data.Dataset.from_tensors(batch).repeat()
        timer = _StepTimer().cb
        model.fit(ds, steps_per_epoch=warmup + steps, epochs=1, verbose=0, callbacks=[timer])
        return statistics.median(timer.times[warmup:])
    finally:
        keras.mixed_precision.set_global_policy("float32")


def time_latency(runs, seed):
    """Median ms of one batch-1 forward pass of the full model (float32, inference mode)."""
    import keras
    import numpy as np
    import tensorflow as tf

    from stnh_tf.modeling import models

    keras.utils.set_random_seed(seed)
    model = models.build_stn_homography()
    x, _ = _random_batch(1, seed)
    fn = tf.function(lambda a, b: model({"patch_a": a, "patch_b": b}, training=False)["h_bar"])
    a, b = tf.constant(x["patch_a"]), tf.constant(x["patch_b"])
    for _ in range(20):
        fn(a, b).numpy()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn(a, b).numpy()
        times.append(time.perf_counter() - t0)
    return {"median_ms": 1e3 * statistics.median(times),
            "p90_ms": 1e3 * float(np.percentile(times, 90)),
            "runs": runs}


SETTINGS_PREFIXES = ("TF_ENABLE_ONEDNN", "TF_ONEDNN_", "TF_SET_ONEDNN", "TF_MKL_", "TF_NUM_",
                     "TF_CPP_", "TF_XLA_", "ONEDNN_", "DNNL_", "OMP_", "KMP_")
"""Environment variables :func:`training_benchmark` records (TensorFlow's, oneDNN's, OpenMP's
settings; not every ``TF_``, which other tools use for their own, tokens included)."""


def training_benchmark(batch_size=64, steps=20, warmup=3, policies=("float32", "mixed_bfloat16"),
                       jit=False, latency_runs=200, seed=0, unlabeled=False) -> dict:
    """Training-step seconds of the full model (``stn``; with ``unlabeled`` also with every pair
    unlabeled, and the ratio) and the bare regression network with the L2 loss (``bare``) per
    policy (and ``jit_compile`` when ``jit``), then batch-1 latency."""
    import tensorflow as tf  # noqa: F401  (loaded first, so machine_info reports it)

    result = {"benchmark": "training_step", "batch_size": batch_size, "steps": steps,
              "seed": seed,
              "machine": machine_info(),
              # the variables TensorFlow, oneDNN and OpenMP read: the run's settings
              "environment": {k: v for k, v in sorted(os.environ.items())
                              if k.startswith(SETTINGS_PREFIXES)},
              "train_step_s": {}}
    for policy in policies:
        for jit_compile in ([False, True] if jit else [False]):
            key = policy + ("_jit" if jit_compile else "")
            args = (policy, jit_compile, batch_size, steps, warmup, seed)
            stn, bare = time_training("stn", *args), time_training("bare", *args)
            entry = result["train_step_s"][key] = {
                "stn_homography": stn, "bare_regression": bare,
                "stn_and_losses_share": (stn - bare) / stn,
                "samples_per_s": batch_size / stn}
            if unlabeled:
                u = entry["stn_homography_unlabeled"] = time_training("stn_unlabeled", *args)
                entry["unlabeled_over_labeled"] = u / stn
    result["inference_batch1"] = time_latency(latency_runs, seed)
    result["machine"]["load_average_at_end"] = os.getloadavg()
    return result


# ------------------------------------------------------------------------------------------------
# The SpatialTransformer against OpenCV
# ------------------------------------------------------------------------------------------------
def stn_inputs(batch_size: int, size: int, seed: int):
    """Grayscale photograph patches ``[B, S, S, 1]`` (float32, 0..255) and ``H_bar`` ``[B, 8]``."""
    import cv2
    import numpy as np
    import skimage.data

    from stnh_tf import geometry

    rng = np.random.default_rng(seed)
    photos = [skimage.data.camera(), skimage.data.astronaut(), skimage.data.coffee(),
              skimage.data.chelsea(), skimage.data.rocket()]
    photos = [cv2.resize(p if p.ndim == 2 else cv2.cvtColor(p, cv2.COLOR_RGB2GRAY), (320, 240))
              for p in photos]
    patches, h_bars, h_pix = [], [], []
    rho = 32.0 * size / 128.0
    for i in range(batch_size):
        photo = photos[i % len(photos)]
        y0 = rng.integers(0, photo.shape[0] - size + 1)
        x0 = rng.integers(0, photo.shape[1] - size + 1)
        patches.append(photo[y0:y0 + size, x0:x0 + size])
        h = geometry.offsets_to_homography(rng.uniform(-rho, rho, size=(4, 2)), size)
        h_pix.append(h)
        h_bars.append(geometry.matrix_to_vector(geometry.normalize_homography(h, size, size)))
    images = np.stack(patches).astype(np.float32)[..., None]
    return images, np.stack(h_bars).astype(np.float32), np.stack(h_pix)


def stn_benchmark(batch_size=64, size=128, iterations=30, warmup=3, seed=0, jit_modes=(False,)):
    """Runs every measurement of ``experiments.benchmark_layers`` and returns the result dict."""
    import cv2
    import numpy as np
    import tensorflow as tf

    from stnh_tf.evaluation.mace import median_ms
    from stnh_tf.modeling.layers import SpatialTransformer

    images_np, h_np, h_pix = stn_inputs(batch_size, size, seed)
    images, h_bar = tf.constant(images_np), tf.constant(h_np)
    weights = tf.constant(np.random.default_rng(seed + 1).normal(
        size=images_np.shape).astype(np.float32))
    layer = SpatialTransformer()

    result = {
        "benchmark": "stn_layers",
        "batch_size": batch_size, "size": size, "channels": 1,
        "iterations": iterations, "warmup": warmup, "seed": seed,
        "machine": machine_info(),
        "stn": {},
    }

    for jit in jit_modes:
        @tf.function(jit_compile=jit)
        def forward(img, h):
            return layer([img, h])

        @tf.function(jit_compile=jit)
        def forward_backward(img, h):
            with tf.GradientTape() as tape:
                tape.watch([img, h])
                loss = tf.reduce_sum(layer([img, h]) * weights)
            return tape.gradient(loss, [img, h])

        key = "jit" if jit else "no_jit"
        result["stn"][key] = {
            "forward_ms": median_ms(lambda: forward(images, h_bar).numpy(), iterations, warmup),
            "forward_backward_ms": median_ms(
                lambda: [g.numpy() for g in forward_backward(images, h_bar)], iterations, warmup),
        }
        # Sanity: the timed function computes the OpenCV warp (mean |diff| on this batch).
        out = forward(images, h_bar).numpy()
        ref = np.stack([cv2.warpPerspective(images_np[i, ..., 0], h_pix[i], (size, size),
                                            flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
                        for i in range(batch_size)])
        result["stn"][key]["mean_abs_diff_vs_cv2_all_pixels"] = float(
            np.abs(out[..., 0] - ref).mean())

    def cv2_loop():
        for i in range(batch_size):
            cv2.warpPerspective(images_np[i, ..., 0], h_pix[i], (size, size),
                                flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)

    result["cv2_loop_forward_ms"] = median_ms(cv2_loop, iterations, warmup)
    if "jit" in result["stn"] and "no_jit" in result["stn"]:
        nj, j = result["stn"]["no_jit"], result["stn"]["jit"]
        result["jit_speedup"] = {
            "forward": nj["forward_ms"] / j["forward_ms"],
            "forward_backward": nj["forward_backward_ms"] / j["forward_backward_ms"],
        }
    return result


# ------------------------------------------------------------------------------------------------
# Pair generation alone and inside model.fit
# ------------------------------------------------------------------------------------------------
def _fit_inputs(mode, pair_batches, image_dir, batch_size, workers, samples_per_image, seed,
                photometric, max_images=0):
    from stnh_tf.data import batches, pair_datasets

    common_args = dict(samples_per_image=samples_per_image, seed=seed, photometric=photometric,
                       max_images=max_images)
    if mode == "array":
        return pair_datasets.ArrayStream(batches.materialize(pair_batches, workers), pair_batches)
    return pair_datasets.PairStream(image_dir, batch_size, fresh_pairs=mode == "fresh",
                                    workers=workers, **common_args)


def time_fit(mode, pair_batches, image_dir, batch_size=64, workers=2, samples_per_image=100,
             steps_per_epoch=50, epochs=3, mixed_precision=True, seed=0, photometric=False,
             steps_per_execution=1, training_callbacks=False, stream=None,
             max_images=0) -> dict:
    """Steps per second of ``model.fit`` fed by ``mode`` (``array``, ``stream`` or ``fresh``;
    or by ``stream`` where given) over ``epochs`` epochs after an untimed one, and the median and
    longest step, at ``steps_per_execution``; ``training_callbacks`` adds the per-step callbacks
    of :func:`stnh_tf.training.loop.train` (non-finite guard, progress), which read the loss
    after every call. ``max_images``: the first N photographs of ``image_dir`` only (0: all)."""
    import keras

    from stnh_tf.training import config as train_config
    from stnh_tf.training import loop as training
    from stnh_tf.training import model_kinds
    from stnh_tf.training.callbacks import NonFiniteGuard, ProgressLogger

    class Ends(keras.callbacks.Callback):
        def __init__(self):
            super().__init__()
            self.times = []

        def on_train_batch_end(self, batch, logs=None):
            self.times.append(time.perf_counter())

    n, k = steps_per_epoch, steps_per_execution
    if n % k:
        raise ValueError(f"steps_per_execution ({k}) must divide steps_per_epoch ({n}).")
    cfg = train_config.TrainConfig(image_dir=",".join(image_dir), model_dir="-", seed=seed,
                                   batch_size=batch_size, mixed_precision=mixed_precision,
                                   steps_per_execution=k)
    keras.mixed_precision.set_global_policy(train_config.dtype_policy(mixed_precision))
    keras.utils.set_random_seed(seed)
    t0 = time.perf_counter()
    owned = stream is None
    if owned:
        stream = _fit_inputs(mode, pair_batches, image_dir, batch_size, workers,
                             samples_per_image, seed, photometric, max_images)
    ready_s = time.perf_counter() - t0
    model = training.compile_model(model_kinds.build_model(cfg), cfg)
    ends = Ends()
    callbacks = [NonFiniteGuard(), ProgressLogger(n, n * (epochs + 1), lambda line: None)] \
        if training_callbacks else []
    try:
        model.fit(stream, epochs=epochs + 1, steps_per_epoch=n, callbacks=[*callbacks, ends],
                  verbose=0)
    finally:
        if owned and hasattr(stream, "close"):
            stream.close()
        keras.mixed_precision.set_global_policy("float32")
    timed = ends.times[n // k - 1:]  # from the end of the untimed epoch; one end per k steps
    gaps = [(b - a) / k for a, b in zip(timed, timed[1:])]
    return {"steps_per_s": len(gaps) / (sum(gaps) or 1e-9),
            "step_ms_median": 1e3 * statistics.median(gaps), "step_ms_max": 1e3 * max(gaps),
            "input_ready_s": ready_s}


def fit_variants(spes=(1,), callback_sets=("none",)) -> list:
    """``(key suffix, steps_per_execution, training_callbacks)`` for every combination; the
    plain combination (1, ``none``) has the empty suffix (the mode's own key)."""
    out = []
    for k in spes:
        for cbs in callback_sets:
            if cbs not in ("none", "training"):
                raise ValueError(f"callbacks must be none or training; received {cbs!r}.")
            suffix = "" if (k, cbs) == (1, "none") else \
                f"/spe{k}" + ("+callbacks" if cbs == "training" else "")
            out.append((suffix, int(k), cbs == "training"))
    return out


def stream_benchmark(image_dir, workers=2, samples_per_image=100, batch_size=64,
                     alone_batches=100, modes=("array", "stream", "fresh"), steps_per_epoch=50,
                     epochs=3, mixed_precision=True, seed=0, photometric=False,
                     steps_per_execution=(1,), callbacks=("none",), max_images=0) -> dict:
    """Runs every measurement of ``experiments.benchmark_stream`` (``image_dir``: a list of
    folders, of which the first ``max_images`` photographs, 0: all) on the current Keras backend
    and returns the result dict; each mode is timed at every ``steps_per_execution`` with each of
    ``callbacks`` (``none``, ``training``: :func:`fit_variants`)."""
    import keras

    from stnh_tf.data import batches, pair_datasets
    from stnh_tf.evaluation.mace import median_ms

    __import__({"tensorflow": "tensorflow", "jax": "jax"}.get(keras.backend.backend(), "keras"))
    pair_batches = batches.PairBatches(image_dir, batch_size, samples_per_image=samples_per_image,
                                       seed=seed, photometric=photometric, max_images=max_images)
    result = {"benchmark": "stream", "image_dir": image_dir, "photometric": photometric,
              "images": len(pair_batches.entries), "max_images": max_images,
              "workers": workers, "samples_per_image": samples_per_image,
              "batch_size": batch_size, "seed": seed, "backend": keras.backend.backend(),
              "mixed_precision": mixed_precision, "machine": machine_info()}
    result["in_process_ms"] = median_ms(lambda: pair_batches.step_batch(1, fresh=True), 10, 1)
    stream = pair_datasets.PairStream(image_dir, batch_size, workers=workers,
                                      samples_per_image=samples_per_image, seed=seed,
                                      fresh_pairs=True, photometric=photometric,
                                      max_images=max_images)
    try:
        stream[0]
        t0 = time.perf_counter()
        for i in range(1, alone_batches + 1):
            stream[i]
        result["alone_batches_per_s"] = alone_batches / (time.perf_counter() - t0)
    finally:
        stream.close()
    variants = fit_variants(steps_per_execution, callbacks)
    arrays = batches.materialize(pair_batches, workers) if "array" in modes else None
    result["fit"] = {}
    for mode in modes:
        for suffix, k, cbs in variants:
            given = pair_datasets.ArrayStream(arrays, pair_batches) if mode == "array" else None
            result["fit"][mode + suffix] = time_fit(
                mode, pair_batches, image_dir, batch_size, workers, samples_per_image,
                steps_per_epoch, epochs, mixed_precision, seed, photometric,
                steps_per_execution=k, training_callbacks=cbs, stream=given,
                max_images=max_images)
    return result


def estimator_benchmark(model=None, compute_dtype="float32", runs=30, warmup=5, large_batch=256,
                        seed=0, options=None):
    """``estimate`` at batch 1 and ``large_batch`` on seeded random uint8 patches, beside
    :func:`stnh_tf.evaluation.mace.latency`'s ``d_e`` for the same models; ``compute_dtype``
    ``"float32"`` or ``"as_saved"``; ``options``: ``estimate``'s
    (:class:`~stnh_tf.inference.options.EstimateOptions`; ``None``: the default with
    ``search="none"``, the network: random patches do not align, so the search would search every
    pair, its worst case)."""
    import numpy as np

    from stnh_tf.inference.options import EstimateOptions

    from stnh_tf.inference import estimator as inference
    from stnh_tf.inference import model_files
    from stnh_tf.evaluation import mace as evaluation
    from stnh_tf.modeling import runner

    dtype = None if compute_dtype == "as_saved" else "float32"
    estimator = inference.HomographyEstimator.load(model, compute_dtype=dtype)
    rng = np.random.default_rng(seed)
    n = large_batch
    a, b = (rng.integers(0, 256, (n, 128, 128), dtype=np.uint8) for _ in range(2))
    options = EstimateOptions(search="none") if options is None else options
    one = evaluation.median_ms(lambda: estimator.estimate(a[0], b[0], options), runs, warmup)
    many = evaluation.median_ms(lambda: estimator.estimate(a, b, options, batch_size=n),
                                max(runs // 10, 3), 1)
    stages = model_files.resolve_model_paths(model)
    bench = evaluation.latency(stages, max_stages=len(stages), runs=runs, warmup=warmup,
                               sequence=False, seed=seed, compute_dtype=dtype)
    d_e = bench["hierarchy"][str(len(stages))]["d_e_ms"]
    return {"benchmark": "estimator_vs_latency", "model": estimator.source,
            "stages": len(stages), "policy": runner.compute_policy(estimator.stages[0]),
            "runs": runs, "seed": seed, "tta": options.tta, "search": options.search,
            "estimate_batch1_ms": one, "benchmark_d_e_ms": d_e, "ratio": one / d_e,
            f"estimate_batch{n}_ms_per_pair": many / n,
            "benchmark_l_m_ms": bench["l_m_ms"], "machine": machine_info()}
