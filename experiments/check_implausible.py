r"""How often the estimator flags its estimates as implausible, on ordinary pairs and on pairs it
was not trained on (another photograph, patch_b rotated 180 degrees, motion of 80 px).

  python -m experiments.check_implausible                      # shipped weights, bundled pairs
  python -m experiments.check_implausible --model=runs/stage1 --data_dir=data/coco_mini
  python -m experiments.check_implausible --refine=ecc          # the estimates ECC-refined
  python -m experiments.check_implausible --tta=dihedral        # test-time augmentation
  python -m experiments.check_implausible --retry_tta=dihedral  # ... of the flagged pairs only
  python -m experiments.check_implausible --search=none         # the network's estimates only

Prints one JSON object (:func:`stnh_tf.evaluation.mace.implausibility_check`).
"""

from __future__ import annotations

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.evaluation import mace

flags.DEFINE_string("model", None, "Model or hierarchy (default: the shipped weights).")
flags.DEFINE_string("data_dir", None, "Stage-1 pairs (default: the model card's bundled pairs).")
flags.DEFINE_string("split", "test", "Split of --data_dir.")
flags.DEFINE_bool("photometric", False, "Bundled pairs with a photometric change of patch_b.")
flags_common.define_estimate_flags(("refine", "tta", "retry_tta", "search"))
flags_common.define_json_out()
FLAGS = flags.FLAGS
flags.adopt_module_key_flags(flags_common)  # --help lists them


def main(argv):
    del argv
    with common.user_errors("check_implausible"):
        result = mace.implausibility_check(FLAGS.model, FLAGS.data_dir, FLAGS.split,
                                           photometric=FLAGS.photometric,
                                           options=flags_common.options_from_flags())
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
