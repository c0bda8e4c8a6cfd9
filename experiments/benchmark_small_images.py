r"""The error of ``estimate_images`` on images shrunk to a few pixels on one side: the measurement
behind ``stnh_tf.inference.image_input.check_image_size`` (images narrower than 20 px or lower
than 15 px are refused). Library code: ``stnh_tf.evaluation.small_images``.

  python -m experiments.benchmark_small_images --json_out=docs/small_images.json

Prints one JSON object: per size, the median and largest corner error (px at 320 x 240) of the
network alone (``EstimateOptions.network_only()``) and of ``estimate_images``' default
(``EstimateOptions.photographs()``), and whether the size is refused.
"""

from __future__ import annotations

from absl import app, flags

from experiments import common, flags_common

flags.DEFINE_string("model", None, "Model or hierarchy (default: the shipped weights).")
flags.DEFINE_integer("pairs", 8, "Photograph pairs per size.", lower_bound=1)
flags_common.define_seed("Seed of the pairs' warps.")
flags_common.define_json_out()
FLAGS = flags.FLAGS
flags.adopt_module_key_flags(flags_common)  # --help lists them

SIZES = [(320, 240), (320, 32), (320, 24), (320, 16), (320, 14), (320, 8), (320, 4), (320, 2),
         (320, 1), (32, 240), (20, 240), (16, 240), (8, 240), (4, 240), (1, 240)]


def main(argv):
    del argv
    with common.user_errors("benchmark_small_images"):
        common.check_flags_apart(("json_out",), (), models=("model",))
    import tensorflow as tf  # noqa: F401  (loaded first, so machine_info reports it)

    from stnh_tf.evaluation import benchmarks, small_images
    from stnh_tf.inference.estimator import HomographyEstimator
    from stnh_tf.inference.options import EstimateOptions

    estimator = HomographyEstimator.load(FLAGS.model)
    result = small_images.small_image_errors(
        estimator, SIZES, {"network_only": EstimateOptions.network_only(),
                           "photographs": EstimateOptions.photographs()},
        pairs=FLAGS.pairs, seed=FLAGS.seed)
    result.update(model=FLAGS.model or "shipped default", machine=benchmarks.machine_info(),
                  command="python -m experiments.benchmark_small_images "
                          f"--pairs={FLAGS.pairs} --seed={FLAGS.seed}")
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
