r"""The first steps of a training run, one JSON line each: loss terms, global gradient norm
(before any clip), each stage's MACE and the sequence model's merge denominators.

  python -m experiments.trace_early_steps --model_dir=D --data_dir=DATA --num_stages=2 \
      --train_steps=180 --warmup_steps=45 --checkpoint_every=90 --mixed_precision --steps=12 \
      [--clipnorm=10]

Takes ``train_sequence``'s model and schedule flags (one model, fresh weights, the same stream,
optimizer, schedule and losses) and traces ``--steps`` of its updates
(:func:`stnh_tf.training.early_steps.trace`); writes ``MODEL_DIR/early_steps.json`` (a
non-finite number as the string ``"nan"`` or ``"inf"``) and nothing else. Used for issue 78's
hour budget, whose sequence model diverged in its first steps (docs/reproduce.md).
"""

import json
import math
import os

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.paths import check_apart
from stnh_tf.training import config as train_config

flags_common.define_training_flags(train_config.SEQUENCE, run_flags=False)
flags.adopt_module_key_flags(flags_common)
flags.DEFINE_integer("steps", 10, "Updates to trace.", lower_bound=1)
FLAGS = flags.FLAGS


def _strict(value):
    """``value`` with every non-finite float as its string (strict JSON has no NaN)."""
    if isinstance(value, dict):
        return {k: _strict(v) for k, v in value.items()}
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


def main(argv):
    del argv
    from stnh_tf.paths import atomic_write_json

    with common.user_errors("trace_early_steps", (ValueError, OSError)):
        cfg = flags_common.config_from_flags(train_config.SEQUENCE, model="sequence")
        check_apart({"--model_dir": cfg.model_dir}, flags_common.training_inputs(cfg))
        from stnh_tf.training import early_steps

        records = [_strict(r) for r in early_steps.trace(
            cfg, FLAGS.steps, printer=lambda r: print(json.dumps(_strict(r)), flush=True))]
        os.makedirs(cfg.model_dir, exist_ok=True)
        atomic_write_json(os.path.join(cfg.model_dir, "early_steps.json"),
                          {"config": cfg.to_json(), "steps": records}, sort_keys=False)


if __name__ == "__main__":
    app.run(main)
