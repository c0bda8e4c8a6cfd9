r"""Training from a folder of images: generator throughput alone and inside ``model.fit``.

  python -m experiments.benchmark_stream --image_dir=IMAGES --workers=2
  KERAS_BACKEND=jax python3 -m experiments.benchmark_stream --image_dir=IMAGES --workers=14

Times, on any Keras backend:

* ``in_process_ms``: one batch generated in this process (``PairBatches.step_batch``);
* ``alone``: items per second read in order from ``PairStream(workers=W)`` (its own worker pool,
  after the first item);
* ``fit``: steps per second of ``model.fit`` on the full STN-Homography model (the paper's
  losses, ``--mixed_precision``) fed by ``array`` (the pairs generated once, in memory:
  ``--in_memory``), ``stream`` (``PairStream`` workers, the fixed pairs) and ``fresh`` (workers,
  new pairs every data epoch: ``--fresh_pairs``), over ``--epochs`` Keras epochs of
  ``--steps_per_epoch`` steps after one untimed epoch (compilation), epoch boundaries included.
  ``step_ms_median`` is the median wall time between consecutive batch ends.

Prints one JSON object.
"""

from __future__ import annotations

import statistics
import time

from absl import app, flags

from experiments import common
from stnh_tf import batches, pair_datasets, train_config

flags.DEFINE_list("image_dir", None, "Folders of training images (comma-separated).",
                  required=True)
flags.DEFINE_bool("photometric", False, "Photometric change of patch_b in the generated pairs.")
flags.DEFINE_integer("workers", 2, "Generator processes.")
flags.DEFINE_integer("samples_per_image", 100, "Pairs per image in one data epoch.")
flags.DEFINE_integer("batch_size", 64, "Batch size.")
flags.DEFINE_integer("alone_batches", 100, "Items read from the stream alone.")
flags.DEFINE_list("modes", ["array", "stream", "fresh"], "Inputs to time inside model.fit.")
flags.DEFINE_integer("steps_per_epoch", 50, "Keras epoch length (training checkpoints each epoch).")
flags.DEFINE_integer("epochs", 3, "Timed Keras epochs (after one untimed).")
flags.DEFINE_bool("mixed_precision", True, "Keras mixed_bfloat16 policy.")
flags.DEFINE_integer("seed", 0, "Pair and weight seed.")
flags.DEFINE_string("json_out", None, "Also write the JSON here.")
FLAGS = flags.FLAGS


def _inputs(mode, pair_batches):
    from stnh_tf import batches, pair_datasets

    common_args = dict(samples_per_image=FLAGS.samples_per_image, seed=FLAGS.seed,
                       photometric=FLAGS.photometric)
    if mode == "array":
        return pair_datasets.ArrayStream(batches.materialize(pair_batches, FLAGS.workers),
                                         pair_batches)
    return pair_datasets.PairStream(FLAGS.image_dir, FLAGS.batch_size,
                                    fresh_pairs=mode == "fresh", workers=FLAGS.workers,
                                    **common_args)


def time_fit(mode, pair_batches):
    import keras

    from stnh_tf import model_kinds, training

    class Ends(keras.callbacks.Callback):
        def __init__(self):
            super().__init__()
            self.times = []

        def on_train_batch_end(self, batch, logs=None):
            self.times.append(time.perf_counter())

    cfg = train_config.TrainConfig(image_dir=",".join(FLAGS.image_dir), model_dir="-", seed=FLAGS.seed,
                                   batch_size=FLAGS.batch_size, mixed_precision=FLAGS.mixed_precision)
    keras.mixed_precision.set_global_policy("mixed_bfloat16" if FLAGS.mixed_precision else "float32")
    keras.utils.set_random_seed(FLAGS.seed)
    t0 = time.perf_counter()
    stream = _inputs(mode, pair_batches)
    ready_s = time.perf_counter() - t0
    model = training.compile_model(model_kinds.build_model(cfg), cfg)
    ends = Ends()
    n = FLAGS.steps_per_epoch
    try:
        model.fit(stream, epochs=FLAGS.epochs + 1, steps_per_epoch=n, callbacks=[ends], verbose=0)
    finally:
        if hasattr(stream, "close"):
            stream.close()
        keras.mixed_precision.set_global_policy("float32")
    timed = ends.times[n - 1:]  # from the end of the untimed epoch
    gaps = [b - a for a, b in zip(timed, timed[1:])]
    return {"steps_per_s": len(gaps) / (timed[-1] - timed[0]),
            "step_ms_median": 1e3 * statistics.median(gaps), "step_ms_max": 1e3 * max(gaps),
            "input_ready_s": ready_s}


def main(argv):
    del argv
    import keras


    __import__({"tensorflow": "tensorflow", "jax": "jax"}.get(keras.backend.backend(), "keras"))
    pair_batches = batches.PairBatches(FLAGS.image_dir, FLAGS.batch_size,
                                       samples_per_image=FLAGS.samples_per_image, seed=FLAGS.seed,
                               photometric=FLAGS.photometric)
    result = {"benchmark": "stream", "image_dir": FLAGS.image_dir, "photometric": FLAGS.photometric,
              "images": len(pair_batches.entries),
              "workers": FLAGS.workers, "samples_per_image": FLAGS.samples_per_image,
              "batch_size": FLAGS.batch_size, "seed": FLAGS.seed,
              "mixed_precision": FLAGS.mixed_precision, "machine": common.machine_info()}
    result["in_process_ms"] = common.median_ms(
        lambda: pair_batches.step_batch(1, fresh=True), 10, 1)
    stream = pair_datasets.PairStream(FLAGS.image_dir, FLAGS.batch_size, workers=FLAGS.workers,
                             samples_per_image=FLAGS.samples_per_image, seed=FLAGS.seed,
                             fresh_pairs=True, photometric=FLAGS.photometric)
    try:
        stream[0]
        t0 = time.perf_counter()
        for i in range(1, FLAGS.alone_batches + 1):
            stream[i]
        result["alone_batches_per_s"] = FLAGS.alone_batches / (time.perf_counter() - t0)
    finally:
        stream.close()
    result["fit"] = {mode: time_fit(mode, pair_batches) for mode in FLAGS.modes}
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
