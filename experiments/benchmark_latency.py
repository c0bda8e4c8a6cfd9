r"""The paper's Table 2: batch-1 latency of 1, 2 and 3 hierarchical stages (and sequence models).

  python -m experiments.benchmark_latency --runs=200 --json_out=/tmp/latency.json
  python -m experiments.benchmark_latency --model_dir=runs/s1,runs/s2,runs/s3

For a hierarchy of n stages, the end-to-end time ``d_e(n)`` of one pair (context_a and patch_b in,
composed pixel ``H_ba`` out: :func:`stnh_tf.hierarchy.run_hierarchy`, the OpenCV warp of the
context between stages included), and separately the two terms of the paper's formula
``d_e = (l_m + l_w) * n``:

* ``l_m``: one stage's model forward pass (compiled, batch 1, inference mode);
* ``l_w``: the work between stages (OpenCV warp and crop of the context, scaling, composition and
  the degenerate-prediction check).

With ``--sequence``, also the forward pass of sequence models with 1-3 stages. Latency does not
depend on the weights, so without ``--model_dir`` untrained models are built (under
``--policy``). Medians over ``--runs`` calls after ``--warmup``. Prints one JSON object.
"""

from __future__ import annotations

import os

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.evaluation import benchmarks

flags.DEFINE_list("model_dir", [], "Stage model directories (default: untrained models).")
flags.DEFINE_integer("max_stages", 3, "Measure 1..max_stages stages.")
flags.DEFINE_integer("runs", 200, "Timed calls per measurement (median reported).")
flags.DEFINE_integer("warmup", 20, "Untimed calls first.")
flags.DEFINE_enum("policy", "float32", ["float32", "mixed_bfloat16"], "Dtype policy of built "
                  "models (loaded models keep theirs; the JSON's policy says what ran).")
flags.DEFINE_bool("sequence", True, "Also time sequence models with 1..max_stages stages.")
flags_common.define_seed("Seed of the inputs and weights.")
flags_common.define_json_out()
FLAGS = flags.FLAGS


def measure(*args, **kwargs):
    """:func:`stnh_tf.evaluation.mace.latency` (the library core, also used by the reproduce
    driver)."""
    from stnh_tf.evaluation import mace as evaluation

    return evaluation.latency(*args, **kwargs)
flags.adopt_module_key_flags(flags_common)  # --help lists them


def main(argv):
    del argv
    with common.user_errors("benchmark_latency"):
        common.check_flags_apart(("json_out",), ("model_dir",))
    import keras

    if keras.backend.backend() == "tensorflow":
        import tensorflow as tf  # noqa: F401  (loaded first, so machine_info reports it)
    elif keras.backend.backend() == "jax":
        import jax  # noqa: F401

    result = {"benchmark": "latency_batch1", "policy": FLAGS.policy, "runs": FLAGS.runs,
              "seed": FLAGS.seed, "model_dirs": FLAGS.model_dir or "untrained",
              "paper_gpu_ms": {"1": 4.87, "2": 11.46, "3": 17.85},
              "machine": benchmarks.machine_info()}
    result.update(measure(FLAGS.model_dir, FLAGS.max_stages, FLAGS.runs, FLAGS.warmup, FLAGS.policy,
                          FLAGS.sequence, FLAGS.seed))
    result["machine"]["load_average_at_end"] = os.getloadavg()
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
