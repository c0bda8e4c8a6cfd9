r"""Export a trained model as a TensorFlow SavedModel and check the export.

  python -m experiments.export --model=runs/stage1 --output=exports/stage1 [--overwrite]

Signature ``serving_default``: ``patch_a``, ``patch_b`` uint8 ``[B, 128, 128, 1]`` ->
``homography`` float32 ``[B, 3, 3]`` (pixel ``H_ba``: patch_b -> patch_a). Beside
``saved_model.pb`` it writes ``README.md`` and ``signature.json``: the signature, the output's
frame, how to cut patches from photographs (a snippet) and the model card's numbers
(``stnh_tf.inference.export_contract``; docs/estimate.md, "The SavedModel export"). After
writing, the SavedModel is reloaded and run on ``--check_pairs`` photograph patch pairs; the JSON
summary (printed on stdout) gives the max abs difference from the same computation on the Keras
model, one line on stderr says what was compared and whether it passed, and the exit status is
nonzero if it exceeds ``--tolerance``. Only a passed check marks the folder verified
(``stnh_tf_export_verified.json``, written last): a folder without it (an export or check that
was killed, or failed) is named as never verified by the next export, which asks for
``--overwrite``, and by ``stnh_tf.inference.export.load_serving_signature``. The export holds
``--output``'s lock from its checks through the verification: a second export to the same
folder is refused at once, and the hidden staging folders a killed export left in it are
removed. Library code:
``stnh_tf.inference.export`` (``export_and_verify``).
"""

import json
import math
import sys

from absl import app, flags

from experiments import common

FLAGS = flags.FLAGS
flags.DEFINE_string("model", None, "Model: .keras file, run directory or hierarchy manifest "
                    "(default: the weights shipped in stnh_tf/weights).")
flags.DEFINE_string("output", None, "SavedModel directory to write.", required=True)
flags.DEFINE_bool("overwrite", False, "Replace an existing SavedModel at --output.")
flags.DEFINE_float("tolerance", 1e-3, "Largest accepted |SavedModel - Keras| on any H entry.")
flags.DEFINE_integer("check_pairs", 8, "Patch pairs used to compare the export with the model.")


def main(argv):
    del argv
    from stnh_tf.inference import export
    from stnh_tf.inference.estimator import HomographyEstimator

    if FLAGS.check_pairs < 1:
        raise SystemExit(f"export: --check_pairs must be >= 1; received {FLAGS.check_pairs}.")
    if not math.isfinite(FLAGS.tolerance) or FLAGS.tolerance < 0:
        raise SystemExit(f"export: --tolerance must be a finite number >= 0; received "
                         f"{FLAGS.tolerance}.")
    with common.user_errors("export"):
        # --overwrite replaces --output: never the model it exports (issue 80)
        common.check_flags_apart(("output",), (), models=("model",))
        estimator = HomographyEstimator.load(FLAGS.model)
        report = export.export_and_verify(estimator, FLAGS.output, overwrite=FLAGS.overwrite,
                                          check_pairs=FLAGS.check_pairs,
                                          tolerance=FLAGS.tolerance)
    report.update(model=estimator.source, output=FLAGS.output)
    print(json.dumps(report, indent=2))
    for path in report["kept_user_files"]:
        print(f"export: warning: kept your {path} (not written by an export); the export's own "
              "is not written there", file=sys.stderr)
    print(f"export: {export.verification_line(report)}", file=sys.stderr)
    if not report["ok"] and report["kept_earlier_export"]:
        raise SystemExit(f"export: the check failed (above): the earlier export at "
                         f"{FLAGS.output} is kept as it was, nothing replaced; export to a new "
                         "--output to inspect the failing one.")
    if not report["ok"]:
        raise SystemExit(f"export: the check failed (above). The SavedModel is left at "
                         f"{FLAGS.output} for inspection, not marked verified; re-export with "
                         "--overwrite.")


if __name__ == "__main__":
    app.run(main)
