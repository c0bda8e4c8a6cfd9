r"""Estimate the homography between two images and draw the alignment.

  python -m experiments.predict --image_a=a.jpg --image_b=b.jpg [--model=runs/stage1] \
      [--output_dir=out] [--tta=dihedral | --retry_tta=dihedral] [--search=none] \
      [--features=none --refine=none --verify=none]

The estimator's options default to ``estimate_images``' (``EstimateOptions.photographs()``: the
feature start, the search, the whole-image refinement, the ECC check of the flag; the coarse
pass is off: ``--coarse=rotations`` adds it); ``--features=none --refine=none --verify=none`` give
``EstimateOptions()``.

Prints a JSON object whose ``homography`` maps image_b pixel coordinates (x, y) to image_a pixel
coordinates (``p_a ~ H @ p_b``, pixel centres at integer coordinates, ``H[2][2] = 1``) and
``network_homography``, the network's own estimate, then (on stderr) one line with the final
estimate's alignment NCC and how far the steps beyond the network (search, ECC refinement,
coarse pass, ...) moved the network's own estimate, with the flags that give the network alone
(``stnh_tf.inference.image_files.summary_line``): the NCC of the default is high even for a
model worse than the identity, the move is not small then. It writes
to ``--output_dir`` (default: the current directory) ``<a>__<b>_overlay.png`` and the same JSON as
``<a>__<b>_homography.json`` (``<a>__<b>-2_...`` and so on when the folder holds the outputs of
another pair of images with the same base names; a re-run of the same pair replaces its own;
the name is chosen and both files written under the lock file ``.stnh_tf_predict.lock`` there,
so that runs into one folder at once never share a name).
The PNG has two panels: image_a with the quadrilateral where image_b's border lands (green), and
image_b (green channel) over image_a warped onto image_b by the estimate (magenta), image_a's
gray levels matched to image_b's over their overlap: aligned regions look gray, also across an
exposure change; the captions wrap to fit their panels. ``--model`` takes what
``HomographyEstimator.load`` takes (``.keras`` file, run directory, hierarchy manifest); without
it the shipped default weights are used. Resizing rule: see ``stnh_tf.inference.image_input``.
The files are read as ``make_dataset`` reads them (``stnh_tf.inference.image_files``): a
truncated or unreadable file is refused (corrupt data inside a JPEG's stream is decoded as
libjpeg decodes it), an alpha channel is composited onto black, pixel frames
are the files' stored pixel order (EXIF orientation ignored); an image under 20 x 15 px is
refused (too small for the patch), and one whose header declares more than
``--max_image_pixels`` pixels before it is decoded (a decompression bomb).
"""

import json
import sys

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.data import sources
from stnh_tf.inference import image_files
from stnh_tf.inference.options import EstimateOptions

FLAGS = flags.FLAGS
flags.DEFINE_string("image_a", None, "Path of image_a (the reference image).", required=True)
flags.DEFINE_string("image_b", None, "Path of image_b (the image mapped into image_a).",
                    required=True)
flags.DEFINE_string("model", None, "Model: .keras file, run directory or hierarchy manifest "
                    "(default: the weights shipped in stnh_tf/weights).")
flags.DEFINE_string("output_dir", ".",
                    "Folder for the overlay PNG and the JSON (created if missing).")
flags.DEFINE_integer("max_image_pixels", sources.MAX_IMAGE_PIXELS,
                     "Refuse an image whose header declares more pixels (width x height) than "
                     "this, before decoding it (a guard against decompression bombs: a small "
                     "file that decodes to gigabytes; about 17 bytes of memory a pixel).",
                     lower_bound=1)
# estimate_images' default options
flags_common.define_estimate_flags(("refine", "tta", "retry_tta", "search", "coarse", "verify",
                                    "features"),
                                   EstimateOptions.photographs(), thresholds=True)
flags.adopt_module_key_flags(flags_common)  # --help lists them


def main(argv):
    del argv
    with common.user_errors("predict"):  # a bad --thresholds item
        options = flags_common.options_from_flags()
    try:
        result = image_files.align_image_files(
            FLAGS.image_a, FLAGS.image_b, FLAGS.model, FLAGS.output_dir,
            warn=lambda message: print(f"predict: warning: {message}", file=sys.stderr),
            note=lambda message: print(f"predict: note: {message}", file=sys.stderr),
            options=options, max_pixels=FLAGS.max_image_pixels)
    except image_files.AlignmentError as e:
        raise SystemExit(f"predict: {e}") from None
    print(json.dumps(result, indent=2))
    print(f"predict: {image_files.summary_line(result)}", file=sys.stderr)


if __name__ == "__main__":
    app.run(main)
