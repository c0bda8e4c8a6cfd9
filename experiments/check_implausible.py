r"""How often the estimator flags its estimates as implausible, on ordinary pairs and on pairs it
was not trained on (another photograph, patch_b rotated 180 degrees, motion of 80 px).

  python -m experiments.check_implausible                      # shipped weights, bundled pairs
  python -m experiments.check_implausible --model=runs/stage1 --data_dir=data/coco_mini
  python -m experiments.check_implausible --refine=ecc          # the estimates ECC-refined
  python -m experiments.check_implausible --tta=dihedral        # test-time augmentation
  python -m experiments.check_implausible --retry_tta=dihedral  # ... of the flagged pairs only
  python -m experiments.check_implausible --search=none         # the network's estimates only

Prints a short table (:func:`stnh_tf.evaluation.summaries.implausibility_table`: the estimator
and the identity on the ordinary pairs, the share flagged per case); --json_out=FILE writes the
JSON of :func:`stnh_tf.evaluation.mace.implausibility_check`, --json_out=- prints it instead.
"""

from __future__ import annotations

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.evaluation import mace, summaries

flags.DEFINE_string("model", None, "Model or hierarchy (default: the shipped weights).")
flags.DEFINE_string("data_dir", None, "Stage-1 pairs (default: the model card's bundled pairs).")
flags.DEFINE_string("split", "test", "Split of --data_dir.")
flags.DEFINE_bool("photometric", False, "Bundled pairs with a photometric change of patch_b.")
flags_common.define_estimate_flags(("refine", "tta", "retry_tta", "search"))
flags.DEFINE_string("json_out", None, summaries.JSON_OUT_HELP)
FLAGS = flags.FLAGS
flags.adopt_module_key_flags(flags_common)  # --help lists them


def main(argv):
    del argv
    with common.user_errors("check_implausible"):
        common.check_flags_apart(("json_out",), ("data_dir",), models=("model",))
        summaries.check_json_out(FLAGS.json_out)
        result = mace.implausibility_check(FLAGS.model, FLAGS.data_dir, FLAGS.split,
                                           photometric=FLAGS.photometric,
                                           options=flags_common.options_from_flags())
    summaries.emit(result, summaries.implausibility_table(result), FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
