r"""Training throughput and batch-1 inference latency of STN-Homography (one stage).

  python -m experiments.benchmark_training --steps=20 --json_out=/tmp/bench_training.json

Measures, on fixed in-memory batches (so input reading is not timed; the data benchmark measures
that separately), the median time of a ``model.fit`` training step at ``--batch_size`` for

* ``stn``: the full model (regression network + SpatialTransformer + L2 and L1 losses),
* ``bare``: the regression network alone with the L2 loss on ``H_bar``,

in float32 and in Keras mixed bfloat16 (optionally also with ``jit_compile``), and reports the
share of the step spent in the STN and the losses, ``(stn - bare) / stn``. Then the batch-1
inference latency of the full model (median over ``--latency_runs`` calls of a compiled
``tf.function`` after warm-up). Prints one JSON object.
"""

from __future__ import annotations

import statistics
import time

from absl import app, flags

from experiments import common
from stnh_tf import train_config

flags.DEFINE_integer("batch_size", 64, "Training batch size.")
flags.DEFINE_integer("steps", 20, "Timed training steps per configuration (median reported).")
flags.DEFINE_integer("warmup", 3, "Untimed steps first.")
flags.DEFINE_list("policies", ["float32", "mixed_bfloat16"], "Keras dtype policies to measure.")
flags.DEFINE_bool("jit", False, "Also measure jit_compile=True.")
flags.DEFINE_integer("latency_runs", 200, "Batch-1 inference calls timed.")
flags.DEFINE_integer("seed", 0, "Seed of the batches and weights.")
flags.DEFINE_string("json_out", None, "Also write the JSON here.")
FLAGS = flags.FLAGS


def _batch(batch_size, seed):
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
    """Median seconds per training step of ``kind`` ("stn" or "bare")."""
    import keras
    import tensorflow as tf

    from stnh_tf import model_kinds, training

    keras.mixed_precision.set_global_policy(policy)
    keras.utils.set_random_seed(seed)
    try:
        cfg = train_config.TrainConfig(data_dir="-", model_dir="-", train_steps=10_000, warmup_steps=100)
        model = model_kinds.build_model(cfg)
        x, y = _batch(batch_size, seed)
        if kind == "bare":
            reg = model.get_layer("regression")
            model = reg
            x = tf.concat([x["patch_a"], x["patch_b"]], axis=-1)
            y = y["h_bar"]
            from stnh_tf import losses

            model.compile(optimizer=keras.optimizers.SGD(training.learning_rate_schedule(cfg), momentum=0.9),
                          loss=losses.h_bar_l2, jit_compile=jit)
        else:
            training.compile_model(model, cfg)
            model.jit_compile = jit
        ds = tf.data.Dataset.from_tensors((x, y)).repeat()
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

    from stnh_tf import models

    keras.utils.set_random_seed(seed)
    model = models.build_stn_homography()
    x, _ = _batch(1, seed)
    fn = tf.function(lambda a, b: model({"patch_a": a, "patch_b": b}, training=False)["h_bar"])
    a, b = tf.constant(x["patch_a"]), tf.constant(x["patch_b"])
    for _ in range(20):
        fn(a, b).numpy()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn(a, b).numpy()
        times.append(time.perf_counter() - t0)
    return {"median_ms": 1e3 * statistics.median(times), "p90_ms": 1e3 * float(np.percentile(times, 90)),
            "runs": runs}


def main(argv):
    del argv
    import os

    import tensorflow as tf  # noqa: F401  (loaded first, so machine_info reports it)

    result = {"benchmark": "training_step", "batch_size": FLAGS.batch_size, "steps": FLAGS.steps,
              "seed": FLAGS.seed,
              "machine": common.machine_info(),
              "train_step_s": {}}
    for policy in FLAGS.policies:
        for jit in ([False, True] if FLAGS.jit else [False]):
            key = policy + ("_jit" if jit else "")
            stn = time_training("stn", policy, jit, FLAGS.batch_size, FLAGS.steps, FLAGS.warmup, FLAGS.seed)
            bare = time_training("bare", policy, jit, FLAGS.batch_size, FLAGS.steps, FLAGS.warmup, FLAGS.seed)
            result["train_step_s"][key] = {
                "stn_homography": stn, "bare_regression": bare,
                "stn_and_losses_share": (stn - bare) / stn,
                "samples_per_s": FLAGS.batch_size / stn}
    result["inference_batch1"] = time_latency(FLAGS.latency_runs, FLAGS.seed)
    result["machine"]["load_average_at_end"] = os.getloadavg()
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
