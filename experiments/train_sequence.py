r"""Train Sequence STN-Homography (paper section 5) end to end with the paper's recipe
(90,000 steps in total unless --train_steps is given, the paper's "total training steps of 90000").

  python -m experiments.train_sequence --num_stages=2 --data_dir=data/coco_mini \
      --model_dir=runs/sequence2 [--init_from=runs/stage1,runs/stage2] [--stage_loss_weights=0.5,1]

Every other flag (schedule, batch, loss weights, checkpoints/resume, logging, NaN guard, strategy)
is shared with ``train_stage`` (:mod:`experiments.flags_common`) and handled by the same
:func:`stnh_tf.training.train`; the two binaries differ only in the model they build. The dataset
is the stage-1 dataset (original patch_a, patch_b, H_bar, patch_a_t). Re-running the same command
resumes from the last checkpoint (``--init_from`` only applies to a fresh start).
"""

import math
import os

from absl import app, flags

from experiments import flags_common
from stnh_tf import training

flags_common.define_training_flags()
flags.DEFINE_integer("num_stages", training.TrainConfig.num_stages, "Number of sequence stages.")
flags.DEFINE_list("init_from", [],
                  "Comma list of single-stage model dirs (each holding model.keras); dir k "
                  "initialises stage k's regression network (at most num_stages dirs).")
flags.DEFINE_list("stage_loss_weights", [],
                  "Comma list of num_stages floats multiplying each stage's L2 and L1 losses "
                  "(default: all 1).")
FLAGS = flags.FLAGS


def sequence_overrides(num_stages, init_from, stage_loss_weights):
    """Validate the sequence flags; return the ``config_from_flags`` overrides.

    Raises ``ValueError`` naming the bad value.
    """
    if num_stages < 1:
        raise ValueError(f"--num_stages must be >= 1; received {num_stages}.")
    try:
        weights = tuple(float(w) for w in stage_loss_weights)
    except ValueError:
        raise ValueError(
            f"--stage_loss_weights must be floats; received {stage_loss_weights}.") from None
    if weights and len(weights) != num_stages:
        raise ValueError(f"--stage_loss_weights needs {num_stages} values (one per stage); "
                         f"received {list(weights)}.")
    if any(not math.isfinite(w) or w < 0 for w in weights):
        raise ValueError(f"--stage_loss_weights must be finite and >= 0; received {list(weights)}.")
    dirs = tuple(init_from)
    if len(dirs) > num_stages:
        raise ValueError(f"--init_from names {len(dirs)} dirs for {num_stages} stages.")
    for d in dirs:
        if not os.path.isfile(os.path.join(d, training.FINAL_MODEL)):
            raise ValueError(f"--init_from: {d} holds no {training.FINAL_MODEL} (a finished "
                             "single-stage run).")
    return dict(model="sequence", stage=1, num_stages=num_stages, init_from=dirs,
                stage_loss_weights=weights)


def main(argv):
    del argv
    try:
        overrides = sequence_overrides(FLAGS.num_stages, FLAGS.init_from, FLAGS.stage_loss_weights)
    except ValueError as e:
        raise SystemExit(f"train_sequence: {e}") from None
    flags_common.run_training(flags_common.config_from_flags(**overrides), "train_sequence")


if __name__ == "__main__":
    app.run(main)
