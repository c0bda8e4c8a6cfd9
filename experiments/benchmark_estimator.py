r"""The estimator against the latency benchmark: ``HomographyEstimator.estimate`` (batch 1 and a
large batch) beside :func:`stnh_tf.evaluation.mace.latency`'s end-to-end hierarchy time ``d_e`` for
the same models in the same precision.

  python -m experiments.benchmark_estimator --runs=30 --json_out=/tmp/estimator.json
  python -m experiments.benchmark_estimator --compute_dtype=as_saved   # bfloat16 as shipped

Both run the shipped default (or ``--model``) on random uint8 patches (seeded): the estimator's
later stages warp the patch itself, the benchmark's warp a 192 x 192 context; both do one OpenCV
warp per pair between stages. Medians over ``--runs`` calls after ``--warmup``. Prints one JSON
object.
"""

from __future__ import annotations

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.evaluation import benchmarks
from stnh_tf.inference.options import EstimateOptions

flags.DEFINE_string("model", None, "Model or hierarchy (default: the shipped weights).")
flags.DEFINE_enum("compute_dtype", "float32", ["float32", "as_saved"],
                  "float32 (the estimator's default) or the policy the models were saved with.")
flags.DEFINE_integer("runs", 30, "Timed calls per measurement (median reported).")
flags.DEFINE_integer("warmup", 5, "Untimed calls first.")
flags.DEFINE_integer("large_batch", 256, "Pairs per call of the large-batch measurement.")
flags_common.define_seed("Seed of the inputs.")
# search=none by default: random patches do not align, so the search would take every pair.
DEFAULTS = EstimateOptions(search="none")
flags_common.define_estimate_flags(("tta", "search"), DEFAULTS)
flags_common.define_json_out()
FLAGS = flags.FLAGS
flags.adopt_module_key_flags(flags_common)  # --help lists them


def main(argv):
    del argv
    with common.user_errors("benchmark_estimator"):
        common.check_flags_apart(("json_out",), (), models=("model",))
    import tensorflow as tf  # noqa: F401  (loaded first, so machine_info reports it)

    result = benchmarks.estimator_benchmark(FLAGS.model, FLAGS.compute_dtype, FLAGS.runs,
                                            FLAGS.warmup, FLAGS.large_batch, FLAGS.seed,
                                            flags_common.options_from_flags(DEFAULTS))
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
