"""Two image files aligned by a :class:`~stnh_tf.inference.estimator.HomographyEstimator`: the
overlay PNG and the JSON of ``experiments.predict`` (library core; the binary's docstring describes
the outputs and their names).

The homography maps image_b pixel coordinates (x, y) to image_a pixel coordinates
(``p_a ~ H @ p_b``, pixel centres at integer coordinates, ``H[2][2] = 1``); resizing rule:
:mod:`stnh_tf.inference.image_input`.

Files are read as make_dataset reads them (:func:`stnh_tf.data.sources.read_gray`, one
implementation): a truncated or unreadable file is refused (OpenCV's ``imread`` would fill in
a truncated JPEG; corrupt data inside a JPEG's stream is decoded as libjpeg decodes it), an alpha channel is composited onto black, 16-bit images are scaled by the bit
depth their values use (their colours too), and the pixel frame is the file's stored pixel order
(EXIF orientation ignored). The network sees the patch make_dataset would cut from the file; the
colours are used only to draw the overlay.
"""

import contextlib
import dataclasses
import json
import os
import sys

import numpy as np

from stnh_tf.inference import overlays


class AlignmentError(Exception):
    """An input image, the output folder or the model cannot be used (the message says which)."""


@dataclasses.dataclass(frozen=True)
class ImageFile:
    """An image file as :func:`read_image` reads it.

    Attributes:
      gray: uint8 ``[h, w]``, what is estimated on (:func:`stnh_tf.data.sources.read_gray`).
      colour: uint8 BGR ``[h, w, 3]`` of the same pixels, for drawing only (the decoder's colours,
        alpha dropped; the gray repeated where OpenCV cannot decode the file in colour).
    """

    gray: np.ndarray
    colour: np.ndarray

    @property
    def size(self) -> tuple:
        """``(w, h)``."""
        return int(self.gray.shape[1]), int(self.gray.shape[0])


def read_image(path, name, max_pixels: int | None = None) -> ImageFile:
    """The image file at ``path`` (``name``: "image_a" or "image_b", for the messages), read as
    make_dataset reads it (module docstring), refused before decoding when its header declares
    more than ``max_pixels`` pixels (``None``: :data:`stnh_tf.data.sources.MAX_IMAGE_PIXELS`).

    Raises:
      AlignmentError: one line naming the file: missing, unreadable, not an image, truncated or
        corrupt, over ``max_pixels`` (naming ``--max_image_pixels``), or too small for the patch
        (:func:`stnh_tf.inference.image_input.check_image_size`).
    """
    import cv2

    from stnh_tf.data import sources
    from stnh_tf.inference import image_input

    if max_pixels is None:
        max_pixels = sources.MAX_IMAGE_PIXELS
    if not os.path.isfile(path):
        raise AlignmentError(f"{name} {path!r} does not exist or is not a file.")
    try:
        with open(path, "rb") as f:
            data = f.read()
        gray = sources.read_gray(data, max_pixels)
    except sources.ImageTooLargeError as e:
        raise AlignmentError(f"{name} {path!r} is {e}; --max_image_pixels raises the cap.") \
            from None
    except (OSError, sources.ImageDecodeError) as e:
        raise AlignmentError(f"cannot read {name} {path!r} as an image: {e}.") from None
    colour = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR
                          | cv2.IMREAD_ANYDEPTH | cv2.IMREAD_IGNORE_ORIENTATION)
    if colour is None or colour.shape[:2] != gray.shape:
        colour = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    colour = sources.to_uint8(colour)  # a 16-bit file scaled as its gray
    image = ImageFile(gray=gray, colour=colour)
    try:
        image_input.check_image_size(image.size, f"{name} {path!r}")
    except ValueError as e:
        raise AlignmentError(str(e)) from None
    return image


PREDICT_LOCK = ".stnh_tf_predict.lock"
"""The lock file in ``predict``'s output folder under which a run chooses its outputs' name and
writes them (:func:`align_image_files`)."""


def output_stem(output_dir, inputs):
    """``<a>__<b>`` from the base names of the two ``inputs`` (absolute paths), or ``<a>__<b>-2``,
    ``-3``, ... when ``output_dir`` already holds the outputs of another pair with the same base
    names (its JSON's ``input_paths`` differ): the outputs of one pair are replaced on a re-run,
    never those of another."""
    base = "__".join(os.path.splitext(os.path.basename(p))[0] for p in inputs)
    stems = [base if k == 1 else f"{base}-{k}" for k in range(1, 10_000)]
    names = set(os.listdir(output_dir)) if os.path.isdir(output_dir) else set()
    for stem in stems:  # this pair's own outputs first, wherever they lie (gaps included)
        if f"{stem}_homography.json" not in names:
            continue
        try:
            with open(os.path.join(output_dir, f"{stem}_homography.json")) as f:
                if json.load(f).get("input_paths") == inputs:
                    return stem
        except (OSError, ValueError, AttributeError):
            pass  # not ours to replace
    for stem in stems:
        if not {f"{stem}_homography.json", f"{stem}_overlay.png"} & names:
            return stem
    raise AlignmentError(f"{output_dir} holds outputs of 9,999 pairs named {base}; choose "
                         "another --output_dir.")


def _warn_stderr(message):
    print(f"warning: {message}", file=sys.stderr)


def _note_stderr(message):
    print(f"note: {message}", file=sys.stderr)


def deviation_notes(estimate) -> list:
    """One line per step beyond the paper's network that changed the estimate of the (first)
    pair of an :class:`~stnh_tf.inference.pipeline.Estimate`: the search, the feature start, the
    refinement, the retry, a test-time symmetry; of an undetermined one, the steps of the
    estimate the identity replaced, said so."""
    notes = _step_notes(estimate)
    if estimate.undetermined is not None and estimate.undetermined[0]:
        return [f"of the estimate the identity replaced (not returned): {n}" for n in notes]
    return notes


def _step_notes(estimate) -> list:
    notes, ncc = [], float(estimate.alignment_ncc[0])
    if estimate.found[0]:
        notes.append(f"the network's estimate aligned the images poorly; the search (a deviation "
                     f"from the paper; --search=none gives the network's estimate) replaced it "
                     f"with one that aligns them at NCC {ncc:.3f}.")
    if estimate.feature_start is not None and estimate.feature_start[0]:
        notes.append(f"the estimate was made from a start found by OpenCV SIFT matches, which "
                     f"aligned the images better than the network's estimate (--features="
                     f"{estimate.options.features}, a deviation from the paper; --features=none "
                     f"leaves it out); it aligns them at NCC {ncc:.3f}.")
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


IDENTITY_FRAMES = (" (of the 320x240 work frames: in the images' own frames, the map between "
                   "their sizes where they differ)")
"""What the identity that ``estimate_images`` returns for a flat or undetermined pair is."""


def implausibility_warning(estimate) -> str | None:
    """The warning for the (first) pair of an :class:`~stnh_tf.inference.pipeline.Estimate`
    flagged implausible, or ``None``."""
    if not estimate.implausible[0]:
        return None
    if estimate.flat[0]:
        return ("the central patch of image_a or image_b is flat (nothing to align there): the "
                f"estimate is the identity{IDENTITY_FRAMES}, flagged implausible.")
    if estimate.undetermined is not None and estimate.undetermined[0]:
        return (f"the two images do not fix the estimate (its corner precision "
                f"{estimate.corner_std_px[0]:.3g} px is beyond Thresholds.undetermined_corner_std):"
                f" the identity{IDENTITY_FRAMES} is returned in its place, flagged implausible.")
    return (f"the estimate is implausible for this model (a patch corner moved "
            f"{estimate.max_corner_shift_px[0]:.1f} px at 128-px patch scale, the models were "
            f"trained on up to 32 px; {int(estimate.rejected_stages[0])} stage(s) skipped as "
            f"degenerate; image_a warped onto image_b correlates "
            f"{estimate.alignment_ncc[0]:.2f} with it at the central patch): the images may not "
            "overlap enough, or differ in ways the model was not trained on.")


def _estimate_json(estimate, shape_b, quad) -> dict:
    """The JSON fields of ``predict`` that describe the (first) pair's estimate."""
    import numpy as np

    h, used, ncc = estimate.homography[0], estimate.options, float(estimate.alignment_ncc[0])
    center_b = np.array([[(shape_b[1] - 1) / 2, (shape_b[0] - 1) / 2]])
    return {"direction": "homography maps image_b pixel (x, y) to image_a pixel: p_a ~ H @ p_b",
            "homography": np.asarray(h, np.float64).tolist(),
            # null for a point beyond image_a's horizon (no place in image_a)
            "image_b_border_in_a": [_point_or_none(p) for p in np.asarray(quad)],
            "image_b_center_in_a": _point_or_none(overlays.points_in_a(h, center_b)[0]),
            "implausible": bool(estimate.implausible[0]), "flat": bool(estimate.flat[0]),
            "refine": used.refine, "refined": bool(estimate.refined[0]),
            "tta": used.tta, "tta_choice": str(estimate.tta_choice[0]),
            "retry_tta": used.retry_tta, "retried": bool(estimate.retried[0]),
            "search": used.search, "searched": bool(estimate.searched[0]),
            "search_found": bool(estimate.found[0]),
            # made from the feature start (issue 64: OpenCV SIFT matches; --features)
            "feature_start": bool(estimate.feature_start[0]),
            "coarse": used.coarse, "features": used.features, "verify": used.verify,
            # the numbers of the checks (predict's --thresholds)
            "thresholds": used.to_json()["thresholds"],
            "max_corner_shift_px": _finite_or_none(estimate.max_corner_shift_px[0]),
            "alignment_ncc": ncc if np.isfinite(ncc) else None,
            # how far the steps beyond the network moved its own estimate (work image's corners)
            "network_homography": np.asarray(estimate.network_homography[0],
                                             np.float64).tolist(),
            "network_move_px": _finite_or_none(estimate.network_move_px[0]),
            # how precisely the two images fix it at image_b's corners (verify="ecc")
            "corner_std_px": _finite_or_none(estimate.corner_std_px[0]),
            # how far ECC on patch_b moved it (verify="ecc"; null: not verified or no
            # convergence), and whether the whole images bring that move back to the estimate
            "verify_move_px": _finite_or_none(estimate.verify_move_px[0]),
            "move_confirmed": bool(estimate.move_confirmed[0]),
            # above Thresholds.undetermined_corner_std: the identity in the estimate's place
            "undetermined": bool(estimate.undetermined[0]),
            # another shift of it aligns the images as well (verify="ecc"; a repeated pattern)
            "ambiguity_gap": _finite_or_none(estimate.ambiguity_gap[0]),
            "tile_ambiguity_gap": _finite_or_none(estimate.tile_ambiguity_gap[0]),
            # how well the whole work images align under it (below min_alignment_ncc: flagged)
            "image_ncc": _finite_or_none(estimate.image_ncc[0])}


BEYOND_NETWORK = ("search", "refine", "coarse", "features", "retry_tta")
"""The options of ``predict``'s JSON whose steps come after the network's own estimate (the
stages composed, with ``tta``); each ``none`` gives the network alone."""


def summary_line(result) -> str:
    """``predict``'s console line from its JSON ``result`` (:func:`align_image_files`): the
    final estimate's alignment NCC, and how far the steps beyond the network
    (:data:`BEYOND_NETWORK`) moved the network's own estimate (``network_move_px``: mean over
    the corners of the 320 x 240 work image), with the flags that give the network alone. A
    high NCC after the search and ECC says nothing about the network: the move does.

        >>> summary_line({"alignment_ncc": 0.993, "network_move_px": 31.2, "search": "ecc",
        ...               "refine": "images", "coarse": "none", "features": "none",
        ...               "retry_tta": "none"})  # doctest: +NORMALIZE_WHITESPACE
        "alignment NCC 0.993 (the final estimate's, at the central patch); the steps beyond the
        network (search=ecc, refine=images) moved the network's own estimate by 31.20 px at the
        320x240 work image's corners (JSON: network_homography); --search=none --refine=none
        gives the network alone."
    """
    ncc = result.get("alignment_ncc")
    line = (f"alignment NCC {ncc:.3f}" if ncc is not None else "alignment NCC undefined (a flat "
            "patch)") + " (the final estimate's, at the central patch); "
    steps = [k for k in BEYOND_NETWORK if result.get(k, "none") != "none"]
    if result.get("flat"):  # (whatever ran: the flat rule put the identity in place)
        return line + ("the central patch is flat: the flat rule (Thresholds.min_patch_std) put "
                       "the identity in place of the network's own estimate (JSON: "
                       "network_homography, network_move_px); --thresholds=min_patch_std=0 "
                       "leaves it out.")
    if not steps:
        return line + "no step beyond the network ran: the estimate is the network's own."
    move = result.get("network_move_px")
    moved = ("moved the network's own estimate by an unbounded distance (a corner of the "
             "320x240 work image maps to infinity)" if move is None else
             f"moved the network's own estimate by {move:.2f} px at the 320x240 work image's "
             "corners")
    return (line + f"the steps beyond the network ({', '.join(f'{k}={result[k]}' for k in steps)})"
            f" {moved} (JSON: network_homography); "
            f"{' '.join(f'--{k}=none' for k in steps)} gives the network alone.")


def _point_or_none(point):
    """``[x, y]`` as floats, or ``None`` where a coordinate is not finite."""
    return [float(v) for v in point] if np.isfinite(point).all() else None


def _finite_or_none(x):
    """``float(x)``, or ``None`` for a non-finite value (strict JSON has no NaN or infinity)."""
    import math

    return float(x) if math.isfinite(float(x)) else None


def align_image_files(image_a_path, image_b_path, model=None, output_dir=".", warn=_warn_stderr,
                      options=None, note=_note_stderr, max_pixels: int | None = None):
    """Estimate ``H_ba`` between two image files with ``model`` (what
    ``HomographyEstimator.load`` takes; ``None``: the shipped weights) and ``options`` (an
    :class:`~stnh_tf.inference.options.EstimateOptions`; ``None``: the estimator's default for
    images, ``EstimateOptions.photographs()``), write
    ``<a>__<b>_overlay.png`` and ``<a>__<b>_homography.json`` into ``output_dir`` (created if
    missing; :func:`output_stem`) and return the JSON's content. ``warn`` receives the warning
    of an implausible estimate, ``note`` each line of :func:`deviation_notes`. An image whose
    header declares more than ``max_pixels`` pixels is refused before it is decoded
    (:func:`read_image`).

    Raises:
      AlignmentError: an image cannot be read, ``output_dir`` cannot be written, or the model
        cannot be loaded.
    """
    import cv2

    from stnh_tf import paths
    from stnh_tf.inference.estimator import HomographyEstimator

    image_a = read_image(image_a_path, "image_a", max_pixels)
    image_b = read_image(image_b_path, "image_b", max_pixels)
    try:
        output_dir = paths.check_output_dir(output_dir)
    except OSError as e:
        raise AlignmentError(f"--output_dir: {e}") from None
    try:
        estimator = HomographyEstimator.load(model)
    except (FileNotFoundError, ValueError) as e:
        raise AlignmentError(str(e)) from None
    estimate = estimator.estimate_images_with_info(image_a.gray, image_b.gray, options)
    warning = implausibility_warning(estimate)
    if warning:
        warn(warning)
    for line in deviation_notes(estimate):
        note(line)
    panels, quad = overlays.overlay(image_a.colour, image_b.colour, estimate.homography[0],
                                    image_a.gray, image_b.gray)
    inputs = [os.path.realpath(image_a_path), os.path.realpath(image_b_path)]
    encoded, data = cv2.imencode(".png", panels)
    if not encoded:
        raise AlignmentError(f"cannot encode the overlay of {image_a_path}, {image_b_path}.")
    result = {"image_a": image_a_path, "image_b": image_b_path,
              "image_a_size": list(image_a.size), "image_b_size": list(image_b.size),
              "model": estimator.source, "kind": estimator.kind,
              "num_stages": estimator.num_stages,
              **_estimate_json(estimate, image_b.gray.shape, quad)}
    with contextlib.ExitStack() as held:
        try:  # another run choosing a name in the folder waits
            held.enter_context(paths.exclusive_lock(os.path.join(output_dir, PREDICT_LOCK), "",
                                                    wait=True))
        except OSError as e:
            raise AlignmentError(f"cannot lock {output_dir} ({PREDICT_LOCK}): {e}") from None
        stem = output_stem(output_dir, inputs)
        png = os.path.join(output_dir, f"{stem}_overlay.png")
        result.update(overlay_png=png, input_paths=inputs)
        doc = os.path.join(output_dir, f"{stem}_homography.json")
        try:  # together: a re-run that fails keeps the earlier overlay and JSON, both whole
            paths.atomic_write_files({png: data.tobytes(), doc: paths.json_text(
                result, sort_keys=False).encode()})
        except OSError as e:
            raise AlignmentError(f"cannot write {png} and {doc}: {e}") from None
    return result
