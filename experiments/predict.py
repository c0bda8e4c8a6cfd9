r"""Estimate the homography between two images and draw the alignment.

  python -m experiments.predict --image_a=a.jpg --image_b=b.jpg [--model=runs/stage1] \
      [--output_dir=out] [--refine=ecc] [--tta=dihedral | --retry_tta=dihedral] [--search=none]

Prints a JSON object whose ``homography`` maps image_b pixel coordinates (x, y) to image_a pixel
coordinates (``p_a ~ H @ p_b``, pixel centres at integer coordinates, ``H[2][2] = 1``), and writes
to ``--output_dir`` (default: the current directory) ``<a>__<b>_overlay.png`` and the same JSON as
``<a>__<b>_homography.json`` (``<a>__<b>-2_...`` and so on when the folder holds the outputs of
another pair of images with the same base names; a re-run of the same pair replaces its own).
The PNG has two panels: image_a with the quadrilateral where image_b's border lands (green), and
image_b (green channel) over image_a warped onto image_b by the estimate (magenta): aligned
regions look gray. ``--model`` takes what
``HomographyEstimator.load`` takes (``.keras`` file, run directory, hierarchy manifest); without
it the shipped default weights are used. Resizing rule: see ``stnh_tf.inference.image_input``.
"""

import json
import sys

from absl import app, flags

from stnh_tf.inference import image_files as alignment
from stnh_tf.inference.estimator import REFINES, SEARCH, SEARCHES, TTAS

FLAGS = flags.FLAGS
flags.DEFINE_string("image_a", None, "Path of image_a (the reference image).", required=True)
flags.DEFINE_string("image_b", None, "Path of image_b (the image mapped into image_a).", required=True)
flags.DEFINE_string("model", None, "Model: .keras file, run directory or hierarchy manifest "
                    "(default: the weights shipped in stnh_tf/weights).")
flags.DEFINE_string("output_dir", ".", "Folder for the overlay PNG and the JSON (created if missing).")
flags.DEFINE_enum("refine", "none", list(REFINES), "After the network: none (the paper) or ecc "
                  "(OpenCV's ECC alignment started from the estimate, a deviation).")
flags.DEFINE_enum("tta", "none", list(TTAS), "Test-time augmentation: none (the paper), flips "
                  "or dihedral (also estimate the images mirrored and rotated, keep the best "
                  "aligned estimate; a deviation).")
flags.DEFINE_enum("retry_tta", "none", list(TTAS), "Estimate again with this test-time "
                  "augmentation only if the estimate is flagged implausible: none (the paper), "
                  "flips or dihedral (a deviation).")
flags.DEFINE_enum("search", SEARCH, list(SEARCHES), "Where the estimate aligns the images poorly: "
                  "ecc (start OpenCV's ECC alignment from the best translations of it, keep a "
                  "near-perfect result; a deviation) or none (the network's estimate).")


def main(argv):
    del argv
    try:
        result = alignment.align_image_files(
            FLAGS.image_a, FLAGS.image_b, FLAGS.model, FLAGS.output_dir,
            warn=lambda message: print(f"predict: warning: {message}", file=sys.stderr),
            refine=FLAGS.refine, tta=FLAGS.tta, retry_tta=FLAGS.retry_tta, search=FLAGS.search)
    except alignment.AlignmentError as e:
        raise SystemExit(f"predict: {e}") from None
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    app.run(main)
