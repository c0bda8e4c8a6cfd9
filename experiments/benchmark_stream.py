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
  ``step_ms_median`` is the median wall time between consecutive batch ends (per step). Each
  mode is timed at every ``--steps_per_execution`` with every ``--callbacks`` set (keys
  ``array/spe50+callbacks``: 50 steps a call, with the training loop's per-step callbacks).

Prints one JSON object.
"""

from __future__ import annotations

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.evaluation import benchmarks

flags.DEFINE_list("image_dir", None, "Folders of training images (comma-separated).",
                  required=True)
flags.DEFINE_bool("photometric", False, "Photometric change of patch_b in the generated pairs.")
flags.DEFINE_integer("workers", 2, "Generator processes.", lower_bound=1)
flags.DEFINE_integer("samples_per_image", 100, "Pairs per image in one data epoch.",
                     lower_bound=1)
flags.DEFINE_integer("batch_size", 64, "Batch size.", lower_bound=1)
flags.DEFINE_integer("alone_batches", 100, "Items read from the stream alone.", lower_bound=1)
flags.DEFINE_list("modes", ["array", "stream", "fresh"], "Inputs to time inside model.fit.")
flags.DEFINE_integer("steps_per_epoch", 50, "Keras epoch length (training checkpoints each epoch).",
                     lower_bound=1)
flags.DEFINE_integer("epochs", 3, "Timed Keras epochs (after one untimed).", lower_bound=1)
flags.DEFINE_bool("mixed_precision", True, "Keras mixed_bfloat16 policy.")
flags_common.define_seed("Pair and weight seed.")
flags.DEFINE_list("steps_per_execution", ["1"], "Keras steps_per_execution values to time each "
                  "mode at (each must divide --steps_per_epoch).")
flags.DEFINE_list("callbacks", ["none"], "Callbacks to time each mode with: none, training (the "
                  "training loop's per-step non-finite guard and progress logger).")
flags_common.define_max_images()
flags_common.define_json_out()
FLAGS = flags.FLAGS
flags.adopt_module_key_flags(flags_common)  # --help lists them


def main(argv):
    del argv
    with common.user_errors("benchmark_stream"):  # (SourceError: a ValueError, one line)
        common.check_flags_apart(("json_out",), ("image_dir",))
        result = benchmarks.stream_benchmark(
            FLAGS.image_dir, FLAGS.workers, FLAGS.samples_per_image, FLAGS.batch_size,
            FLAGS.alone_batches, FLAGS.modes, FLAGS.steps_per_epoch, FLAGS.epochs,
            FLAGS.mixed_precision, FLAGS.seed, FLAGS.photometric,
            steps_per_execution=[int(k) for k in FLAGS.steps_per_execution],
            callbacks=FLAGS.callbacks, max_images=FLAGS.max_images)
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
