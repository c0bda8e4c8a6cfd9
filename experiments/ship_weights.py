r"""Copy trained stage models into the package as its shipped weights, with a model card.

  python -m experiments.ship_weights --model_dir=runs/cpu/stage1,runs/cpu/stage2 \
      --eval_json=runs/cpu/eval_hierarchy.json

Writes ``stnh_tf/weights/stage{k}.keras`` (weights and architecture only, no optimizer state), the
manifest ``default.json`` naming them in order (the default of ``HomographyEstimator.load()``),
and ``model_card.json`` with each stage's training configuration, its final step, the given
evaluation results, the bundled check (MACE on seeded bundled pairs, which
``tests/test_shipped_weights.py`` re-computes) and, under ``machine``, the commit, machine and
library versions of the run that wrote the card (:func:`stnh_tf.provenance.machine_info`).

  python -m experiments.ship_weights --replace_stage=2 --model_dir=runs/cpu/stage2_more \
      --init_from_previous --eval_json=runs/cpu/eval_hierarchy.json

replaces one stage of the weights already shipped (same file name, the other stages' files and
card entries kept; with ``--init_from_previous`` the replaced stage's entry is kept as the new
entry's ``init_from_run``) and re-computes the bundled check; without ``--eval_json`` the card's
evaluation is kept marked ``evaluation_stale``.

Every model and ``--eval_json`` is read and the new files written and checked in a staging folder
inside ``--weights_dir`` before anything shipped is replaced; files, manifest and card then go in
together, or nothing does. Weights whose bundled check is worse than the card they replace says
are refused unless ``--allow_worse``; the printed JSON's ``bundled_check_change`` lists the
numbers that moved (old, new). One command writes in a weights folder at a time (a second,
whichever of these, is refused while the first holds the folder's lock); what a command killed
in its swap left is put back by the next, unless its card was written (then it stands).

  python -m experiments.ship_weights --refresh_check

re-computes only the bundled check of the weights already shipped (after a change to how
``HomographyEstimator`` computes, e.g. its default ``compute_dtype``), leaving the rest of the card.

  python -m experiments.ship_weights --refresh_evaluation \
      --test_image_dir=../shared/data/coco_mini/test [--weights_dir=stnh_tf/weights/paper_recipe]

re-measures every evaluation the card holds on the shipped files, on the test pairs made from
the photographs (:mod:`stnh_tf.evaluation.card_evaluation`), each with the commit and machine of
this run; with ``--refresh_check`` both.
"""

from __future__ import annotations

import json

from absl import app, flags

from experiments import common
from stnh_tf.inference import shipped_weights

flags.DEFINE_list("model_dir", None, "Trained stage model directories, in stage order.")
flags.DEFINE_string("eval_json", None, "experiments.evaluate output to record in the card.")
flags.DEFINE_string("weights_dir", None, "Destination (default: the package's stnh_tf/weights).")
flags.DEFINE_integer("replace_stage", None, "Replace only this stage (1-based) of the weights "
                     "already shipped by the single run in --model_dir.")
flags.DEFINE_bool("init_from_previous", False, "With --replace_stage: the run was initialised "
                  "from the stage it replaces; keep that stage's card entry as init_from_run.")
flags.DEFINE_bool("refresh_check", False, "Only re-compute the bundled check of the shipped "
                  "weights in --weights_dir (no --model_dir).")
flags.DEFINE_bool("refresh_evaluation", False, "Only re-measure the card's evaluation of the "
                  "shipped weights in --weights_dir on pairs made from --test_image_dir.")
flags.DEFINE_string("test_image_dir", None, "--refresh_evaluation: the test photographs the "
                    "card was measured on (the coco_mini test photographs).")
flags.DEFINE_bool("allow_worse", False, "Ship weights whose bundled check is worse than the "
                  "card they replace says (refused without it, nothing replaced).")
FLAGS = flags.FLAGS


def main(argv):
    del argv
    from stnh_tf.inference import model_files

    if not FLAGS.weights_dir:  # (so that the package's folder is checked apart from the inputs)
        FLAGS.weights_dir = model_files.default_weights_dir()
    with common.user_errors("ship_weights"):
        common.check_flags_apart(("weights_dir",), ("model_dir", "eval_json"))
    if FLAGS.refresh_evaluation != bool(FLAGS.test_image_dir):
        raise app.UsageError("--refresh_evaluation and --test_image_dir go together.")
    if FLAGS.refresh_check or FLAGS.refresh_evaluation:
        if FLAGS.model_dir or FLAGS.eval_json or FLAGS.replace_stage is not None:
            raise app.UsageError("--refresh_check and --refresh_evaluation take neither "
                                 "--model_dir, --eval_json nor --replace_stage.")
        out = {}
        if FLAGS.refresh_evaluation:
            from stnh_tf.evaluation import card_evaluation

            with common.user_errors("ship_weights"):
                card = card_evaluation.refresh_card(FLAGS.weights_dir, FLAGS.test_image_dir)
            out["evaluation"] = sorted(card["evaluation"])
        if FLAGS.refresh_check:
            with common.user_errors("ship_weights"):
                out["bundled_check"] = shipped_weights.refresh_check(FLAGS.weights_dir)[
                    "bundled_check"]
        print(json.dumps(out))
        return
    if not FLAGS.model_dir:
        raise app.UsageError("--model_dir is required (or --refresh_check).")
    if FLAGS.replace_stage is not None:
        if len(FLAGS.model_dir) != 1:
            raise app.UsageError("--replace_stage takes exactly one --model_dir.")
        with common.user_errors("ship_weights"):
            card = shipped_weights.replace_stage(FLAGS.replace_stage, FLAGS.model_dir[0],
                                                 FLAGS.weights_dir, FLAGS.eval_json,
                                                 FLAGS.init_from_previous, FLAGS.allow_worse)
        print(json.dumps({"replaced": card["stages"][FLAGS.replace_stage - 1]["file"],
                          "bundled_check_change": card["bundled_check_change"],
                          **({"evaluation_stale": card["evaluation_stale"]}
                             if "evaluation_stale" in card else {})}))
        return
    if FLAGS.init_from_previous:
        raise app.UsageError("--init_from_previous goes with --replace_stage.")
    with common.user_errors("ship_weights"):
        card = shipped_weights.ship(FLAGS.model_dir, FLAGS.weights_dir, FLAGS.eval_json,
                                    FLAGS.allow_worse)
    print(json.dumps({"shipped": [s["file"] for s in card["stages"]],
                      "bundled_check_change": card["bundled_check_change"]}))


if __name__ == "__main__":
    app.run(main)
