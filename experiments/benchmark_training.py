r"""Training throughput and batch-1 inference latency of STN-Homography (one stage).

  python -m experiments.benchmark_training --steps=20 --json_out=/tmp/bench_training.json

Measures, on fixed in-memory batches (so input reading is not timed; the data benchmark measures
that separately), the median time of a ``model.fit`` training step at ``--batch_size`` for

* ``stn``: the full model (regression network + SpatialTransformer + L2 and L1 losses),
* ``bare``: the regression network alone with the L2 loss on ``H_bar``,

in float32 and in Keras mixed bfloat16 (optionally also with ``jit_compile``), and reports the
share of the step spent in the STN and the losses, ``(stn - bare) / stn``; with ``--unlabeled``
also the step of a run with unlabeled pairs (its model has the output of their L1 term against
patch_b: training with missing labels, docs/training.md) on the same batch with every pair
unlabeled (``h_mask`` 0) and its ratio to the labeled step. Then
the batch-1 inference latency of the full model (median over ``--latency_runs`` calls of a
compiled ``tf.function`` after warm-up). With ``--onednn_layers``, also oneDNN's own time of
each primitive of the ``stn`` step (every convolution's three passes, with the kernel it runs)
per policy (:mod:`stnh_tf.evaluation.onednn_profile`). Prints one JSON object.

  python -m experiments.benchmark_training --policies=mixed_bfloat16 --steps=6 --warmup=2 --latency_runs=5 --onednn_layers
"""

from __future__ import annotations

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.evaluation import benchmarks, onednn_profile

flags.DEFINE_integer("batch_size", 64, "Training batch size.")
flags.DEFINE_integer("steps", 20, "Timed training steps per configuration (median reported).")
flags.DEFINE_integer("warmup", 3, "Untimed steps first.")
flags.DEFINE_list("policies", ["float32", "mixed_bfloat16"], "Keras dtype policies to measure.")
flags.DEFINE_bool("jit", False, "Also measure jit_compile=True.")
flags.DEFINE_integer("latency_runs", 200, "Batch-1 inference calls timed.")
flags_common.define_seed("Seed of the batches and weights.")
flags.DEFINE_bool("unlabeled", False, "Also time the step of a run with unlabeled pairs, every "
                  "pair unlabeled (h_mask 0: the L1 term against patch_b alone), against the "
                  "labeled one.")
flags.DEFINE_bool("onednn_layers", False, "Also profile the stage's step per oneDNN primitive "
                  "(each convolution's forward, backward-data and backward-weights pass, with "
                  "its kernel) for each policy, from ONEDNN_VERBOSE in a child process "
                  "(stnh_tf.evaluation.onednn_profile; issue 77, item 5).")
flags_common.define_json_out()
FLAGS = flags.FLAGS
flags.adopt_module_key_flags(flags_common)  # --help lists them


def main(argv):
    del argv
    result = benchmarks.training_benchmark(FLAGS.batch_size, FLAGS.steps, FLAGS.warmup,
                                           FLAGS.policies, FLAGS.jit, FLAGS.latency_runs,
                                           FLAGS.seed, FLAGS.unlabeled)
    if FLAGS.onednn_layers:
        result["onednn_layers"] = {
            policy: onednn_profile.profile_training_step(policy, FLAGS.batch_size, FLAGS.steps,
                                                         FLAGS.warmup, FLAGS.seed)
            for policy in FLAGS.policies}
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
