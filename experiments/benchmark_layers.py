r"""Benchmark of the SpatialTransformer: forward and forward+backward vs OpenCV.

Measures the median wall time of
  * STN forward on ``[batch, size, size, 1]`` photograph patches with paper-protocol homographies
    (corners perturbed uniformly in [-32, 32] at size 128, scaled with size), in a ``tf.function``;
  * STN forward + backward (gradient of ``sum(out * w)`` w.r.t. both image and homography);
  * ``cv2.warpPerspective`` (WARP_INVERSE_MAP | INTER_LINEAR) in a Python loop over the batch
    (forward only, the reference the layer reproduces);
with ``jit_compile`` off, on, or both (``--compare_jit``). Prints one JSON object.

  python -m experiments.benchmark_layers --iterations=50 --compare_jit
"""

from __future__ import annotations

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.evaluation import benchmarks

flags.DEFINE_integer("batch_size", 64, "Patches per batch.")
flags.DEFINE_integer("size", 128, "Patch side in pixels.")
flags.DEFINE_integer("iterations", 30, "Timed iterations per measurement (the median is reported).")
flags.DEFINE_integer("warmup", 3, "Untimed iterations before each measurement (tracing, XLA).")
flags_common.define_seed("Seed for patch positions and homographies.")
flags.DEFINE_bool("jit_compile", False, "Compile the tf.functions with XLA.")
flags.DEFINE_bool("compare_jit", False,
                  "Measure both jit_compile=False and True (overrides --jit_compile).")
flags_common.define_json_out()

FLAGS = flags.FLAGS
flags.adopt_module_key_flags(flags_common)  # --help lists them


def main(argv):
    del argv
    jit_modes = (False, True) if FLAGS.compare_jit else (FLAGS.jit_compile,)
    result = benchmarks.stn_benchmark(FLAGS.batch_size, FLAGS.size, FLAGS.iterations,
                                      FLAGS.warmup, FLAGS.seed, jit_modes)
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
