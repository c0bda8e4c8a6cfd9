r"""Evaluate models, hierarchies and classical baselines on stored test pairs (MACE in pixels).

  python -m experiments.evaluate --model_dir=runs/stage1 --data_dir=data/coco_mini --split=test
  python -m experiments.evaluate --model_dir=runs/stage1,runs/stage2,runs/stage3 --data_dir=...
  python -m experiments.evaluate --baselines=identity,orb_ransac,sift_ransac --data_dir=...

One model directory: its final estimate (every stage's for a sequence model). Several: a
hierarchy, reported after 1, 2, ..., n stages; --no_clip reports it without the clipping of
predicted corners onto the context border (post-processing that is not the paper's). Prints a
short table (:func:`stnh_tf.evaluation.summaries.evaluation_table`): the identity, the model
(after each stage), the baselines, each with its MACE, median and the pairs it estimates worse
than the identity, and "worse than the identity" where its mean is above the identity's; a note
under it (``notes`` in the JSON) where a model was trained as another stage (its run's
``config.json``) than the pairs are for (the dataset's ``metadata.json``), e.g. a stage-1 model
on stage-2 data, and where the split was made from the same photograph folders as another split
of the dataset (or one inside the other), so that its photographs are not unseen.
--json_out=FILE writes the full JSON (mean/median/p90/p99 MACE, the identity on the same pairs,
the number of pairs, ``worse_than_identity``); --json_out=- prints it instead of the table.
Uncertainty: ``mace_se`` over the pairs, and by photograph (the pairs' ``image_id``) a percentile
bootstrap that resamples whole photographs, their pairs together: ``mace_se_by_photograph`` and
``mace_ci95_by_photograph`` (2,000 resamples, seed 0:
:func:`stnh_tf.evaluation.uncertainty.by_photograph`), the model's in a line under the table.
"""

from absl import app, flags

from experiments import common
from stnh_tf.evaluation import baselines as baselines_lib
from stnh_tf.evaluation import summaries

flags.DEFINE_list("model_dir", [], "Model directory, or several (comma-separated) for a hierarchy.")
flags.DEFINE_string("data_dir", None, "Dataset directory (data_prep output).", required=True)
flags.DEFINE_string("split", "test", "Split to evaluate.")
flags.DEFINE_list("baselines", [],
                  f"Classical baselines: {', '.join(baselines_lib.BASELINES)}.")
flags.DEFINE_integer("max_samples", None, "Evaluate only the first N pairs.")
flags.DEFINE_integer("batch_size", 64, "Inference batch size.")
flags.DEFINE_enum("compute_dtype", None, ["float32"],
                  "Rebuild mixed-precision models to compute in this dtype (as "
                  "HomographyEstimator.load does by default); default: as saved.")
flags.DEFINE_bool("no_clip", False, "Hierarchy only: keep estimates whose corners leave the "
                  "stored context as predicted, instead of clipping them onto its border (the "
                  "degenerate-prediction rule's post-processing, which uses the knowledge that "
                  "true corners move at most 32 px).")
flags.DEFINE_string("json_out", None, summaries.JSON_OUT_HELP)
FLAGS = flags.FLAGS


def main(argv):
    del argv
    from stnh_tf.evaluation import mace as evaluation
    from stnh_tf.provenance import machine_info

    if not FLAGS.model_dir and not FLAGS.baselines:
        raise SystemExit("evaluate: give --model_dir and/or --baselines.")
    with common.user_errors("evaluate"):
        common.check_flags_apart(("json_out",), ("model_dir", "data_dir"))
        summaries.check_json_out(FLAGS.json_out)  # before: the result must not be lost at the end
        result = evaluation.evaluate(FLAGS.model_dir, FLAGS.data_dir, FLAGS.split, FLAGS.baselines,
                                     FLAGS.max_samples, FLAGS.batch_size,
                                     FLAGS.compute_dtype, clip_to_context=not FLAGS.no_clip)
    result["machine"] = machine_info()  # the commit, the machine and the library versions
    summaries.emit(result, summaries.evaluation_table(result), FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
