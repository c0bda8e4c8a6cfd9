r"""Train one STN-Homography stage (or the HomographyNet baseline) with the paper's recipe.

  python -m experiments.train_stage --stage=1 --data_dir=data/coco_mini --model_dir=runs/stage1
  python -m experiments.train_stage --stage=2 --image_dir=IMAGES --in_memory \
      --prev_stages=runs/stage1 --model_dir=runs/stage2    # no TFRecords, any Keras backend

Defaults are the paper's (SGD momentum 0.9, batch 64, lr 0 -> 0.05 over 1,000 steps then cosine
decay over 90,000); ``--model=homographynet`` defaults to DeTone et al.'s (lr 0.005, divided by 10
after each third of --train_steps). Re-running the same command resumes from the last checkpoint.
"""

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.training import config as train_config
from stnh_tf.training import presets

flags_common.define_training_flags(
    train_config.STAGE,
    choices={"model": [k for k in presets.MODEL_KINDS if k != "sequence"]})
flags.adopt_module_key_flags(flags_common)  # --help lists the training flags


def main(argv):
    del argv
    with common.user_errors("train_stage", (ValueError,)):
        cfg = flags_common.config_from_flags(train_config.STAGE)
        cfg.validate()  # every flag's problem in one message, before TensorFlow starts
    flags_common.run_training(cfg, "train_stage")


if __name__ == "__main__":
    app.run(main)
