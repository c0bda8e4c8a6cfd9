r"""Estimate the homography between two images and draw the alignment.

  python -m experiments.predict --image_a=a.jpg --image_b=b.jpg [--model=runs/stage1] \
      [--output_dir=out]

Prints a JSON object whose ``homography`` maps image_b pixel coordinates (x, y) to image_a pixel
coordinates (``p_a ~ H @ p_b``, pixel centres at integer coordinates, ``H[2][2] = 1``), and writes
to ``--output_dir`` (default: the current directory) ``<a>__<b>_overlay.png`` and the same JSON as
``<a>__<b>_homography.json`` (``<a>__<b>-2_...`` and so on when the folder holds the outputs of
another pair of images with the same base names; a re-run of the same pair replaces its own).
The PNG has two panels: image_a with the quadrilateral where image_b's border lands (green), and
image_b (green channel) over image_a warped onto image_b by the estimate (magenta): aligned
regions look gray. ``--model`` takes what
``HomographyEstimator.load`` takes (``.keras`` file, run directory, hierarchy manifest); without
it the shipped default weights are used. Resizing rule: see ``stnh_tf.image_input``.
"""

import json
import os
import sys

from absl import app, flags

FLAGS = flags.FLAGS
flags.DEFINE_string("image_a", None, "Path of image_a (the reference image).", required=True)
flags.DEFINE_string("image_b", None, "Path of image_b (the image mapped into image_a).", required=True)
flags.DEFINE_string("model", None, "Model: .keras file, run directory or hierarchy manifest "
                    "(default: the weights shipped in stnh_tf/weights).")
flags.DEFINE_string("output_dir", ".", "Folder for the overlay PNG and the JSON (created if missing).")


def read_image(path, name):
    """BGR (or gray) uint8 image at ``path``; SystemExit with a message if it cannot be read."""
    import cv2

    if not os.path.isfile(path):
        raise SystemExit(f"predict: {name} {path!r} does not exist or is not a file.")
    image = cv2.imread(path, cv2.IMREAD_COLOR)
    if image is None or image.size == 0:
        raise SystemExit(f"predict: cannot read {name} {path!r} as an image (OpenCV could not "
                         "decode it).")
    return image


def output_stem(output_dir, inputs):
    """``<a>__<b>`` from the base names of the two ``inputs`` (absolute paths), or ``<a>__<b>-2``,
    ``-3``, ... when ``output_dir`` already holds the outputs of another pair with the same base
    names (its JSON's ``input_paths`` differ): the outputs of one pair are replaced on a re-run,
    never those of another."""
    base = "__".join(os.path.splitext(os.path.basename(p))[0] for p in inputs)
    for k in range(1, 10_000):
        stem = base if k == 1 else f"{base}-{k}"
        existing = os.path.join(output_dir, f"{stem}_homography.json")
        if not os.path.exists(existing) and \
                not os.path.exists(os.path.join(output_dir, f"{stem}_overlay.png")):
            return stem
        try:
            with open(existing) as f:
                if json.load(f).get("input_paths") == inputs:
                    return stem
        except (OSError, ValueError, AttributeError):
            pass  # not ours to replace
    raise SystemExit(f"predict: {output_dir} holds outputs of 9,999 pairs named {base}; choose "
                     "another --output_dir.")


def overlay(image_a, image_b, h_ba):
    """Two panels (uint8 BGR): image_a with image_b's border mapped into it, and the colour
    overlay of image_b on image_a warped onto image_b's frame by ``h_ba``."""
    import cv2
    import numpy as np

    from stnh_tf import geometry

    (ha, wa), (hb, wb) = image_a.shape[:2], image_b.shape[:2]
    gray_a = cv2.cvtColor(image_a, cv2.COLOR_BGR2GRAY)
    gray_b = cv2.cvtColor(image_b, cv2.COLOR_BGR2GRAY)
    warped_a = cv2.warpPerspective(gray_a, h_ba, (wb, hb), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    blend = np.stack([warped_a, gray_b, warped_a], axis=-1)  # BGR: a -> magenta, b -> green
    left = image_a.copy()
    border_b = np.array([[0, 0], [wb - 1, 0], [wb - 1, hb - 1], [0, hb - 1]], np.float64)
    quad = geometry.warp_points(h_ba, border_b)
    thickness = max(1, round(max(wa, ha) / 300))
    cv2.polylines(left, [np.round(quad).astype(np.int32).reshape(-1, 1, 2)], True, (0, 255, 0),
                  thickness, cv2.LINE_AA)
    height = max(ha, hb)
    pad = lambda im: cv2.copyMakeBorder(im, 0, height - im.shape[0], 0, 8, cv2.BORDER_CONSTANT, value=0)
    return np.concatenate([pad(left), pad(blend)], axis=1), quad


def main(argv):
    del argv
    import cv2
    import numpy as np

    from stnh_tf import geometry, paths
    from stnh_tf.inference import HomographyEstimator

    image_a = read_image(FLAGS.image_a, "image_a")
    image_b = read_image(FLAGS.image_b, "image_b")
    try:
        output_dir = paths.check_output_dir(FLAGS.output_dir)
    except OSError as e:
        raise SystemExit(f"predict: --output_dir: {e}") from None
    try:
        estimator = HomographyEstimator.load(FLAGS.model)
    except (FileNotFoundError, ValueError) as e:
        raise SystemExit(f"predict: {e}") from None
    h = estimator.estimate_images(image_a, image_b, channel_order="bgr")
    info = estimator.last_info
    implausible = bool(info["implausible"][0])
    if implausible:
        print(f"predict: warning: the estimate is implausible for this model (a patch corner "
              f"moved {info['max_corner_shift_px'][0]:.1f} px at 128-px patch scale, the models "
              f"were trained on up to 32 px; {int(info['rejected_stages'][0])} stage(s) skipped "
              "as degenerate): the images may not overlap enough, or differ in ways the model "
              "was not trained on.", file=sys.stderr)
    panels, quad = overlay(image_a, image_b, h)

    inputs = [os.path.realpath(FLAGS.image_a), os.path.realpath(FLAGS.image_b)]
    stem = output_stem(output_dir, inputs)
    png = os.path.join(output_dir, f"{stem}_overlay.png")
    if not cv2.imwrite(png, panels):
        raise SystemExit(f"predict: cannot write {png}.")
    result = {
        "image_a": FLAGS.image_a, "image_b": FLAGS.image_b,
        "image_a_size": [int(image_a.shape[1]), int(image_a.shape[0])],
        "image_b_size": [int(image_b.shape[1]), int(image_b.shape[0])],
        "model": estimator.source, "kind": estimator.kind, "num_stages": estimator.num_stages,
        "direction": "homography maps image_b pixel (x, y) to image_a pixel: p_a ~ H @ p_b",
        "homography": np.asarray(h, np.float64).tolist(),
        "image_b_border_in_a": np.asarray(quad).tolist(),
        "image_b_center_in_a": geometry.warp_points(
            h, np.array([[(image_b.shape[1] - 1) / 2, (image_b.shape[0] - 1) / 2]]))[0].tolist(),
        "overlay_png": png,
        "input_paths": inputs,
        "implausible": implausible,
        "max_corner_shift_px": float(info["max_corner_shift_px"][0]),
    }
    with open(os.path.join(output_dir, f"{stem}_homography.json"), "w") as f:
        json.dump(result, f, indent=2)
        f.write("\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    app.run(main)
