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
entry's ``init_from_run``) and re-computes the bundled check.

  python -m experiments.ship_weights --refresh_check

re-computes only the bundled check of the weights already shipped (after a change to how
``HomographyEstimator`` computes, e.g. its default ``compute_dtype``), leaving the rest of the card.
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
FLAGS = flags.FLAGS


def main(argv):
    del argv
    with common.user_errors("ship_weights"):
        common.check_flags_apart(("weights_dir",), ("model_dir", "eval_json"))
    if FLAGS.refresh_check:
        if FLAGS.model_dir or FLAGS.eval_json:
            raise app.UsageError("--refresh_check takes neither --model_dir nor --eval_json.")
        card = shipped_weights.refresh_check(FLAGS.weights_dir)
        print(json.dumps({"bundled_check": card["bundled_check"]}))
        return
    if not FLAGS.model_dir:
        raise app.UsageError("--model_dir is required (or --refresh_check).")
    if FLAGS.replace_stage is not None:
        if len(FLAGS.model_dir) != 1:
            raise app.UsageError("--replace_stage takes exactly one --model_dir.")
        card = shipped_weights.replace_stage(FLAGS.replace_stage, FLAGS.model_dir[0],
                                             FLAGS.weights_dir, FLAGS.eval_json,
                                             FLAGS.init_from_previous)
        print(json.dumps({"replaced": card["stages"][FLAGS.replace_stage - 1]["file"]}))
        return
    if FLAGS.init_from_previous:
        raise app.UsageError("--init_from_previous goes with --replace_stage.")
    card = shipped_weights.ship(FLAGS.model_dir, FLAGS.weights_dir, FLAGS.eval_json)
    print(json.dumps({"shipped": [s["file"] for s in card["stages"]]}))


if __name__ == "__main__":
    app.run(main)
