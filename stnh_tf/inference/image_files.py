"""Two image files aligned by a :class:`~stnh_tf.inference.estimator.HomographyEstimator`: the
overlay PNG and the JSON of ``experiments.predict`` (library core; the binary's docstring describes
the outputs and their names).

The homography maps image_b pixel coordinates (x, y) to image_a pixel coordinates
(``p_a ~ H @ p_b``, pixel centres at integer coordinates, ``H[2][2] = 1``); resizing rule:
:mod:`stnh_tf.inference.image_input`.
"""

import json
import os
import sys


class AlignmentError(Exception):
    """An input image, the output folder or the model cannot be used (the message says which)."""


def read_image(path, name):
    """BGR (or gray) uint8 image at ``path``; :class:`AlignmentError` if it cannot be read."""
    import cv2

    if not os.path.isfile(path):
        raise AlignmentError(f"{name} {path!r} does not exist or is not a file.")
    image = cv2.imread(path, cv2.IMREAD_COLOR)
    if image is None or image.size == 0:
        raise AlignmentError(f"cannot read {name} {path!r} as an image (OpenCV could not "
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
    raise AlignmentError(f"{output_dir} holds outputs of 9,999 pairs named {base}; choose "
                         "another --output_dir.")


OVERLAY_CAPTIONS = ("image_a; green: image_b's border mapped into it",
                    "magenta: image_a warped onto image_b; green: image_b; gray: aligned")
"""The caption above each panel of :func:`overlay`."""


def _caption(panel, text, scale):
    """``panel`` with a black band above it holding ``text`` in white (font ``scale``)."""
    import cv2
    import numpy as np

    (_, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    band = np.zeros((h + base + 8, panel.shape[1], 3), np.uint8)
    cv2.putText(band, text, (4, h + 4), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1,
                cv2.LINE_AA)
    return np.concatenate([band, panel], axis=0)


def overlay(image_a, image_b, h_ba):
    """Two captioned panels (uint8 BGR, :data:`OVERLAY_CAPTIONS`): image_a with image_b's border
    mapped into it, and the colour overlay of image_b on image_a warped onto image_b's frame by
    ``h_ba``. Returns ``(panels, quad)``, ``quad`` the ``[4, 2]`` border of image_b in image_a."""
    import cv2
    import numpy as np

    from stnh_tf import geometry

    (ha, wa), (hb, wb) = image_a.shape[:2], image_b.shape[:2]
    gray_a = cv2.cvtColor(image_a, cv2.COLOR_BGR2GRAY)
    gray_b = cv2.cvtColor(image_b, cv2.COLOR_BGR2GRAY)
    warped_a = cv2.warpPerspective(gray_a, h_ba, (wb, hb),
                                   flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    blend = np.stack([warped_a, gray_b, warped_a], axis=-1)  # BGR: a -> magenta, b -> green
    left = image_a.copy()
    border_b = np.array([[0, 0], [wb - 1, 0], [wb - 1, hb - 1], [0, hb - 1]], np.float64)
    quad = geometry.warp_points(h_ba, border_b)
    thickness = max(1, round(max(wa, ha) / 300))
    cv2.polylines(left, [np.round(quad).astype(np.int32).reshape(-1, 1, 2)], True, (0, 255, 0),
                  thickness, cv2.LINE_AA)
    scale = max(max(wa, wb) / 900.0, 0.35)  # one font size: the captions' bands are as high
    left, blend = (_caption(p, c, scale) for p, c in zip((left, blend), OVERLAY_CAPTIONS))
    height = max(left.shape[0], blend.shape[0])
    panels = [cv2.copyMakeBorder(p, 0, height - p.shape[0], 0, 8, cv2.BORDER_CONSTANT, value=0)
              for p in (left, blend)]
    return np.concatenate(panels, axis=1), quad


def _warn_stderr(message):
    print(f"warning: {message}", file=sys.stderr)


def _note_stderr(message):
    print(f"note: {message}", file=sys.stderr)


def deviation_notes(estimate) -> list:
    """One line per step beyond the paper's network that changed the estimate of the (first)
    pair of an :class:`~stnh_tf.inference.pipeline.Estimate`: the search, the refinement, the
    retry, a test-time symmetry."""
    notes, ncc = [], float(estimate.alignment_ncc[0])
    if estimate.found[0]:
        notes.append(f"the network's estimate aligned the images poorly; the search (a deviation "
                     f"from the paper; --search=none gives the network's estimate) replaced it "
                     f"with one that aligns them at NCC {ncc:.3f}.")
    if estimate.refined[0]:
        notes.append(f"the estimate is the ECC refinement of the network's "
                     f"(--refine={estimate.options.refine}, a deviation from the paper).")
    if estimate.retried[0]:
        notes.append(f"the estimate was flagged and estimated again with test-time augmentation "
                     f"(--retry_tta={estimate.options.retry_tta}, a deviation from the paper).")
    if estimate.tta_choice[0] != "identity":
        notes.append(f"the estimate is the network's on the images transformed by "
                     f"{estimate.tta_choice[0]} (test-time augmentation, a deviation).")
    return notes


def implausibility_warning(estimate) -> str | None:
    """The warning for the (first) pair of an :class:`~stnh_tf.inference.pipeline.Estimate`
    flagged implausible, or ``None``."""
    if not estimate.implausible[0]:
        return None
    if estimate.flat[0]:
        return ("the central patch of image_a or image_b is flat (nothing to align): the "
                "estimate is the identity, flagged implausible.")
    return (f"the estimate is implausible for this model (a patch corner moved "
            f"{estimate.max_corner_shift_px[0]:.1f} px at 128-px patch scale, the models were "
            f"trained on up to 32 px; {int(estimate.rejected_stages[0])} stage(s) skipped as "
            f"degenerate; image_a warped onto image_b correlates "
            f"{estimate.alignment_ncc[0]:.2f} with it at the central patch): the images may not "
            "overlap enough, or differ in ways the model was not trained on.")


def _estimate_json(estimate, shape_b, quad) -> dict:
    """The JSON fields of ``predict`` that describe the (first) pair's estimate."""
    import numpy as np

    from stnh_tf import geometry

    h, used, ncc = estimate.homography[0], estimate.options, float(estimate.alignment_ncc[0])
    center_b = np.array([[(shape_b[1] - 1) / 2, (shape_b[0] - 1) / 2]])
    return {"direction": "homography maps image_b pixel (x, y) to image_a pixel: p_a ~ H @ p_b",
            "homography": np.asarray(h, np.float64).tolist(),
            "image_b_border_in_a": np.asarray(quad).tolist(),
            "image_b_center_in_a": geometry.warp_points(h, center_b)[0].tolist(),
            "implausible": bool(estimate.implausible[0]), "flat": bool(estimate.flat[0]),
            "refine": used.refine, "refined": bool(estimate.refined[0]),
            "tta": used.tta, "tta_choice": str(estimate.tta_choice[0]),
            "retry_tta": used.retry_tta, "retried": bool(estimate.retried[0]),
            "search": used.search, "searched": bool(estimate.searched[0]),
            "search_found": bool(estimate.found[0]),
            "max_corner_shift_px": float(estimate.max_corner_shift_px[0]),
            "alignment_ncc": ncc if np.isfinite(ncc) else None}


def align_image_files(image_a_path, image_b_path, model=None, output_dir=".", warn=_warn_stderr,
                      options=None, note=_note_stderr):
    """Estimate ``H_ba`` between two image files with ``model`` (what
    ``HomographyEstimator.load`` takes; ``None``: the shipped weights) and ``options`` (an
    :class:`~stnh_tf.inference.options.EstimateOptions`; ``None``: the estimator's default for
    images, ``EstimateOptions.photographs()``), write
    ``<a>__<b>_overlay.png`` and ``<a>__<b>_homography.json`` into ``output_dir`` (created if
    missing; :func:`output_stem`) and return the JSON's content. ``warn`` receives the warning
    of an implausible estimate, ``note`` each line of :func:`deviation_notes`.

    Raises:
      AlignmentError: an image cannot be read, ``output_dir`` cannot be written, or the model
        cannot be loaded.
    """
    import cv2

    from stnh_tf import paths
    from stnh_tf.inference.estimator import HomographyEstimator

    image_a = read_image(image_a_path, "image_a")
    image_b = read_image(image_b_path, "image_b")
    try:
        output_dir = paths.check_output_dir(output_dir)
    except OSError as e:
        raise AlignmentError(f"--output_dir: {e}") from None
    try:
        estimator = HomographyEstimator.load(model)
    except (FileNotFoundError, ValueError) as e:
        raise AlignmentError(str(e)) from None
    estimate = estimator.estimate_images_with_info(image_a, image_b, options, channel_order="bgr")
    warning = implausibility_warning(estimate)
    if warning:
        warn(warning)
    for line in deviation_notes(estimate):
        note(line)
    panels, quad = overlay(image_a, image_b, estimate.homography[0])
    inputs = [os.path.realpath(image_a_path), os.path.realpath(image_b_path)]
    stem = output_stem(output_dir, inputs)
    png = os.path.join(output_dir, f"{stem}_overlay.png")
    if not cv2.imwrite(png, panels):
        raise AlignmentError(f"cannot write {png}.")
    result = {"image_a": image_a_path, "image_b": image_b_path,
              "image_a_size": [int(image_a.shape[1]), int(image_a.shape[0])],
              "image_b_size": [int(image_b.shape[1]), int(image_b.shape[0])],
              "model": estimator.source, "kind": estimator.kind,
              "num_stages": estimator.num_stages,
              **_estimate_json(estimate, image_b.shape, quad), "overlay_png": png,
              "input_paths": inputs}
    with open(os.path.join(output_dir, f"{stem}_homography.json"), "w") as f:
        json.dump(result, f, indent=2)
        f.write("\n")
    return result
