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

from experiments import common
from stnh_tf.evaluation import mace as evaluation
from stnh_tf.inference.estimator import REFINES, SEARCH, SEARCHES, TTAS

flags.DEFINE_string("model", None, "Model or hierarchy (default: the shipped weights).")
flags.DEFINE_string("data_dir", None, "Stage-1 pairs (default: the model card's bundled pairs).")
flags.DEFINE_string("split", "test", "Split of --data_dir.")
flags.DEFINE_bool("photometric", False, "Bundled pairs with a photometric change of patch_b.")
flags.DEFINE_enum("refine", "none", list(REFINES), "estimate's refine: none or ecc.")
flags.DEFINE_enum("tta", "none", list(TTAS), "estimate's test-time augmentation.")
flags.DEFINE_enum("retry_tta", "none", list(TTAS), "estimate's retry of flagged pairs.")
flags.DEFINE_enum("search", SEARCH, list(SEARCHES), "estimate's search of poorly aligned pairs.")
flags.DEFINE_string("json_out", None, "Also write the JSON here.")
FLAGS = flags.FLAGS


def main(argv):
    del argv
    try:
        result = evaluation.implausibility_check(FLAGS.model, FLAGS.data_dir, FLAGS.split,
                                                 photometric=FLAGS.photometric,
                                                 refine=FLAGS.refine, tta=FLAGS.tta,
                                                 retry_tta=FLAGS.retry_tta, search=FLAGS.search)
    except (ValueError, OSError) as e:
        raise SystemExit(f"check_implausible: {e}") from None
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
