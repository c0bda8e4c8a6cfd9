r"""Train Sequence STN-Homography (paper section 5) end to end with the paper's recipe
(90,000 steps in total unless --train_steps is given, the paper's "total training steps of 90000").

  python -m experiments.train_sequence --num_stages=2 --data_dir=data/coco_mini \
      --model_dir=runs/sequence2 [--init_from=runs/stage1,runs/stage2] [--stage_loss_weights=0.5,1]

Every other flag (schedule, batch, loss weights, checkpoints/resume, logging, NaN guard, strategy)
is shared with ``train_stage`` (:mod:`experiments.flags_common`) and handled by the same
:func:`stnh_tf.training.loop.train`; the two binaries differ only in the model they build. The
dataset is the stage-1 dataset (original patch_a, patch_b, H_bar, patch_a_t). Re-running the same
command resumes from the last checkpoint (``--init_from`` only applies to a fresh start).
"""

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.training import config as train_config

flags_common.define_training_flags(train_config.SEQUENCE)
flags.adopt_module_key_flags(flags_common)  # --help lists the training flags


def main(argv):
    del argv
    with common.user_errors("train_sequence", (ValueError,)):
        cfg = flags_common.config_from_flags(train_config.SEQUENCE, model="sequence")
        cfg.validate()  # every flag's problem in one message, before TensorFlow starts
    flags_common.run_training(cfg, "train_sequence")


if __name__ == "__main__":
    app.run(main)
