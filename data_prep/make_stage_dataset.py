r"""Generate the stage-k dataset of hierarchical STN-Homography from stage k-1's data and model.

  python -m data_prep.make_stage_dataset --stage=2 --input_dir=data/cpu --model_dir=runs/stage1 \
      --output_dir=data/cpu_stage2                      # train, val (if any) and test
  python -m data_prep.make_stage_dataset --stage=3 --input_dir=data/cpu_stage2 \
      --model_dir=runs/stage2 --output_dir=data/cpu_stage3

Runs the stage-(k-1) model on every stored pair, composes its prediction with the earlier
estimate (degenerate predictions are replaced by the identity and counted), re-crops patch_a from
the stored context with OpenCV, and stores the residual target, the new patch_a_t, the original
H_ba and the composed estimate (stnh_tf/data/stage_k.py). Same sharding, atomic writes, metadata and
progress as data_prep.make_dataset.
"""

from __future__ import annotations

import os

from absl import app, flags, logging

from experiments import common
from stnh_tf.data import stage_k

flags.DEFINE_integer("stage", None, "Stage k >= 2 of the dataset to build.", required=True)
flags.DEFINE_string("input_dir", None, "Stage-(k-1) dataset directory.", required=True)
flags.DEFINE_string("model_dir", None, "Trained stage-(k-1) model directory.", required=True)
flags.DEFINE_string("output_dir", None, "Stage-k dataset directory (created).", required=True)
flags.DEFINE_list("splits", None, "Splits to build (default: train and test, and val where "
                  "--input_dir holds it).")
flags.DEFINE_integer("num_shards", 0, "Shards per split; 0 = as many as the input split has.")
flags.DEFINE_integer("num_workers", os.cpu_count() or 1, "Re-cropping processes.")
flags.DEFINE_bool("overwrite", False, "Regenerate splits that are already complete (without it, "
                  "those made from the same data and model are kept and the others made).")
FLAGS = flags.FLAGS


def check_model_stage(model_dir, stage: int) -> None:
    """Stage-``stage`` data is made with the stage-(``stage``-1) model: refuse a ``model_dir``
    whose run configuration or stage record says another stage
    (:func:`stnh_tf.training.run_records.trained_stage`); where none says it (a ``.keras`` file
    alone), log that the stage could not be checked.

    Raises:
      ValueError: naming the model, its stage, the file that says so and the stage needed.
    """
    from stnh_tf.training import run_records

    found = run_records.trained_stage(model_dir)
    if found is None and os.path.exists(model_dir):
        logging.warning("%s records no stage (no run config.json or stage record beside it): "
                        "taken to be the stage-%d model.", model_dir, stage - 1)
    elif found is not None and found[0] != stage - 1:
        raise ValueError(f"--model_dir {model_dir} is a stage-{found[0]} model ({found[1]}); "
                         f"stage-{stage} data is made with the stage-{stage - 1} model (trained "
                         f"on stage-{stage - 1} data).")


def main(argv):
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments: {argv[1:]}")
    with common.user_errors("make_stage_dataset"):  # every split's flags, before the model loads
        splits = (stage_k.default_splits(FLAGS.input_dir) if FLAGS.splits is None
                  else FLAGS.splits)
        stage_k.check_stage_arguments(FLAGS.stage, FLAGS.input_dir, FLAGS.output_dir, splits,
                                      num_shards=FLAGS.num_shards, model_dir=FLAGS.model_dir)
        common.check_flags_apart(("output_dir",), ("input_dir", "model_dir"))
        common.check_not_a_run(FLAGS.output_dir)
        check_model_stage(FLAGS.model_dir, FLAGS.stage)
        writing = list(splits)
        if not FLAGS.overwrite:  # (a run cut short: the same command makes the rest)
            done = stage_k.check_one_source(FLAGS.output_dir, splits,
                                            stage_k.made_from(FLAGS.input_dir, FLAGS.model_dir))
            for split in done:
                logging.info("%s: complete in %s, made from the same data and model: kept "
                             "(--overwrite makes it again)", split, FLAGS.output_dir)
            splits = [s for s in splits if s not in done]
    for split in splits:
        with common.user_errors("make_stage_dataset"):
            result = stage_k.make_stage_dataset(
                FLAGS.stage, FLAGS.input_dir, FLAGS.output_dir, split, model_dir=FLAGS.model_dir,
                num_shards=FLAGS.num_shards, num_workers=FLAGS.num_workers, log=logging.info,
                overwrite=FLAGS.overwrite, writing=writing)
        logging.info("%s: %d samples; degenerate predictions %s", split, result["num_samples"],
                     result["degenerate_predictions"])


if __name__ == "__main__":
    app.run(main)
