r"""Train one STN-Homography stage (or the HomographyNet baseline) with the paper's recipe.

  python -m experiments.train_stage --stage=1 --data_dir=data/coco_mini --model_dir=runs/stage1
  python -m experiments.train_stage --stage=2 --image_dir=IMAGES --in_memory \
      --prev_stages=runs/stage1 --model_dir=runs/stage2    # no TFRecords, any Keras backend

Defaults are the paper's (SGD momentum 0.9, batch 64, lr 0 -> 0.05 over 1,000 steps then cosine
decay over 90,000); ``--model=homographynet`` defaults to DeTone et al.'s (lr 0.005, divided by 10
after each third of --train_steps). Re-running the same command resumes from the last checkpoint.
"""

from absl import app, flags

from experiments import flags_common

flags_common.define_training_flags()
flags.DEFINE_integer("stage", 1, "Hierarchical stage; the dataset's metadata must say the same.")
flags.DEFINE_enum("model", "stn", ["stn", "homographynet", "homographynet_gap"],
                  "Model kind: stn (the paper's stage), homographynet (DeTone et al.'s network; "
                  "unless given: --batch_norm=conv, their recipe --lr_schedule=step "
                  "--learning_rate=0.005 --warmup_steps=0 --train_steps=90000) or "
                  "homographynet_gap (its 4-point "
                  "regression on this project's backbone, the paper's recipe).")
FLAGS = flags.FLAGS


def main(argv):
    del argv
    flags_common.run_training(flags_common.config_from_flags(stage=FLAGS.stage, model=FLAGS.model),
                              "train_stage")


if __name__ == "__main__":
    app.run(main)
