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

Where the models are (hierarchy manifests, the accepted layouts, the shipped default in
``stnh_tf/weights/``): :mod:`stnh_tf.inference.model_files`. What the estimator accepts, and the resizing
rule of :meth:`HomographyEstimator.estimate_images`: :mod:`stnh_tf.inference.image_input`.

Context in the hierarchy. The paper warps the whole image_a between stages and crops patch_a_k
from it, so pixels that the warp brings into the patch come from real image content.
:meth:`HomographyEstimator.estimate` only receives 128 x 128 patches, so it warps **the patch
itself** and, by default, fills what lies outside it with the patch mirrored about its border
(``fill="reflect"``, a deviation: the stages were trained on real content there, which a mirror
image resembles more than the zeros of the sequence model's internal warp, ``fill="zeros"``);
:meth:`HomographyEstimator.estimate_images` has the whole image and uses it as context, as the
paper does.

Degenerate predictions. As in evaluation and stage-data generation
(:func:`stnh_tf.hierarchy.accept_or_reject`), a stage whose prediction makes the composed
estimate non-finite or singular (``|det| < 1e-6``, or a patch corner mapped to ``w <= 0``) is
skipped: the estimate so far is kept (the identity if it is the first stage), a warning is logged,
and :attr:`HomographyEstimator.last_rejected` counts the skipped predictions of the last call by
reason. (The context bound of the hierarchy does not apply: there is no stored context to leave.)

Refinement (opt-in, a deviation from the paper). ``refine="ecc"`` polishes the network's estimate
with OpenCV's ECC image alignment (:func:`ecc_refine`, ``cv2.findTransformECC``, invariant to gain
and offset), started from it; a refinement that fails to converge or moves the patch corners by
more than :data:`MAX_REFINE_MOVE` px on average is dropped for the network's estimate.

Test-time augmentation (opt-in, a deviation from the paper). ``tta="flips"`` or ``"dihedral"``
(:data:`TTAS`) also runs the stages on each pair mirrored and rotated
(:func:`stnh_tf.geometry.dihedral_image`), maps each estimate back to the pair's frame
(``inv(G) @ H' @ G``, :func:`stnh_tf.geometry.dihedral_matrix`) and keeps, per pair, the one with
the highest :func:`alignment_ncc`. ``retry_tta`` (opt-in) spends that augmentation on the pairs
whose estimate is flagged implausible (below) only: each is estimated again with
``tta=retry_tta`` and keeps that estimate.

Search of poorly aligned estimates (default, a deviation from the paper). ``search="ecc"``: where
an estimate aligns its pair poorly (:func:`alignment_ncc` below :data:`SEARCH_BELOW_NCC`) or is
flagged implausible, :func:`search_translations` scores translations of it by normalized
cross-correlation and starts coarse-to-fine ECC from each of the best; the best-aligned result at
:data:`VERIFIED_NCC` or better replaces the estimate, which is kept otherwise. It gives the same
result on OpenCV's optimized and unoptimized paths (the per-CPU kernels). ``search="none"``: the
network's estimate (what the exported SavedModel computes).

Implausible estimates. :attr:`HomographyEstimator.last_info` flags, per pair, an estimate that
moves a patch corner beyond the trained range, needed a skipped stage, or leaves patch_a warped
onto patch_b poorly correlated with it (:func:`alignment_ncc`): the images may not overlap, or
differ in ways the model was not trained on.
"""

from __future__ import annotations

import logging
import os

import cv2
import numpy as np

from stnh_tf import geometry
from stnh_tf.inference.image_input import (PATCH_ORIGIN, PATCH_SIZE, central_patch, patch_to_image_frames,
                                 prepare_image, prepare_patches, resize_to_work_size)
from stnh_tf.inference.model_files import default_source, resolve_model_paths

KINDS = ("single", "sequence", "hierarchy")

PATCH_FILL = "reflect"
"""How :meth:`HomographyEstimator.estimate` fills patch_a beyond the patch for a hierarchy's later
stages by default (:data:`stnh_tf.geometry.FILLS`); the exported SavedModel does the same."""

IMPLAUSIBLE_CORNER_SHIFT = 1.5 * geometry.MAX_PERTURBATION
"""Corner displacement (px, 128 x 128 patch frame) beyond which an estimate is flagged as
implausible: the models were trained on corners moved by up to 32 px."""

MIN_ALIGNMENT_NCC = 0.7
"""Normalized cross-correlation between patch_b and patch_a warped by the estimate below which the
estimate is flagged as implausible: it does not explain the pair (:func:`alignment_ncc`; how the
value was chosen: BENCHMARKS.md, "The alignment threshold re-chosen for the shipped default")."""

MIN_PATCH_STD = 0.5 / 255
"""Standard deviation of a patch's intensities (on the [0, 1] scale) below which it is flat: it
holds nothing to align (e.g. a dark patch an exposure change clipped to black), so the estimate of
its pair is the identity, flagged as implausible."""

MIN_OVERLAP = 0.25
"""Fraction of patch_b's pixels whose estimated position must lie inside patch_a's source for
:func:`alignment_ncc` to be defined."""

REFINES = ("none", "ecc")
"""What :meth:`HomographyEstimator.estimate` does after the network: ``"none"`` (the paper) or
``"ecc"`` (:func:`ecc_refine`)."""

TTAS = {"none": ("identity",),
        "flips": ("identity", "flip_x", "flip_y", "rotate_180"),
        "dihedral": tuple(geometry.DIHEDRAL)}
"""Test-time augmentation of :meth:`HomographyEstimator.estimate` by name (a deviation from the
paper): the symmetries (:data:`stnh_tf.geometry.DIHEDRAL`) the stages also run on; ``"none"``
(the paper) runs them once."""

MAX_REFINE_MOVE = 16.0
"""Mean corner distance (px, 128 x 128 patch frame) between the network's estimate and its ECC
refinement beyond which the refinement is taken to have diverged and is dropped."""

ECC_CRITERIA = (50, 1e-5)
"""``cv2.findTransformECC``'s iteration limit and convergence threshold in :func:`ecc_refine`."""

ECC_GAUSSIAN = 1
"""``cv2.findTransformECC``'s Gaussian pre-filter size in :func:`ecc_refine` (1: none)."""

SEARCHES = ("none", "ecc")
"""What :meth:`HomographyEstimator.estimate` does with a pair its estimate aligns poorly
(:data:`SEARCH_BELOW_NCC`): ``"ecc"`` tries :func:`search_translations`; ``"none"`` keeps the
network's estimate."""

SEARCH = "ecc"
"""The default of :meth:`HomographyEstimator.estimate`'s ``search`` (a deviation from the paper)."""

SEARCH_BELOW_NCC = 0.9
""":func:`alignment_ncc` of an estimate below which ``search="ecc"`` searches its pair (as it does
every pair flagged implausible); how the value was chosen: BENCHMARKS.md, "The search of poorly
aligned estimates"."""

VERIFIED_NCC = 0.95
""":func:`alignment_ncc` a result of :func:`search_translations` must reach to replace an
estimate."""

SEARCH_TEMPLATE = 64
"""Side (px) of patch_b's central square that :func:`search_translations` slides over the warped
patch_a: translations of up to ``(128 - 64) / 2 = 32`` px, the trained range, are scored."""

SEARCH_PEAKS = 8
"""Translation peaks :func:`search_translations` starts ECC from (all of them, best result kept)."""

SEARCH_COARSE_ITERATIONS = (100, 50)
"""Iteration limits of the float64 ECC on the 32 x 32 and 64 x 64 pyramid levels of
:func:`search_translations` (:func:`stnh_tf.inference.ecc.coarse_to_fine_ecc`)."""

SEARCH_ECC_ITERATIONS = 100
"""``cv2.findTransformECC``'s iteration limit at full resolution in :func:`search_translations`."""

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


def alignment_ncc(source_a, patch_b, a_from_b, origin=(0, 0)) -> float:
    """Normalized cross-correlation between ``patch_b`` and patch_a warped onto it by ``a_from_b``,
    over the pixels whose position ``a_from_b @ p`` lies inside ``source_a``.

    Args:
      source_a: ``[h, w]`` image holding patch_a with its top-left corner at ``origin`` (the patch
        itself with ``(0, 0)``, or the image it was cut from as context).
      patch_b: ``[S, S]`` (any real scale; NCC ignores gain and offset).
      a_from_b: ``[3, 3]`` pixel ``H_ba`` in the patch frame.
    Returns:
      NCC in [-1, 1]: 1 for a perfect alignment up to gain and offset, about 0 for unrelated
      content; NaN where fewer than :data:`MIN_OVERLAP` of the pixels overlap or either side is
      constant there.

    >>> p = np.random.default_rng(0).random((128, 128))
    >>> round(alignment_ncc(p, 2 * p + 1, np.eye(3)), 6)
    1.0
    """
    from stnh_tf import hierarchy

    size = np.shape(patch_b)[0]
    warped = hierarchy.warp_crop(source_a, a_from_b, origin, size).astype(np.float64)
    inside = hierarchy.warp_crop(np.ones(np.shape(source_a), np.float32), a_from_b, origin,
                                 size) > 0.999
    if inside.mean() < MIN_OVERLAP:
        return float("nan")
    x = warped[inside] - warped[inside].mean()
    y = np.asarray(patch_b, np.float64)[inside]
    y = y - y.mean()
    norm = np.sqrt((x * x).sum() * (y * y).sum())
    return float((x * y).sum() / norm) if norm > 1e-12 else float("nan")


def ecc_refine(source_a, patch_b, a_from_b, origin=(0, 0), iterations=None):
    """``a_from_b`` refined by OpenCV's ECC alignment (``cv2.findTransformECC``,
    ``MOTION_HOMOGRAPHY``, :data:`ECC_CRITERIA`, :data:`ECC_GAUSSIAN`), started from it: the
    homography maximising the correlation of ``patch_b`` and patch_a warped onto it, over the
    pixels that land inside ``source_a``.

    Args:
      source_a: ``[h, w]`` image holding patch_a with its top-left corner at ``origin`` (the patch
        itself with ``(0, 0)``, or the image it was cut from as context).
      patch_b: ``[S, S]`` (any real scale: ECC ignores gain and offset).
      a_from_b: ``[3, 3]`` pixel ``H_ba`` in the patch frame, the starting point.
      iterations: iteration limit (``None``: :data:`ECC_CRITERIA`'s).
    Returns:
      float64 ``[3, 3]`` refined ``H_ba`` in the patch frame (``[2, 2] = 1``), or ``None`` where
      ECC does not converge (OpenCV raises) or gives a non-finite matrix.

    >>> p = cv2.GaussianBlur(np.random.default_rng(0).random((128, 128), np.float32), (0, 0), 2)
    >>> b = cv2.warpPerspective(p, geometry.translation(1.5, -1.0), (128, 128),
    ...                         flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    >>> np.round(ecc_refine(p, b, np.eye(3))[:2, 2], 1)
    array([ 1.5, -1. ])
    """
    from stnh_tf.inference import ecc

    source_from_patch = geometry.translation(*origin)
    limit, eps = ECC_CRITERIA
    warp = ecc.opencv_ecc(source_a, patch_b, source_from_patch @ np.asarray(a_from_b, np.float64),
                          limit if iterations is None else iterations, eps, ECC_GAUSSIAN)
    return None if warp is None else geometry.scale_to_unit(np.linalg.inv(source_from_patch) @ warp)


def search_translations(source_a, patch_b, a_from_b, origin=(0, 0)):
    """A homography near ``a_from_b`` that aligns the pair almost perfectly, or ``None``.

    Patch_a is warped onto patch_b by ``a_from_b`` (mirror fill beyond ``source_a``), the central
    :data:`SEARCH_TEMPLATE` square of ``patch_b`` is slid over it (``cv2.matchTemplate``,
    ``TM_CCOEFF_NORMED``), and from the translations ``d`` at its :data:`SEARCH_PEAKS` highest
    local peaks coarse-to-fine ECC (:func:`stnh_tf.inference.ecc.coarse_to_fine_ecc`,
    :data:`SEARCH_COARSE_ITERATIONS`, :data:`SEARCH_ECC_ITERATIONS`) is started at
    ``a_from_b @ T(d)``. Of the results whose :func:`alignment_ncc` reaches :data:`VERIFIED_NCC`,
    the highest is returned (the better-ranked peak on a tie). It finds the estimate that a network
    put one period off on a repetitive texture (a brick wall), or a few px off under an exposure
    change; the same result on every CPU (BENCHMARKS.md, "Same answer on every machine").

    Args:
      source_a: ``[h, w]`` image holding patch_a with its top-left corner at ``origin`` (the patch
        itself with ``(0, 0)``, or the image it was cut from as context).
      patch_b: ``[S, S]`` (any real scale).
      a_from_b: ``[3, 3]`` pixel ``H_ba`` in the patch frame, the estimate searched around.
    Returns:
      ``(h, ncc)``: float64 ``[3, 3]`` ``H_ba`` in the patch frame (``[2, 2] = 1``) and its
      :func:`alignment_ncc`; ``None`` where no result reaches :data:`VERIFIED_NCC`.

    >>> p = cv2.GaussianBlur(np.random.default_rng(0).random((128, 128), np.float32), (0, 0), 2)
    >>> b = cv2.warpPerspective(p, geometry.translation(9.0, -6.0), (128, 128),
    ...                         flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    >>> h, ncc = search_translations(p, b, np.eye(3))
    >>> np.round(h[:2, 2], 1), ncc > 0.95
    (array([ 9., -6.]), True)
    """
    from stnh_tf import hierarchy
    from stnh_tf.inference import ecc

    size = np.shape(patch_b)[0]
    margin = (size - SEARCH_TEMPLATE) // 2
    b = np.asarray(patch_b, np.float32)
    warped = hierarchy.warp_crop(source_a, a_from_b, origin, size, fill="reflect")
    scores = cv2.matchTemplate(warped, b[margin:margin + SEARCH_TEMPLATE,
                                         margin:margin + SEARCH_TEMPLATE], cv2.TM_CCOEFF_NORMED)
    scores = np.nan_to_num(scores, nan=-1.0)
    ys, xs = np.nonzero(scores >= cv2.dilate(scores, np.ones((5, 5), np.uint8)))
    source_from_patch = geometry.translation(*origin)
    best = None
    for k in np.argsort(-scores[ys, xs], kind="stable")[:SEARCH_PEAKS]:
        start = np.asarray(a_from_b, np.float64) @ geometry.translation(xs[k] - margin,
                                                                         ys[k] - margin)
        h = ecc.coarse_to_fine_ecc(source_a, b, source_from_patch @ start,
                                   SEARCH_COARSE_ITERATIONS, SEARCH_ECC_ITERATIONS)
        if h is None:
            continue
        h = geometry.scale_to_unit(np.linalg.inv(source_from_patch) @ h)
        if not np.isfinite(corner_shift(h[None])[0]):
            continue
        ncc = alignment_ncc(source_a, b, h, origin)
        if ncc >= VERIFIED_NCC and (best is None or ncc > best[1]):
            best = (h, ncc)
    return best


def _beyond_rule(rejected_stages, shift, ncc, min_ncc):
    """Per pair ``[B]``: a stage was skipped, a corner moved beyond
    :data:`IMPLAUSIBLE_CORNER_SHIFT`, or the alignment NCC is below ``min_ncc`` or undefined (the
    implausibility rule with ``MIN_ALIGNMENT_NCC``, the search's trigger with
    ``SEARCH_BELOW_NCC``)."""
    return (rejected_stages > 0) | (shift > IMPLAUSIBLE_CORNER_SHIFT) | ~(ncc >= min_ncc)


def _nccs(sources, patches_b, a_from_b, origin):
    """:func:`alignment_ncc` of each pair ``[B]``, NaN (undefined) as ``-inf`` so that it ranks
    below every defined NCC."""
    return np.nan_to_num([alignment_ncc(src, b[..., 0], h, origin)
                          for src, b, h in zip(sources, patches_b, a_from_b)], nan=-np.inf)


# --------------------------------------------------------------------------------------------
# The estimator
# --------------------------------------------------------------------------------------------
def _output_names(model):
    names = getattr(model, "output_names", None)
    return list(names) if names else []


def _check_model(model, where):
    from stnh_tf.modeling.runner import final_h_bar_name

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
        was skipped as degenerate, a patch corner moved more than
        :data:`IMPLAUSIBLE_CORNER_SHIFT` px, beyond what the models were trained on, or the
        estimate does not explain the pair: ``alignment_ncc`` below :data:`MIN_ALIGNMENT_NCC` or
        undefined), ``max_corner_shift_px`` (largest corner displacement of the 128 x 128 patch
        estimate), ``rejected_stages`` (stages skipped as degenerate), ``gated_stages`` (later
        stages whose update ``estimate`` did not keep because it lowered the alignment; see its
        ``gate_stages``), ``alignment_ncc``
        (:func:`alignment_ncc` of patch_b and patch_a warped by the estimate, read from the
        image context in ``estimate_images``; NaN for a flat pair) and ``flat`` (patch_a or
        patch_b varies less than :data:`MIN_PATCH_STD`: the estimate is the identity and
        flagged implausible), ``searched`` (``search`` searched the pair: its estimate aligned
        it below :data:`SEARCH_BELOW_NCC` or was implausible), ``search_found`` (the estimate is
        :func:`search_translations`' result), ``refined`` (the estimate is the ECC refinement of
        ``refine="ecc"``; False where it was not asked for, failed or was dropped, or where the
        search replaced the estimate) and
        ``tta_choice`` (the name of the symmetry whose estimate was kept, ``"identity"`` without
        ``tta``; ``rejected_stages`` and ``gated_stages`` are that estimate's) and ``retried``
        (the pair was estimated again with ``retry_tta``; every other entry is then the
        retry's)."""

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def load(cls, path=None, compute_dtype: str | None = "float32") -> "HomographyEstimator":
        """Load a single-stage or sequence ``.keras`` model, a training run directory, or a
        hierarchy (manifest or ``stage1, stage2, ...`` directory); ``None`` loads the shipped
        default from ``stnh_tf/weights/``. See :mod:`stnh_tf.inference.model_files` for the layouts.

        ``compute_dtype``: models trained in mixed precision (the shipped ones: mixed bfloat16)
        are rebuilt to compute in float32 by default, so an estimate does not depend on the batch
        size or on eager vs graph execution, and the exported SavedModel matches it (see
        docs/estimate.md); ``None`` keeps the policy they were saved with (faster on CPUs with
        bfloat16 units; ``experiments.evaluate`` scores models so).

        Raises ``FileNotFoundError`` if nothing is found (also when no weights are shipped) and
        ``ValueError`` if a file is not a usable model.
        """
        from stnh_tf.modeling.runner import load_model

        paths = resolve_model_paths(path)
        models = []
        for p in paths:
            try:
                models.append(load_model(p, compute_dtype=compute_dtype))
            except (FileNotFoundError, ValueError):
                raise
            except Exception as e:  # a corrupt or foreign file
                raise ValueError(f"cannot load a Keras model from {p}: {type(e).__name__}: {e}") from None
        return cls(models, source=os.fspath(path) if path is not None else default_source())

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
        through the stage's compiled predictor (:func:`stnh_tf.modeling.runner.predictor`, built on
        first use and kept)."""
        from stnh_tf.modeling import runner

        if self._predictors[k] is None:
            self._predictors[k] = runner.predictor(self._stages[k], output=self._outputs[k])
        return self._predictors[k](patch_a, patch_b, batch_size)

    def _run_stages(self, patch_a, patch_b, sources, origin, batch_size, gate_stages, fill):
        """The stages on one set of pairs: ``(total, rejected, gated_stages, ncc_total)`` with
        ``rejected`` the per-pair count ``[B]`` of skipped predictions by reason and
        ``ncc_total`` the gate's alignment of ``total`` (``None`` where nothing was gated)."""
        from stnh_tf import hierarchy

        total = np.broadcast_to(np.eye(3), (len(patch_a), 3, 3)).copy()
        current = patch_a
        rejected = {"non_finite": np.zeros(len(patch_a), np.int64),
                    "singular": np.zeros(len(patch_a), np.int64)}
        gated_stages = np.zeros(len(patch_a), np.int64)
        ncc_total = None  # alignment of the estimate so far, while gating
        for k in range(self.num_stages):
            if k:
                current = np.stack([hierarchy.warp_crop(src, h, origin, PATCH_SIZE, fill)
                                    for src, h in zip(sources, total)])[..., None]
            h_stage = self._predict_stage(k, current, patch_b, batch_size)
            # The hierarchy's degenerate-prediction rule without its context bound (there is no
            # stored context to leave): a non-finite or singular composition keeps the estimate
            # so far.
            proposed, reasons = hierarchy.accept_or_reject(total, h_stage, margin=np.inf)
            for i, reason in enumerate(reasons):
                if reason:
                    rejected[reason][i] += 1
            if gate_stages and k:
                ncc_proposed = _nccs(sources, patch_b, proposed, origin)
                lowered = ncc_proposed < ncc_total
                gated_stages += lowered
                total = np.where(lowered[:, None, None], total, proposed)
                ncc_total = np.where(lowered, ncc_total, ncc_proposed)
            else:
                total = proposed
            if gate_stages and k == 0 and self.num_stages > 1:
                ncc_total = _nccs(sources, patch_b, total, origin)
        return total, rejected, gated_stages, ncc_total

    def _estimate(self, patch_a, patch_b, context=None, origin=(0, 0), batch_size=64,
                  gate_stages=False, fill="zeros", refine="none", tta="none", retry_tta="none",
                  search=SEARCH):
        """Composed ``H_1 @ ... @ H_n`` ``[B, 3, 3]`` for float32 ``[B, S, S, 1]`` pairs
        (:meth:`_estimate_once`); where that estimate is flagged implausible (and the pair is not
        flat), the pair is estimated again with ``tta=retry_tta`` and keeps that estimate, if
        ``retry_tta`` runs more symmetries than ``tta``. Sets :attr:`last_info` (with
        ``retried``) and :attr:`last_rejected`."""
        if not isinstance(retry_tta, str) or retry_tta not in TTAS:
            raise ValueError(f"retry_tta must be one of {tuple(TTAS)}; received {retry_tta!r}.")
        total, info, rejected = self._estimate_once(patch_a, patch_b, context, origin, batch_size,
                                                    gate_stages, fill, refine, tta, search)
        info["retried"] = np.zeros(len(total), bool)
        retry = (np.flatnonzero(info["implausible"] & ~info["flat"])
                 if set(TTAS[retry_tta]) > set(TTAS[tta]) else [])
        if len(retry):
            r_total, r_info, r_rejected = self._estimate_once(
                patch_a[retry], patch_b[retry],
                None if context is None else [context[i] for i in retry], origin, batch_size,
                gate_stages, fill, refine, retry_tta, search)
            r_info["retried"] = np.ones(len(retry), bool)
            total[retry] = r_total
            for key, value in r_info.items():  # (result_type: tta_choice names may be longer)
                info[key] = info[key].astype(np.result_type(info[key], value))
                info[key][retry] = value
            for reason, counts in r_rejected.items():
                rejected[reason][retry] = counts
        self.last_info = info
        self.last_rejected = {reason: int(counts.sum()) for reason, counts in rejected.items()}
        if any(self.last_rejected.values()):
            _log.warning("HomographyEstimator: stage predictions skipped as degenerate: %s",
                         self.last_rejected)
        return total

    def _estimate_once(self, patch_a, patch_b, context, origin, batch_size, gate_stages, fill,
                       refine, tta, search):
        """Composed ``H_1 @ ... @ H_n`` ``[B, 3, 3]`` for float32 ``[B, S, S, 1]`` pairs, with
        the per-pair :attr:`last_info` entries (but ``retried``) and the per-pair counts ``[B]``
        of skipped stage predictions by reason: ``(total, info, rejected)``.

        ``context``: optional list of float32 ``[h, w]`` images holding patch_a at ``origin``;
        later stages then crop their patch_a_k from the warped context, else from patch_a alone.
        ``fill``: what later stages see beyond the source (:func:`stnh_tf.hierarchy.warp_crop`).
        ``gate_stages``: keep a later stage's update of a pair only where it does not lower
        :func:`alignment_ncc` (an undefined NCC counts as the lowest).
        ``search``: one of :data:`SEARCHES`: ``"ecc"`` replaces the estimate of a pair it aligns
        poorly (below :data:`SEARCH_BELOW_NCC`, or implausible; not flat) by
        :func:`search_translations`' result where there is one.
        ``refine``: one of :data:`REFINES`, applied to the final estimate.
        ``tta``: a key of :data:`TTAS`: the stages also run on the pairs (and contexts) transformed
        by each of its symmetries, and each pair keeps the estimate, mapped back, whose
        :func:`alignment_ncc` is highest (the first listed on a tie).
        """
        if refine not in REFINES:
            raise ValueError(f"refine must be one of {REFINES}; received {refine!r}.")
        if search not in SEARCHES:
            raise ValueError(f"search must be one of {SEARCHES}; received {search!r}.")
        if not isinstance(tta, str) or tta not in TTAS:
            raise ValueError(f"tta must be one of {tuple(TTAS)}; received {tta!r}.")
        sources = (context if context is not None
                   else [np.ascontiguousarray(p[..., 0]) for p in patch_a])
        org = origin if context is not None else (0, 0)
        if len(TTAS[tta]) > 1 and len({np.shape(src) for src in sources}) > 1:
            raise ValueError("tta needs contexts of one size.")
        chosen = None
        for j, name in enumerate(TTAS[tta]):
            # Pixel p of the patch (source) lands at g_patch @ p (g_source @ p) once transformed.
            g_patch = geometry.dihedral_matrix(name, PATCH_SIZE, PATCH_SIZE)
            t_sources = [np.ascontiguousarray(geometry.dihedral_image(src, name))
                         for src in sources]
            g_source = geometry.dihedral_matrix(name, sources[0].shape[1], sources[0].shape[0])
            t_org = (g_source @ [org[0], org[1], 1.0] - g_patch @ [0.0, 0.0, 1.0])[:2]
            t_total, t_rejected, t_gated, t_ncc = self._run_stages(
                np.ascontiguousarray(geometry.dihedral_image(patch_a, name, axes=(1, 2))),
                np.ascontiguousarray(geometry.dihedral_image(patch_b, name, axes=(1, 2))),
                t_sources, tuple(t_org), batch_size, gate_stages, fill)
            run = {"total": geometry.scale_to_unit(np.linalg.inv(g_patch) @ t_total @ g_patch),
                   "gated": t_gated, "choice": np.full(len(patch_a), j), **{
                       f"rejected_{r}": v for r, v in t_rejected.items()}}
            if len(TTAS[tta]) == 1:
                run["ncc"] = t_ncc
            else:  # the same alignment as measured in the transformed frame (NaN ranks lowest)
                run["ncc"] = _nccs(sources, patch_b, run["total"], org)
            if chosen is None:
                chosen = run
            else:
                better = run["ncc"] > chosen["ncc"]
                chosen = {key: np.where(better.reshape((-1,) + (1,) * (value.ndim - 1)),
                                        value, chosen[key]) for key, value in run.items()}
        total, gated_stages, ncc_total = chosen["total"], chosen["gated"], chosen["ncc"]
        rejected = {r: chosen[f"rejected_{r}"] for r in ("non_finite", "singular")}
        rejected_stages = chosen["rejected_non_finite"] + chosen["rejected_singular"]
        flat = ((patch_a.std(axis=(1, 2, 3)) < MIN_PATCH_STD)
                | (patch_b.std(axis=(1, 2, 3)) < MIN_PATCH_STD))
        if flat.any():
            _log.warning("HomographyEstimator: %d pair(s) with a flat patch (nothing to align): "
                         "estimate set to the identity", int(flat.sum()))
            total[flat] = np.eye(3)
        shift = corner_shift(total)
        if ncc_total is not None:  # the gate already measured the estimate's alignment
            ncc = np.where(np.isfinite(ncc_total) & np.isfinite(shift) & ~flat, ncc_total, np.nan)
        else:
            ncc = np.array([alignment_ncc(src, b[..., 0], h, org) if np.isfinite(s) and not f
                            else np.nan
                            for src, b, h, s, f in zip(sources, patch_b, total, shift, flat)])
        searched, found = np.zeros(len(total), bool), np.zeros(len(total), bool)
        if search == "ecc":
            searched = (~flat & np.isfinite(shift)
                        & _beyond_rule(rejected_stages, shift, ncc, SEARCH_BELOW_NCC))
            for i in np.flatnonzero(searched):
                result = search_translations(sources[i], patch_b[i, ..., 0], total[i], org)
                if result is not None:
                    (total[i], ncc[i]), found[i] = result, True
        refined = np.zeros(len(total), bool)
        if refine == "ecc":  # (a found estimate is an ECC optimum already)
            for i in np.flatnonzero(~flat & ~found & np.isfinite(total).all(axis=(1, 2))):
                h = ecc_refine(sources[i], patch_b[i, ..., 0], total[i], org)
                if h is not None and float(geometry.corner_errors(
                        h[None], total[i][None])[0]) <= MAX_REFINE_MOVE:
                    total[i], refined[i] = h, True
                    ncc[i] = alignment_ncc(sources[i], patch_b[i, ..., 0], h, org)
        shift = corner_shift(total)
        ncc = np.where(np.isfinite(shift) & ~flat, ncc, np.nan)
        info = {"implausible": _beyond_rule(rejected_stages, shift, ncc, MIN_ALIGNMENT_NCC) | flat,
                "max_corner_shift_px": shift, "rejected_stages": rejected_stages,
                "gated_stages": gated_stages, "alignment_ncc": ncc, "flat": flat,
                "searched": searched, "search_found": found,
                "refined": refined, "tta_choice": np.array(TTAS[tta])[chosen["choice"]]}
        return total, info, rejected

    def estimate(self, patch_a, patch_b, batch_size: int = 64,
                 gate_stages: bool = True, fill: str = PATCH_FILL,
                 refine: str = "none", tta: str = "none",
                 retry_tta: str = "none", search: str = SEARCH) -> np.ndarray:
        """Pixel homography between 128 x 128 grayscale patches.

        Args:
          patch_a, patch_b: one pair (``[128, 128]`` or ``[128, 128, 1]``) or a batch
            (``[B, 128, 128]`` or ``[B, 128, 128, 1]``), uint8 (0..255) or float in [0, 1].
          batch_size: pairs per model call.
          gate_stages: in a hierarchy, keep a later stage's update of a pair only where it does
            not lower the :func:`alignment_ncc` of patch_b and the warped patch_a (a deviation
            from the paper for bare patches: later stages are trained with image context and can
            misread what lies beyond the patch, see docs/estimate.md); ``False`` composes every
            stage.
          fill: in a hierarchy, what later stages see of patch_a beyond the patch once warped by
            the earlier estimates (there is no context): ``"reflect"`` (default, a deviation from
            the paper: the patch mirrored about its border) or ``"zeros"``
            (:data:`stnh_tf.geometry.FILLS`).
          refine: ``"none"`` (default) or ``"ecc"``: polish each estimate with OpenCV's ECC
            alignment started from it (:func:`ecc_refine`, a deviation from the paper; dropped
            where it fails or moves the corners by more than :data:`MAX_REFINE_MOVE` px;
            ``last_info["refined"]`` says where it was kept).
          tta: ``"none"`` (default, the paper), ``"flips"`` or ``"dihedral"``
            (:data:`TTAS`, a deviation from the paper): also estimate each pair mirrored (and
            rotated), map each estimate back, and keep the one that aligns the pair best
            (highest :func:`alignment_ncc`; ``last_info["tta_choice"]`` names it). Costs 4 or 8
            network passes per stage; ``refine`` then polishes the kept estimate.
          retry_tta: ``"none"`` (default) or a key of :data:`TTAS` with more symmetries than
            ``tta`` (a deviation from the paper): a pair whose estimate is flagged implausible
            (``last_info["implausible"]``, not a flat pair) is estimated again with
            ``tta=retry_tta`` and keeps that estimate and its flags (``last_info["retried"]``);
            the extra network passes are spent on the flagged pairs only. One with no more
            symmetries than ``tta`` does nothing.
          search: ``"ecc"`` (default, a deviation from the paper) or ``"none"``
            (:data:`SEARCHES`): a pair whose estimate aligns it poorly (:func:`alignment_ncc`
            below :data:`SEARCH_BELOW_NCC`) or is flagged implausible gets the result of
            :func:`search_translations` (ECC started from the best translations of the estimate)
            where one aligns it at :data:`VERIFIED_NCC` or better, and keeps the network's
            estimate elsewhere (``last_info["searched"]``, ``["search_found"]``). ``"none"``:
            the network's estimate only.
        Returns:
          float64 ``[B, 3, 3]`` ``H_ba``, mapping patch_b pixel coordinates to patch_a pixel
          coordinates (``[2, 2] = 1``; B = 1 for a single pair).
        Raises:
          ValueError: wrong rank, size, channel count or dtype, empty or different-sized
            batches, ``batch_size`` < 1, an unknown ``fill``, ``refine``, ``tta``,
            ``retry_tta`` or ``search``.
        """
        if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) \
                or batch_size < 1:
            raise ValueError(f"batch_size must be an integer >= 1; received {batch_size!r}.")
        fill = geometry.check_fill(fill)
        a = prepare_patches(patch_a, "patch_a")
        b = prepare_patches(patch_b, "patch_b")
        if len(a) != len(b):
            raise ValueError(f"patch_a and patch_b must hold the same number of patches; received "
                             f"shapes {np.shape(patch_a)} and {np.shape(patch_b)}.")
        return self._estimate(a, b, batch_size=batch_size, gate_stages=bool(gate_stages),
                              fill=fill, refine=refine, tta=tta, retry_tta=retry_tta,
                              search=search)

    def estimate_images(self, image_a, image_b, channel_order: str = "rgb",
                        refine: str = "none", tta: str = "none",
                        retry_tta: str = "none", search: str = SEARCH) -> np.ndarray:
        """Homography between two images of any size and colour, in their own pixel frames.

        Each image is made grayscale and resized to 320 x 240; the central 128 x 128 squares are
        the patch pair; a hierarchy's later stages crop from the warped 320 x 240 image_a
        (context beyond the patch, as in the paper). The rule: :mod:`stnh_tf.inference.image_input`.

        Args:
          image_a, image_b: ``[H, W]`` or ``[H, W, C]`` (C = 1, 3, 4), uint8 or float in [0, 1];
            the two may differ in size.
          channel_order: "rgb" (NumPy/scikit-image) or "bgr" (``cv2.imread``).
          refine: ``"none"`` (default) or ``"ecc"`` (as in :meth:`estimate`, aligning patch_b
            with the 320 x 240 image_a).
          tta: as in :meth:`estimate` (image_a mirrored and rotated with its patch).
          retry_tta: as in :meth:`estimate`.
          search: as in :meth:`estimate` (aligning patch_b with the 320 x 240 image_a).
        Returns:
          float64 ``[3, 3]`` ``H_ba`` mapping image_b pixel coordinates to image_a pixel
          coordinates (``[2, 2] = 1``).
        """
        gray_a = prepare_image(image_a, "image_a", channel_order)
        gray_b = prepare_image(image_b, "image_b", channel_order)
        work_a, work_b = resize_to_work_size(gray_a), resize_to_work_size(gray_b)
        h_patch = self._estimate(central_patch(work_a), central_patch(work_b), context=[work_a],
                                 origin=PATCH_ORIGIN, refine=refine, tta=tta,
                                 retry_tta=retry_tta, search=search)[0]
        return patch_to_image_frames(h_patch, (gray_a.shape[1], gray_a.shape[0]),
                                     (gray_b.shape[1], gray_b.shape[0]))
