"""Two image files aligned by a :class:`~stnh_tf.inference.estimator.HomographyEstimator`: the
overlay PNG and the JSON of ``experiments.predict`` (library core; the binary's docstring describes
the outputs and their names).

The homography maps image_b pixel coordinates (x, y) to image_a pixel coordinates
(``p_a ~ H @ p_b``, pixel centres at integer coordinates, ``H[2][2] = 1``); resizing rule:
:mod:`stnh_tf.inference.image_input`.

Files are read as make_dataset reads them (:func:`stnh_tf.data.sources.read_gray`, one
implementation): a truncated or corrupt file is refused (OpenCV's ``imread`` would fill in a
truncated JPEG), an alpha channel is composited onto black, 16-bit images are scaled by the bit
depth their values use (their colours too), and the pixel frame is the file's stored pixel order
(EXIF orientation ignored). The network sees the patch make_dataset would cut from the file; the
colours are used only to draw the overlay.
"""

import dataclasses
import json
import os
import sys

import numpy as np

from stnh_tf.paths import atomic_write_json


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
"""The caption above each panel of :func:`overlay` (wrapped to the panel's width:
:func:`caption_lines`)."""
CAPTION_MARGIN = 4
"""Pixels left free on each side of a caption line."""
MIN_PANEL_WIDTH = 240
"""Panels narrower than this are enlarged (nearest neighbour, an integer factor) before their
caption is drawn, so that the caption stays legible (images down to 20 x 15 px are accepted)."""


def caption_scale(widths) -> float:
    """The font scale of both captions of panels of ``widths`` (one size, so that equal lines
    are as high): ``min(widths) / 900``, at least 0.35."""
    return max(min(widths) / 900.0, 0.35)


def caption_lines(text, width, scale) -> list:
    """``text`` wrapped into lines that fit a panel ``width`` px wide at font ``scale`` (each
    line's ``cv2.getTextSize`` width plus :data:`CAPTION_MARGIN` on each side): whole clauses
    (split after ``;``) where they fit, else words; a word wider than that on its own is a line
    of its own (at :func:`caption_scale` none is: the longest word takes about a fifth of the
    narrowest panel). ``" ".join(lines) == text`` for a text with single spaces.

        >>> caption_lines("magenta: image_a warped; green: image_b", 180, 0.35)
        ['magenta: image_a warped;', 'green: image_b']
    """
    import cv2

    def fits(line):
        size, _ = cv2.getTextSize(line, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
        return size[0] + 2 * CAPTION_MARGIN <= width

    def pack(pieces, lines):
        for piece in pieces:
            if lines and fits(f"{lines[-1]} {piece}"):
                lines[-1] = f"{lines[-1]} {piece}"
            elif fits(piece) or " " not in piece:
                lines.append(piece)
            else:
                pack(piece.split(" "), lines)
        return lines

    clauses = text.split("; ")
    return pack([c + ";" for c in clauses[:-1]] + clauses[-1:], [])


def _line_step(scale):
    """``(text height, pixels from one caption line to the next)`` at font ``scale``."""
    import cv2

    (_, h), base = cv2.getTextSize("Ag", cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    return h, h + base + 4


def _caption_band(lines, width, scale, height):
    """A black band ``height`` x ``width`` px holding ``lines`` in white (font ``scale``)."""
    import cv2

    h, step = _line_step(scale)
    band = np.zeros((height, width, 3), np.uint8)
    for k, line in enumerate(lines):
        cv2.putText(band, line, (CAPTION_MARGIN, 4 + h + k * step), cv2.FONT_HERSHEY_SIMPLEX,
                    scale, (255, 255, 255), 1, cv2.LINE_AA)
    return band


def _enlarged(panel):
    """``panel`` enlarged by the smallest integer factor that makes it at least
    :data:`MIN_PANEL_WIDTH` wide (nearest neighbour), or as it is."""
    import cv2

    factor = -(-MIN_PANEL_WIDTH // panel.shape[1])
    if factor <= 1:
        return panel
    return cv2.resize(panel, None, fx=factor, fy=factor, interpolation=cv2.INTER_NEAREST)


def matched_brightness(warped_a, gray_b, valid) -> np.ndarray:
    """``warped_a`` (uint8 ``[h, w]``) with its gray levels mapped onto those of ``gray_b``
    (histogram matching over ``valid``, bool ``[h, w]``: where image_a reaches; 0 elsewhere), so
    that a change of brightness, contrast, gamma or clipping between the photographs does not
    tint the overlay's aligned regions: a level whose share of ``warped_a``'s pixels at or below
    it is q becomes the lowest level of ``gray_b`` with a share of at least q.

        >>> a = np.arange(256, dtype=np.uint8).reshape(16, 16)
        >>> b = np.clip(a * 1.5, 0, 255).astype(np.uint8)
        >>> bool((matched_brightness(a, b, np.ones_like(a, bool)) == b).all())
        True
    """
    if not valid.any():
        return np.zeros_like(warped_a)
    share_a, share_b = (np.cumsum(np.bincount(x[valid], minlength=256)) / valid.sum()
                        for x in (warped_a, gray_b))
    lut = np.searchsorted(share_b, share_a - 1e-9).clip(0, 255).astype(np.uint8)
    return np.where(valid, lut[warped_a], 0).astype(np.uint8)


def overlay(image_a, image_b, h_ba, gray_a=None, gray_b=None):
    """Two captioned panels (uint8 BGR, :data:`OVERLAY_CAPTIONS`): image_a with image_b's border
    mapped into it, and the colour overlay of image_b (green) on image_a warped onto image_b's
    frame by ``h_ba`` (magenta), of ``gray_a`` and ``gray_b`` (the gray images estimated on, when
    given; else the BGR images made gray), image_a's gray levels matched to image_b's over
    their overlap (:func:`matched_brightness`): aligned regions look gray, also across an
    exposure change.
    Each caption is wrapped to its panel's width (:func:`caption_lines`), a panel narrower than
    :data:`MIN_PANEL_WIDTH` enlarged first. Returns ``(panels, quad)``, ``quad`` the ``[4, 2]``
    border of image_b in image_a."""
    import cv2

    from stnh_tf import geometry

    (ha, wa), (hb, wb) = image_a.shape[:2], image_b.shape[:2]
    if gray_a is None:
        gray_a = cv2.cvtColor(image_a, cv2.COLOR_BGR2GRAY)
    if gray_b is None:
        gray_b = cv2.cvtColor(image_b, cv2.COLOR_BGR2GRAY)
    warped_a = cv2.warpPerspective(gray_a, h_ba, (wb, hb),
                                   flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    valid = cv2.warpPerspective(np.ones((ha, wa), np.uint8), h_ba, (wb, hb),
                                flags=cv2.WARP_INVERSE_MAP | cv2.INTER_NEAREST) > 0
    warped_a = matched_brightness(warped_a, gray_b, valid)
    blend = np.stack([warped_a, gray_b, warped_a], axis=-1)  # BGR: a -> magenta, b -> green
    left = image_a.copy()
    border_b = np.array([[0, 0], [wb - 1, 0], [wb - 1, hb - 1], [0, hb - 1]], np.float64)
    quad = geometry.warp_points(h_ba, border_b)
    thickness = max(1, round(max(wa, ha) / 300))
    cv2.polylines(left, [np.round(quad).astype(np.int32).reshape(-1, 1, 2)], True, (0, 255, 0),
                  thickness, cv2.LINE_AA)
    left, blend = _enlarged(left), _enlarged(blend)
    widths = (left.shape[1], blend.shape[1])
    scale = caption_scale(widths)
    lines = [caption_lines(c, w, scale) for c, w in zip(OVERLAY_CAPTIONS, widths)]
    band_height = _line_step(scale)[1] * max(map(len, lines)) + 4  # both panels start level
    panels = [np.concatenate([_caption_band(ls, w, scale, band_height), p], axis=0)
              for ls, w, p in zip(lines, widths, (left, blend))]
    height = max(p.shape[0] for p in panels)
    panels = [cv2.copyMakeBorder(p, 0, height - p.shape[0], 0, 8, cv2.BORDER_CONSTANT, value=0)
              for p in panels]
    return np.concatenate(panels, axis=1), quad


def _warn_stderr(message):
    print(f"warning: {message}", file=sys.stderr)


def _note_stderr(message):
    print(f"note: {message}", file=sys.stderr)


def deviation_notes(estimate) -> list:
    """One line per step beyond the paper's network that changed the estimate of the (first)
    pair of an :class:`~stnh_tf.inference.pipeline.Estimate`: the search, the feature start, the
    refinement, the retry, a test-time symmetry."""
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
            # made from the feature start (issue 64: OpenCV SIFT matches; --features)
            "feature_start": bool(estimate.feature_start[0]),
            "coarse": used.coarse, "features": used.features, "verify": used.verify,
            # the numbers of the checks (predict's --thresholds)
            "thresholds": used.to_json()["thresholds"],
            "max_corner_shift_px": float(estimate.max_corner_shift_px[0]),
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
            "ambiguity_gap": _finite_or_none(estimate.ambiguity_gap[0])}


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
    panels, quad = overlay(image_a.colour, image_b.colour, estimate.homography[0], image_a.gray,
                           image_b.gray)
    inputs = [os.path.realpath(image_a_path), os.path.realpath(image_b_path)]
    stem = output_stem(output_dir, inputs)
    png = os.path.join(output_dir, f"{stem}_overlay.png")
    encoded, data = cv2.imencode(".png", panels)
    if not encoded:
        raise AlignmentError(f"cannot encode {png}.")
    try:  # a re-run cut short keeps the earlier overlay whole
        paths.atomic_write_bytes(png, data.tobytes())
    except OSError as e:
        raise AlignmentError(f"cannot write {png}: {e}") from None
    result = {"image_a": image_a_path, "image_b": image_b_path,
              "image_a_size": list(image_a.size), "image_b_size": list(image_b.size),
              "model": estimator.source, "kind": estimator.kind,
              "num_stages": estimator.num_stages,
              **_estimate_json(estimate, image_b.gray.shape, quad), "overlay_png": png,
              "input_paths": inputs}
    atomic_write_json(os.path.join(output_dir, f"{stem}_homography.json"), result,
                      sort_keys=False)
    return result
