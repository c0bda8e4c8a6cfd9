r"""Train one STN-Homography stage (or the HomographyNet baseline) with the paper's recipe.

  python -m experiments.train_stage --stage=1 --data_dir=data/coco_mini --model_dir=runs/stage1
  python -m experiments.train_stage --stage=2 --image_dir=IMAGES --in_memory \
      --prev_stages=runs/stage1 --model_dir=runs/stage2    # no TFRecords, any Keras backend

Defaults are the paper's (SGD momentum 0.9, batch 64, lr 0 -> 0.05 over 1,000 steps then cosine
decay over 90,000). Re-running the same command resumes from the last checkpoint.
"""

from absl import app, flags

from experiments import flags_common

flags_common.define_training_flags()
flags.DEFINE_integer("stage", 1, "Hierarchical stage; the dataset's metadata must say the same.")
flags.DEFINE_enum("model", "stn", ["stn", "homographynet"], "Model kind.")
FLAGS = flags.FLAGS


def main(argv):
    del argv
    flags_common.run_training(flags_common.config_from_flags(stage=FLAGS.stage, model=FLAGS.model),
                              "train_stage")


if __name__ == "__main__":
    app.run(main)
