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

import json
import os

from absl import app, flags

from experiments import common

flags.DEFINE_list("model_dir", [], "Stage model directories (default: untrained models).")
flags.DEFINE_integer("max_stages", 3, "Measure 1..max_stages stages.")
flags.DEFINE_integer("runs", 200, "Timed calls per measurement (median reported).")
flags.DEFINE_integer("warmup", 20, "Untimed calls first.")
flags.DEFINE_enum("policy", "float32", ["float32", "mixed_bfloat16"], "Dtype policy of built models.")
flags.DEFINE_bool("sequence", True, "Also time sequence models with 1..max_stages stages.")
flags.DEFINE_integer("seed", 0, "Seed of the inputs and weights.")
flags.DEFINE_string("json_out", None, "Also write the JSON here.")
FLAGS = flags.FLAGS


def measure(model_dirs=(), max_stages=3, runs=200, warmup=20, policy="float32", sequence=True, seed=0):
    import keras
    import numpy as np

    from stnh_tf import evaluation, hierarchy, models

    rng = np.random.default_rng(seed)
    context = rng.integers(0, 256, (1, 192, 192), dtype=np.uint8)
    patch_b = rng.integers(0, 256, (1, 128, 128), dtype=np.uint8)
    keras.mixed_precision.set_global_policy(policy)
    keras.utils.set_random_seed(seed)
    try:
        if model_dirs:
            stage_models = [evaluation.load_model(d) for d in model_dirs]
        else:
            stage_models = [models.build_stn_homography() for _ in range(max_stages)]
        stages = [hierarchy.keras_stage(m) for m in stage_models]
        forward = evaluation.compiled_forward(stage_models[0])
        a = context[:, 32:160, 32:160, None].astype(np.float32) / 255.0
        b = patch_b[..., None].astype(np.float32) / 255.0
        l_m = common.median_ms(lambda: forward(a, b), runs, warmup)
        h_prev = np.eye(3)[None] + 0.01
        h_stage = np.eye(3)[None]

        def between_stages():
            patch = hierarchy.crop_warped_context(context[0], h_prev[0])
            patch = patch[None, ..., None] / 255.0
            hierarchy.accept_or_reject(h_prev, h_stage)
            return patch

        l_w = common.median_ms(between_stages, runs, warmup)
        result = {"l_m_ms": l_m, "l_w_ms": l_w, "l_w_over_l_m": l_w / l_m, "hierarchy": {}}
        for n in range(1, len(stages) + 1):
            d_e = common.median_ms(lambda: hierarchy.run_hierarchy(stages[:n], context, patch_b), runs, warmup)
            result["hierarchy"][str(n)] = {"d_e_ms": d_e, "formula_ms": n * (l_m + l_w),
                                           "ratio_to_one_stage": None}
        one = result["hierarchy"]["1"]["d_e_ms"]
        for v in result["hierarchy"].values():
            v["ratio_to_one_stage"] = v["d_e_ms"] / one
        if sequence:
            result["sequence"] = {}
            for n in range(1, max_stages + 1):
                seq_fwd = evaluation.compiled_forward(models.build_sequence_stn_homography(n))
                result["sequence"][str(n)] = {"forward_ms": common.median_ms(lambda: seq_fwd(a, b), runs, warmup)}
        return result
    finally:
        keras.mixed_precision.set_global_policy("float32")


def main(argv):
    del argv
    import tensorflow as tf  # noqa: F401  (loaded first, so machine_info reports it)

    result = {"benchmark": "latency_batch1", "policy": FLAGS.policy, "runs": FLAGS.runs,
              "seed": FLAGS.seed, "model_dirs": FLAGS.model_dir or "untrained",
              "paper_gpu_ms": {"1": 4.87, "2": 11.46, "3": 17.85},
              "machine": common.machine_info()}
    result.update(measure(FLAGS.model_dir, FLAGS.max_stages, FLAGS.runs, FLAGS.warmup, FLAGS.policy,
                          FLAGS.sequence, FLAGS.seed))
    result["machine"]["load_average_at_end"] = os.getloadavg()
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
