"""User-facing inference: :class:`HomographyEstimator` for patches and for whole images.

Convention (see :mod:`stnh_tf.geometry`): every homography returned here is ``H_ba``
(``a_from_b``), mapping **b** pixel coordinates ``(x, y)`` to **a** pixel coordinates,
``p_a ~ H_ba @ p_b``, scaled so that ``H[2, 2] = 1``; pixel centres sit at integer coordinates as
in OpenCV. Warping a by ``H_ba`` (``cv2.warpPerspective(a, H_ba, size_b, flags=WARP_INVERSE_MAP)``)
brings it onto b.

Model kinds (all loaded with :meth:`HomographyEstimator.load`):

* **single**: one STN-Homography stage saved as ``.keras`` (also a training run directory holding
  ``model.keras``, or the HomographyNet baseline, which has the same ``h_bar`` output).
* **sequence**: an end-to-end sequence model (outputs ``h_bar_1 .. h_bar_n``); its last
  ``h_bar_n`` is the estimate.
* **hierarchy**: several independently trained models run one after another (paper section 4).
  Stage k sees ``patch_a_k(p) = patch_a(H_1 @ ... @ H_{k-1} @ p)``, produced with an OpenCV
  bilinear warp, and the estimate is ``H_1 @ H_2 @ ... @ H_n``.

Hierarchy manifest (a JSON file; by convention ``hierarchy.json``)::

    {
      "format": "stnh_tf.hierarchy",
      "version": 1,
      "stages": ["stage1/model.keras", "stage2", "stage3.keras"],
      "description": "optional free text"
    }

``stages`` lists the stage models in order: each a ``.keras`` file or a training run directory
holding ``model.keras``, given relative to the manifest's folder and inside it (absolute paths
and ``../`` are refused, so a manifest cannot make the loader read models from elsewhere). Each stage may be a
single-stage or a sequence model. :func:`write_manifest` writes one. :meth:`HomographyEstimator.load`
accepts

* a ``.keras`` file;
* a ``.json`` manifest;
* a directory holding ``model.keras`` (a training run: single or sequence model);
* a directory holding ``hierarchy.json`` (the manifest);
* a directory holding stage models named ``stage1``, ``stage2``, ... (sub-directories holding
  ``model.keras``, or files ``stage1.keras``, ...), taken as a hierarchy in numeric order;
* nothing: the shipped default in the package folder ``stnh_tf/weights/``: ``default.json`` (a
  manifest) if present, else ``default.keras``.

Context in the hierarchy. The paper warps the whole image_a between stages and crops patch_a_k
from it, so pixels that the warp brings into the patch come from real image content.
:meth:`HomographyEstimator.estimate` only receives 128 x 128 patches, so it warps **the patch
itself** and fills everything outside it with zeros (the same as the sequence model's internal
warp); :meth:`HomographyEstimator.estimate_images` has the whole image and uses it as context,
as the paper does.

Degenerate predictions. As in evaluation and stage-data generation
(:func:`stnh_tf.hierarchy.accept_or_reject`), a stage whose prediction makes the composed
estimate non-finite or singular (``|det| < 1e-6``, or a patch corner mapped to ``w <= 0``) is
skipped: the estimate so far is kept (the identity if it is the first stage), a warning is logged,
and :attr:`HomographyEstimator.last_rejected` counts the skipped predictions of the last call by
reason. (The context bound of the hierarchy does not apply: there is no stored context to leave.)

Resizing rule of :meth:`HomographyEstimator.estimate_images`. The models were trained on 128 x 128
crops of 320 x 240 images with corners moved by up to 32 px. Each image (any size, any aspect
ratio; image_a and image_b need not have the same size) is converted to grayscale (ITU-R 601
luma; an alpha channel is composited onto black), resized to 320 x 240 (aspect ratio not
preserved; ``cv2.INTER_AREA`` when both sides shrink, else ``cv2.INTER_LINEAR``: the training
data's rule), and the central 128 x 128 square (top-left corner ``(96, 56)``) of each is the patch pair. The patch
estimate is mapped back with ``H_img = inv(S_a) @ T @ H_patch @ inv(T) @ S_b`` where ``T`` is the
translation by ``(96, 56)`` and ``S_x`` maps pixels of image x to pixels of its 320 x 240 version.
With pixel centres at integer coordinates a resize by ``s`` maps ``x -> s (x + 0.5) - 0.5``
(exactly what ``cv2.resize`` does), so ``S_x`` has that half-pixel offset. The result is
meaningful when, in the 320 x 240 frame, the motion between the images is of the size the model
was trained on (corners of the central square moving by up to about 32 px, i.e. 10% of the
width) and the central square holds texture.
"""

from __future__ import annotations

import json
import logging
import os
import re

import cv2
import numpy as np

from stnh_tf import geometry, pixels

PATCH_SIZE = geometry.PATCH_SIZE
WORK_SIZE = (geometry.IMAGE_WIDTH, geometry.IMAGE_HEIGHT)
"""``(width, height)`` every image is resized to by :meth:`HomographyEstimator.estimate_images`."""
PATCH_ORIGIN = ((WORK_SIZE[0] - PATCH_SIZE) // 2, (WORK_SIZE[1] - PATCH_SIZE) // 2)
"""Top-left corner ``(x0, y0) = (96, 56)`` of the central patch in the 320 x 240 frame."""

MANIFEST_FORMAT = "stnh_tf.hierarchy"
MANIFEST_VERSION = 1
MANIFEST_FILE = "hierarchy.json"
MODEL_FILE = "model.keras"
DEFAULT_MANIFEST = "default.json"
DEFAULT_MODEL = "default.keras"
KINDS = ("single", "sequence", "hierarchy")

IMPLAUSIBLE_CORNER_SHIFT = 1.5 * geometry.MAX_PERTURBATION
"""Corner displacement (px, 128 x 128 patch frame) beyond which an estimate is flagged as
implausible: the models were trained on corners moved by up to 32 px."""

_log = logging.getLogger(__name__)


def corner_shift(a_from_b) -> np.ndarray:
    """Largest displacement ``|H c - c|`` (px) of the four patch corners ``c`` under each
    ``a_from_b`` ``[B, 3, 3]`` (patch frame); ``inf`` where a corner maps to infinity or NaN.
    Returns float64 ``[B]``."""
    corners = geometry.patch_corners(PATCH_SIZE)
    with np.errstate(all="ignore"):
        moved = geometry.warp_points(np.asarray(a_from_b, np.float64), corners)
        shift = np.linalg.norm(moved - corners, axis=-1).max(axis=-1)
    return np.where(np.isfinite(shift), shift, np.inf)


# --------------------------------------------------------------------------------------------
# Frames
# --------------------------------------------------------------------------------------------
def resize_matrix(src_size, dst_size) -> np.ndarray:
    """``[3, 3]`` float64 map from pixels of an image of ``src_size = (w, h)`` to pixels of its
    resized version of ``dst_size = (w', h')`` (``cv2.resize`` geometry, pixel centres at integer
    coordinates): ``x' = s_x (x + 0.5) - 0.5`` with ``s_x = w' / w`` (same for y)."""
    sx, sy = dst_size[0] / src_size[0], dst_size[1] / src_size[1]
    return np.array([[sx, 0.0, 0.5 * sx - 0.5],
                     [0.0, sy, 0.5 * sy - 0.5],
                     [0.0, 0.0, 1.0]], dtype=np.float64)


def default_weights_dir() -> str:
    """The package folder ``stnh_tf/weights`` (may not exist before weights are shipped)."""
    return os.path.join(os.path.dirname(os.path.abspath(__file__)), "weights")


# --------------------------------------------------------------------------------------------
# Manifests
# --------------------------------------------------------------------------------------------
def write_manifest(path, stages, description: str = "") -> str:
    """Write a hierarchy manifest to ``path`` naming ``stages`` (model files or run directories).

    Every stage must lie in the manifest's folder or below it (:func:`read_manifest` reads no
    other); it is stored relative to the folder, so the folder can be moved. Returns ``path``.

    Raises:
      ValueError: no stage, or a stage outside the manifest's folder.
    """
    folder = os.path.dirname(os.path.abspath(path))
    entries = []
    for stage in stages:
        full = os.path.abspath(os.fspath(stage))
        rel = os.path.relpath(full, folder)
        if rel == os.pardir or rel.startswith(os.pardir + os.sep):
            raise ValueError(f"stage {full} is outside the manifest's folder {folder}: a manifest "
                             "names stages beside it or below it; write it next to the stages, "
                             "or copy the stage models into its folder.")
        entries.append(rel.replace(os.sep, "/"))
    if not entries:
        raise ValueError("a hierarchy manifest needs at least one stage; received none.")
    doc = {"format": MANIFEST_FORMAT, "version": MANIFEST_VERSION, "stages": entries}
    if description:
        doc["description"] = description
    with open(path, "w") as f:
        json.dump(doc, f, indent=2)
        f.write("\n")
    return os.fspath(path)


def read_manifest(path) -> list:
    """The stage model paths (absolute, in order) named by the hierarchy manifest at ``path``.

    Every stage must be a relative path inside the manifest's folder (beside it or below it);
    absolute paths and ``../`` escapes raise ``ValueError`` (:func:`stnh_tf.paths.inside`)."""
    from stnh_tf.paths import inside, read_json

    path = os.fspath(path)
    doc = read_json(path, "hierarchy manifest")
    if not isinstance(doc, dict) or doc.get("format") != MANIFEST_FORMAT:
        raise ValueError(f"{path} is not a hierarchy manifest: expected a JSON object with "
                         f"\"format\": \"{MANIFEST_FORMAT}\"; received {str(doc)[:200]}.")
    if doc.get("version") != MANIFEST_VERSION:
        raise ValueError(f"hierarchy manifest {path} has version {doc.get('version')!r}; this "
                         f"version of stnh_tf reads version {MANIFEST_VERSION}.")
    stages = doc.get("stages")
    if not isinstance(stages, list) or not stages or not all(isinstance(s, str) and s for s in stages):
        raise ValueError(f"hierarchy manifest {path}: \"stages\" must be a non-empty list of paths; "
                         f"received {stages!r}.")
    folder = os.path.dirname(os.path.abspath(path))
    return [inside(folder, s, f"hierarchy manifest {path}, stage {k}")
            for k, s in enumerate(stages, start=1)]


def _numbered_stages(directory):
    """``stage1``, ``stage2``, ... (directories or ``.keras`` files) in ``directory``, in order."""
    found = {}
    for name in os.listdir(directory):
        m = re.fullmatch(r"stage(\d+)(\.keras)?", name)
        if m:
            found.setdefault(int(m.group(1)), os.path.join(directory, name))
    return [found[k] for k in sorted(found)]


def _default_source() -> str:
    """The shipped weights' manifest (or single model) that ``load()`` reads."""
    folder = default_weights_dir()
    manifest = os.path.join(folder, DEFAULT_MANIFEST)
    return manifest if os.path.isfile(manifest) else os.path.join(folder, DEFAULT_MODEL)


def resolve_model_paths(path=None) -> list:
    """The stage model paths that :meth:`HomographyEstimator.load` would load (see the module
    docstring for the accepted layouts). Raises ``FileNotFoundError`` with the places looked at."""
    if path is None:
        folder = default_weights_dir()
        manifest, model = os.path.join(folder, DEFAULT_MANIFEST), os.path.join(folder, DEFAULT_MODEL)
        if os.path.isfile(manifest):
            return read_manifest(manifest)
        if os.path.isfile(model):
            return [model]
        raise FileNotFoundError(
            f"no shipped weights: this copy of stnh_tf has neither {manifest} nor {model}. Pass "
            "the path of a trained model (.keras file, run directory or hierarchy manifest) instead.")
    path = os.fspath(path)
    if os.path.isdir(path):
        for candidate in (MODEL_FILE, MANIFEST_FILE):
            if os.path.isfile(os.path.join(path, candidate)):
                break
        else:
            stages = _numbered_stages(path)
            if stages:
                return stages
            raise FileNotFoundError(
                f"{path} holds no model: expected {MODEL_FILE}, {MANIFEST_FILE} or stage1, "
                "stage2, ... models.")
        path = os.path.join(path, candidate)
    if not os.path.exists(path):
        raise FileNotFoundError(f"no model at {path}.")
    if path.endswith(".json"):
        return read_manifest(path)
    return [path]


# --------------------------------------------------------------------------------------------
# Input checking
# --------------------------------------------------------------------------------------------
def _to_unit_float(x, name, what):
    """uint8 (0..255) or float in [0, 1] -> float32 in [0, 1]."""
    if x.dtype == np.uint8:
        return pixels.to_unit(x)
    if np.issubdtype(x.dtype, np.floating):
        finite = np.isfinite(x)
        if not np.all(finite) or x.min() < 0.0 or x.max() > 1.0:
            seen = (f"values in [{x[finite].min()}, {x[finite].max()}]" if finite.any() else
                    "no finite values")
            if not finite.all():
                seen += f" and {int(x.size - finite.sum())} NaN/inf"
            raise ValueError(f"{name}: floating-point {what} must lie in [0, 1] (use uint8 for "
                             f"0..255); received {seen} with shape {x.shape}.")
        return x.astype(np.float32)
    raise ValueError(f"{name}: {what} must be uint8 (0..255) or floating point in [0, 1]; "
                     f"received dtype {x.dtype} with shape {x.shape}.")


def _as_array(x, name):
    if x is None:
        raise ValueError(f"{name} is None; expected an image array.")
    try:
        arr = np.asarray(x)
    except Exception as e:  # ragged nested lists and the like
        raise ValueError(f"{name} is not an array ({type(x).__name__}): {e}") from None
    if arr.dtype == object or arr.dtype.kind in "USV":
        raise ValueError(f"{name} is not a numeric image array; received dtype {arr.dtype} with "
                         f"shape {arr.shape}.")
    return arr


def prepare_patches(x, name="patch") -> np.ndarray:
    """Patches ``[S, S]``, ``[S, S, 1]``, ``[B, S, S]`` or ``[B, S, S, 1]`` (S = 128; uint8 0..255
    or float in [0, 1]) -> float32 ``[B, S, S, 1]`` in [0, 1]. Anything else raises ``ValueError``."""
    s = PATCH_SIZE
    arr = _as_array(x, name)
    shape = tuple(arr.shape)
    if len(shape) == 2:
        core = shape
        batch = (1,) + shape
    elif len(shape) == 3 and shape[:2] == (s, s) and shape[2] in (1, 3, 4):
        if shape[2] != 1:
            raise ValueError(f"{name} must be grayscale ([{s}, {s}] or [{s}, {s}, 1]); received "
                             f"shape {shape} (convert colour images to gray first).")
        core = shape[:2]
        batch = (1,) + core
    elif len(shape) == 3:
        core = shape[1:]
        batch = shape
    elif len(shape) == 4 and shape[-1] == 1:
        core = shape[1:3]
        batch = shape[:3]
    else:
        raise ValueError(f"{name} must have shape [{s}, {s}], [{s}, {s}, 1], [B, {s}, {s}] or "
                         f"[B, {s}, {s}, 1]; received shape {shape}.")
    if core != (s, s):
        raise ValueError(f"{name} must be {s}x{s} patches ([{s}, {s}], [{s}, {s}, 1], [B, {s}, {s}] "
                         f"or [B, {s}, {s}, 1]); received shape {shape}.")
    if batch[0] == 0:
        raise ValueError(f"{name} is an empty batch; received shape {shape}.")
    return _to_unit_float(arr, name, "patches").reshape(batch + (1,))


def prepare_image(x, name="image", channel_order: str = "rgb") -> np.ndarray:
    """One image ``[H, W]`` or ``[H, W, C]`` (C = 1, 3 or 4; uint8 or float in [0, 1]) ->
    grayscale float32 ``[H, W]`` in [0, 1]. Colour is ``channel_order`` ("rgb" as NumPy/scikit-image
    read it, "bgr" as OpenCV does)."""
    if channel_order not in ("rgb", "bgr"):
        raise ValueError(f"channel_order must be 'rgb' or 'bgr'; received {channel_order!r}.")
    arr = _as_array(x, name)
    shape = tuple(arr.shape)
    if not (len(shape) == 2 or (len(shape) == 3 and shape[2] in (1, 3, 4))):
        raise ValueError(f"{name} must be one image [H, W] or [H, W, C] with C in (1, 3, 4); "
                         f"received shape {shape}.")
    if shape[0] == 0 or shape[1] == 0:
        raise ValueError(f"{name} is empty; received shape {shape}.")
    img = _to_unit_float(arr, name, "images")
    if img.ndim == 3:
        alpha = img[..., 3] if img.shape[2] == 4 else None
        if img.shape[2] == 1:
            img = img[..., 0]
        else:
            code = cv2.COLOR_RGB2GRAY if channel_order == "rgb" else cv2.COLOR_BGR2GRAY
            img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), code)
        if alpha is not None:
            img = img * alpha  # composited onto black, as the training data does
    return np.ascontiguousarray(img, dtype=np.float32)


def resize_to_work_size(gray: np.ndarray) -> np.ndarray:
    """Grayscale ``[h, w]`` -> ``[240, 320]`` as the training data was made (``cv2.INTER_AREA``
    when both sides shrink, else ``cv2.INTER_LINEAR``; both keep the geometry of
    :func:`resize_matrix`)."""
    h, w = gray.shape[:2]
    if (w, h) == WORK_SIZE:
        return np.ascontiguousarray(gray)
    interp = cv2.INTER_AREA if (w >= WORK_SIZE[0] and h >= WORK_SIZE[1]) else cv2.INTER_LINEAR
    return cv2.resize(gray, WORK_SIZE, interpolation=interp)


def warp_patch(source, a_from_b, origin=(0, 0), size: int = PATCH_SIZE) -> np.ndarray:
    """The hierarchy's inter-stage warp, :func:`stnh_tf.hierarchy.warp_crop` (``source``
    float32 ``[h, w]`` holding the patch at ``origin``; ``a_from_b`` ``[3, 3]`` patch frame)."""
    from stnh_tf import hierarchy

    return hierarchy.warp_crop(source, a_from_b, origin, size)


# --------------------------------------------------------------------------------------------
# The estimator
# --------------------------------------------------------------------------------------------
def _output_names(model):
    names = getattr(model, "output_names", None)
    return list(names) if names else []


def _check_model(model, where):
    from stnh_tf.runner import final_h_bar_name

    inputs = getattr(model, "inputs", None) or []
    names = {getattr(t, "name", "").split(":")[0] for t in inputs}
    shapes = {getattr(t, "name", "").split(":")[0]: tuple(t.shape) for t in inputs}
    want = (None, PATCH_SIZE, PATCH_SIZE, 1)
    if not {"patch_a", "patch_b"} <= names or any(shapes[n] != want for n in ("patch_a", "patch_b")):
        raise ValueError(f"{where}: expected a model with inputs patch_a and patch_b of shape "
                         f"{list(want)}; received inputs {shapes}.")
    out = final_h_bar_name(model)
    if out not in _output_names(model):
        raise ValueError(f"{where}: expected a model with an 'h_bar' (or 'h_bar_k') output; "
                         f"received outputs {_output_names(model)}.")
    return out


class HomographyEstimator:
    """Estimates ``H_ba`` (b pixel -> a pixel) with one model or a hierarchy of models.

    Build it with :meth:`load` (from files) or directly from in-memory Keras models:
    ``HomographyEstimator([model])`` (single or sequence model) or
    ``HomographyEstimator([stage1, stage2, ...])`` (hierarchy).
    """

    def __init__(self, stages, source=None):
        if not isinstance(stages, (list, tuple)):
            stages = [stages]
        if not stages:
            raise ValueError("HomographyEstimator needs at least one model; received none.")
        self._stages = list(stages)
        self._outputs = [_check_model(m, f"stage {k}") for k, m in enumerate(self._stages, 1)]
        self._predictors = [None] * len(self._stages)
        self.source = source
        self.last_rejected = {"non_finite": 0, "singular": 0}
        """Stage predictions the last estimate skipped as degenerate, by reason."""
        self.last_info = None
        """Per pair of the last estimate (arrays of length B): ``implausible`` (bool: a stage
        was skipped as degenerate, or a patch corner moved more than
        :data:`IMPLAUSIBLE_CORNER_SHIFT` px, beyond what the models were trained on),
        ``max_corner_shift_px`` (largest corner displacement of the 128 x 128 patch estimate)
        and ``rejected_stages`` (stages skipped as degenerate)."""

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def load(cls, path=None, compute_dtype: str | None = "float32") -> "HomographyEstimator":
        """Load a single-stage or sequence ``.keras`` model, a training run directory, or a
        hierarchy (manifest or ``stage1, stage2, ...`` directory); ``None`` loads the shipped
        default from ``stnh_tf/weights/``. See the module docstring for the layouts.

        ``compute_dtype``: models trained in mixed precision (the shipped ones: mixed bfloat16)
        are rebuilt to compute in float32 by default, so an estimate does not depend on the batch
        size or on eager vs graph execution, and the exported SavedModel matches it (shipped
        3-stage hierarchy: largest difference of an ``H`` entry 2.3e-5 in float32, 0.39 in
        bfloat16); ``None`` keeps the policy they were saved with (faster on CPUs with bfloat16
        units; ``experiments.evaluate`` scores models so).

        Raises ``FileNotFoundError`` if nothing is found (also when no weights are shipped) and
        ``ValueError`` if a file is not a usable model.
        """
        from stnh_tf.runner import load_model

        paths = resolve_model_paths(path)
        models = []
        for p in paths:
            try:
                models.append(load_model(p, compute_dtype=compute_dtype))
            except (FileNotFoundError, ValueError):
                raise
            except Exception as e:  # a corrupt or foreign file
                raise ValueError(f"cannot load a Keras model from {p}: {type(e).__name__}: {e}") from None
        return cls(models, source=os.fspath(path) if path is not None else _default_source())

    # -- description --------------------------------------------------------------------------
    @property
    def stages(self) -> list:
        """The Keras models, in the order they run."""
        return list(self._stages)

    @property
    def output_names(self) -> list:
        """The output of each stage model that holds its final ``H_bar`` (``h_bar`` or ``h_bar_n``)."""
        return list(self._outputs)

    @property
    def num_stages(self) -> int:
        """Number of models run one after another (a sequence model counts as one)."""
        return len(self._stages)

    @property
    def kind(self) -> str:
        """``"hierarchy"`` (several models), ``"sequence"`` or ``"single"``."""
        if len(self._stages) > 1:
            return "hierarchy"
        return "sequence" if self._outputs[0].startswith("h_bar_") else "single"

    def __repr__(self):
        return (f"HomographyEstimator(kind={self.kind!r}, num_stages={self.num_stages}, "
                f"source={self.source!r})")

    # -- estimation ---------------------------------------------------------------------------
    def _predict_stage(self, k, patch_a, patch_b, batch_size):
        """Stage k's pixel ``H_ba`` ``[B, 3, 3]`` (float64) for float32 ``[B, S, S, 1]`` inputs,
        through the stage's compiled predictor (:func:`stnh_tf.runner.predictor`, built on
        first use and kept)."""
        from stnh_tf import runner

        if self._predictors[k] is None:
            self._predictors[k] = runner.predictor(self._stages[k], output=self._outputs[k])
        return self._predictors[k](patch_a, patch_b, batch_size)

    def _estimate(self, patch_a, patch_b, context=None, origin=(0, 0), batch_size=64):
        """Composed ``H_1 @ ... @ H_n`` ``[B, 3, 3]`` for float32 ``[B, S, S, 1]`` pairs.

        ``context``: optional list of float32 ``[h, w]`` images holding patch_a at ``origin``;
        later stages then crop their patch_a_k from the warped context, else from patch_a alone.
        """
        from stnh_tf import hierarchy

        total = np.broadcast_to(np.eye(3), (len(patch_a), 3, 3)).copy()
        current = patch_a
        rejected = {"non_finite": 0, "singular": 0}
        rejected_stages = np.zeros(len(patch_a), np.int64)
        for k in range(self.num_stages):
            if k:
                sources = context if context is not None else [np.ascontiguousarray(p[..., 0]) for p in patch_a]
                org = origin if context is not None else (0, 0)
                current = np.stack([warp_patch(src, h, org) for src, h in zip(sources, total)])[..., None]
            h_stage = self._predict_stage(k, current, patch_b, batch_size)
            # The hierarchy's degenerate-prediction rule without its context bound (there is no
            # stored context to leave): a non-finite or singular composition keeps the estimate
            # so far.
            total, reasons = hierarchy.accept_or_reject(total, h_stage, margin=np.inf)
            for i, reason in enumerate(reasons):
                if reason:
                    rejected[reason] += 1
                    rejected_stages[i] += 1
        self.last_rejected = rejected
        if any(rejected.values()):
            _log.warning("HomographyEstimator: stage predictions skipped as degenerate: %s",
                         rejected)
        shift = corner_shift(total)
        self.last_info = {"implausible": (rejected_stages > 0) | (shift > IMPLAUSIBLE_CORNER_SHIFT),
                          "max_corner_shift_px": shift, "rejected_stages": rejected_stages}
        return total

    def estimate(self, patch_a, patch_b, batch_size: int = 64) -> np.ndarray:
        """Pixel homography between 128 x 128 grayscale patches.

        Args:
          patch_a, patch_b: one pair (``[128, 128]`` or ``[128, 128, 1]``) or a batch
            (``[B, 128, 128]`` or ``[B, 128, 128, 1]``), uint8 (0..255) or float in [0, 1].
          batch_size: pairs per model call.
        Returns:
          float64 ``[B, 3, 3]`` ``H_ba``, mapping patch_b pixel coordinates to patch_a pixel
          coordinates (``[2, 2] = 1``; B = 1 for a single pair). In a hierarchy, later stages see
          patch_a warped by the earlier estimates with zeros outside the patch (no context).
        Raises:
          ValueError: wrong rank, size, channel count or dtype, empty or different-sized
            batches, ``batch_size`` < 1.
        """
        if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) \
                or batch_size < 1:
            raise ValueError(f"batch_size must be an integer >= 1; received {batch_size!r}.")
        a = prepare_patches(patch_a, "patch_a")
        b = prepare_patches(patch_b, "patch_b")
        if len(a) != len(b):
            raise ValueError(f"patch_a and patch_b must hold the same number of patches; received "
                             f"shapes {np.shape(patch_a)} and {np.shape(patch_b)}.")
        return self._estimate(a, b, batch_size=batch_size)

    def estimate_images(self, image_a, image_b, channel_order: str = "rgb") -> np.ndarray:
        """Homography between two images of any size and colour, in their own pixel frames.

        Each image is made grayscale and resized to 320 x 240; the central 128 x 128 squares are
        the patch pair; a hierarchy's later stages crop from the warped 320 x 240 image_a
        (context beyond the patch, as in the paper). See the module docstring for the rule.

        Args:
          image_a, image_b: ``[H, W]`` or ``[H, W, C]`` (C = 1, 3, 4), uint8 or float in [0, 1];
            the two may differ in size.
          channel_order: "rgb" (NumPy/scikit-image) or "bgr" (``cv2.imread``).
        Returns:
          float64 ``[3, 3]`` ``H_ba`` mapping image_b pixel coordinates to image_a pixel
          coordinates (``[2, 2] = 1``).
        """
        gray_a = prepare_image(image_a, "image_a", channel_order)
        gray_b = prepare_image(image_b, "image_b", channel_order)
        work_a, work_b = resize_to_work_size(gray_a), resize_to_work_size(gray_b)
        (x0, y0), s = PATCH_ORIGIN, PATCH_SIZE
        patch_a = np.ascontiguousarray(work_a[None, y0:y0 + s, x0:x0 + s, None])
        patch_b = np.ascontiguousarray(work_b[None, y0:y0 + s, x0:x0 + s, None])
        h_patch = self._estimate(patch_a, patch_b, context=[work_a], origin=PATCH_ORIGIN)[0]
        h_work = geometry.patch_to_image(h_patch, x0, y0)
        size_a = (gray_a.shape[1], gray_a.shape[0])
        size_b = (gray_b.shape[1], gray_b.shape[0])
        s_a, s_b = resize_matrix(size_a, WORK_SIZE), resize_matrix(size_b, WORK_SIZE)
        return geometry.scale_to_unit(np.linalg.inv(s_a) @ h_work @ s_b)
