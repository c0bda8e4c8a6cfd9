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

What the estimator does beyond the network is one value,
:class:`~stnh_tf.inference.options.EstimateOptions` (given to :meth:`HomographyEstimator.load`,
or to one call); the steps are in :mod:`stnh_tf.inference.pipeline`, and
``estimate_with_info`` returns their findings as an :class:`~stnh_tf.inference.pipeline.Estimate`.
Where the models are: :mod:`stnh_tf.inference.model_files`. What the estimator accepts, and the
resizing rule of :meth:`HomographyEstimator.estimate_images`: :mod:`stnh_tf.inference.image_input`.

Context in the hierarchy. The paper warps the whole image_a between stages and crops patch_a_k
from it. :meth:`HomographyEstimator.estimate` only receives 128 x 128 patches, so it warps **the
patch itself** and fills what lies outside it as ``options.fill`` says;
:meth:`HomographyEstimator.estimate_images` has the whole image and uses it as context, as the
paper does.

Degenerate predictions. As in evaluation and stage-data generation
(:func:`stnh_tf.hierarchy.accept_or_reject`), a stage whose prediction makes the composed
estimate non-finite or singular is skipped: the estimate so far is kept (the identity if it is the
first stage), a warning is logged, and the :class:`~stnh_tf.inference.pipeline.Estimate` counts
the skipped predictions by reason.

    >>> import numpy as np
    >>> from stnh_tf.inference import EstimateOptions, HomographyEstimator
    >>> estimator = HomographyEstimator.load()  # doctest: +SKIP
    >>> a = b = np.random.default_rng(0).integers(0, 255, (128, 128), np.uint8)
    >>> res = estimator.estimate_with_info(a, b, EstimateOptions.network_only())  # doctest: +SKIP
    >>> res.homography.shape, res.implausible.shape  # doctest: +SKIP
    ((1, 3, 3), (1,))
"""

from __future__ import annotations

import dataclasses
import logging
import os
import warnings

import numpy as np

from stnh_tf import geometry
from stnh_tf.inference import ambiguity, checks, coarse, features, image_refine, pipeline
# Public names of this module before the pipeline was split (stnh_tf.inference.<name>).
from stnh_tf.inference.checks import alignment_ncc, corner_shift  # noqa: F401
from stnh_tf.inference.image_input import (PATCH_ORIGIN, PATCH_SIZE, central_patch,  # noqa: F401
                                           check_patches, input_image, patch_to_image_frames,
                                           prepare_image, prepare_patches, resize_to_work_size,
                                           unit_patches, work_image)
from stnh_tf.inference.model_files import default_source, resolve_model_paths
from stnh_tf.inference.options import (REFINES, SEARCHES, TTAS, EstimateOptions,  # noqa: F401
                                       Thresholds)
from stnh_tf.inference.pipeline import Estimate
from stnh_tf.inference.search import ecc_refine, search_translations  # noqa: F401

KINDS = ("single", "sequence", "hierarchy")
"""What :attr:`HomographyEstimator.kind` can be."""

_LEGACY_OPTIONS = ("gate_stages", "fill", "refine", "tta", "retry_tta", "search")

CHUNK_PAIRS = 256
"""Pairs at a time through the pipeline (rounded up to a multiple of the batch size): memory
stays bounded however many pairs one call gets, and the result is the same as in one pass
(:func:`stnh_tf.inference.pipeline.estimate_in_chunks`)."""

_log = logging.getLogger(__name__)


def _output_names(model):
    names = getattr(model, "output_names", None)
    return list(names) if names else []


def _check_model(model, where):
    from stnh_tf.modeling.runner import final_h_bar_name

    inputs = getattr(model, "inputs", None) or []
    names = {getattr(t, "name", "").split(":")[0] for t in inputs}
    shapes = {getattr(t, "name", "").split(":")[0]: tuple(t.shape) for t in inputs}
    want = (None, PATCH_SIZE, PATCH_SIZE, 1)
    if not {"patch_a", "patch_b"} <= names or any(shapes[n] != want
                                                  for n in ("patch_a", "patch_b")):
        raise ValueError(f"{where}: expected a model with inputs patch_a and patch_b of shape "
                         f"{list(want)}; received inputs {shapes}.")
    out = final_h_bar_name(model)
    if out not in _output_names(model):
        raise ValueError(f"{where}: expected a model with an 'h_bar' (or 'h_bar_k') output; "
                         f"received outputs {_output_names(model)}.")
    try:  # issue 61: a foreign body behind the right names failed later with a TypeError
        structure = model.output
    except (AttributeError, ValueError):
        structure = None
    h_bar = structure.get(out) if isinstance(structure, dict) else None
    if h_bar is None or tuple(h_bar.shape) != (None, 8):
        shapes = [tuple(t.shape) for t in getattr(model, "outputs", None) or []]
        got = (f"output {out!r} of shape {tuple(h_bar.shape)}" if h_bar is not None else
               f"a list of unnamed outputs of shapes {shapes}"
               if isinstance(structure, (list, tuple)) else
               f"unnamed outputs of shapes {shapes}")
        raise ValueError(f"{where}: expected a model whose outputs are named, {out!r} of shape "
                         f"[None, 8] (H_bar, as this project's models give); received {got}.")
    return out


def _check_batch_size(batch_size):
    if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) \
            or batch_size < 1:
        raise ValueError(f"batch_size must be an integer >= 1; received {batch_size!r}.")


class HomographyEstimator:
    """Estimates ``H_ba`` (b pixel -> a pixel) with one model or a hierarchy of models.

    Build it with :meth:`load` (from files) or directly from in-memory Keras models:
    ``HomographyEstimator([model])`` (single or sequence model) or
    ``HomographyEstimator([stage1, stage2, ...])`` (hierarchy). ``options``
    (:class:`~stnh_tf.inference.options.EstimateOptions`) is what every call does unless it is
    given other options; without it, each method has its own default: ``EstimateOptions()`` for
    patches (``estimate``), :meth:`EstimateOptions.photographs
    <stnh_tf.inference.options.EstimateOptions.photographs>` for whole images
    (``estimate_images``), the attributes ``options`` and ``image_options``.
    """

    def __init__(self, stages, source=None, options: EstimateOptions | None = None):
        if not isinstance(stages, (list, tuple)):
            stages = [stages]
        if not stages:
            raise ValueError("HomographyEstimator needs at least one model; received none.")
        self._stages = list(stages)
        self._outputs = [_check_model(m, f"stage {k}") for k, m in enumerate(self._stages, 1)]
        self._predictors = [None] * len(self._stages)
        self.source = source
        self.options = self._check_options(options or EstimateOptions())
        self.image_options = self._check_options(options or EstimateOptions.photographs())
        self._last = None

    @staticmethod
    def _check_options(options):
        if not isinstance(options, EstimateOptions):
            raise TypeError(f"options must be an EstimateOptions; received {options!r} (the "
                            "batch size is the keyword batch_size=).")
        return options

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def load(cls, path=None, compute_dtype: str | None = "float32",
             options: EstimateOptions | None = None) -> "HomographyEstimator":
        """Load a single-stage or sequence ``.keras`` model, a training run directory, or a
        hierarchy (manifest or ``stage1, stage2, ...`` directory); ``None`` loads the shipped
        default from ``stnh_tf/weights/``. See :mod:`stnh_tf.inference.model_files` for the
        layouts. ``options``: what every call does by default (``None``: ``EstimateOptions()``
        on patches, ``EstimateOptions.photographs()`` on whole images).

        ``compute_dtype``: models trained in mixed precision (the shipped ones: mixed bfloat16)
        are rebuilt to compute in float32 by default, so an estimate depends on the batch size
        and on eager vs graph execution only by float32 rounding, and the exported SavedModel
        matches it (see docs/estimate.md, "Batch size"); ``None`` keeps the policy they were
        saved with (faster on CPUs with bfloat16 units; ``experiments.evaluate`` scores models
        so).

        Raises ``FileNotFoundError`` if nothing is found (also when no weights are shipped) and
        ``ValueError`` if a file is not a usable model.
        """
        from stnh_tf.modeling.runner import load_model

        models = []
        for p in resolve_model_paths(path):
            try:
                models.append(load_model(p, compute_dtype=compute_dtype))
            except FileNotFoundError:
                raise
            except Exception as e:  # a corrupt or foreign file (Keras' ValueError names none)
                if isinstance(e, ValueError) and os.fspath(p) in str(e):
                    raise
                raise ValueError(f"cannot load a Keras model from {p}: {type(e).__name__}: "
                                 f"{e}") from None
            _check_model(models[-1], p)  # naming the file
        return cls(models, source=os.fspath(path) if path is not None else default_source(),
                   options=options)

    # -- description --------------------------------------------------------------------------
    @property
    def stages(self) -> list:
        """The Keras models, in the order they run."""
        return list(self._stages)

    @property
    def output_names(self) -> list:
        """The output of each stage model that holds its final ``H_bar`` (``h_bar`` or
        ``h_bar_n``)."""
        return list(self._outputs)

    @property
    def num_stages(self) -> int:
        """Number of models run one after another (a sequence model counts as one)."""
        return len(self._stages)

    @property
    def kind(self) -> str:
        """``"hierarchy"`` (several models), ``"sequence"`` or ``"single"`` (:data:`KINDS`)."""
        if len(self._stages) > 1:
            return "hierarchy"
        return "sequence" if self._outputs[0].startswith("h_bar_") else "single"

    def __repr__(self):
        return (f"HomographyEstimator(kind={self.kind!r}, num_stages={self.num_stages}, "
                f"source={self.source!r})")

    @property
    def last_info(self) -> dict | None:
        """Deprecated (removed in the next release): the per-pair fields of the last call's
        :class:`~stnh_tf.inference.pipeline.Estimate` as a dict (``Estimate.info()``); use
        :meth:`estimate_with_info`."""
        warnings.warn("HomographyEstimator.last_info is deprecated; use estimate_with_info(), "
                      "which returns an Estimate.", DeprecationWarning, stacklevel=2)
        return None if self._last is None else self._last.info()

    @property
    def last_rejected(self) -> dict:
        """Deprecated (removed in the next release): ``Estimate.rejected`` of the last call."""
        warnings.warn("HomographyEstimator.last_rejected is deprecated; use estimate_with_info(), "
                      "whose Estimate has .rejected.", DeprecationWarning, stacklevel=2)
        return {r: 0 for r in pipeline.REASONS} if self._last is None else self._last.rejected

    # -- estimation ---------------------------------------------------------------------------
    def _predict_stage(self, k, patch_a, patch_b, batch_size):
        """Stage k's pixel ``H_ba`` ``[B, 3, 3]`` (float64) for float32 ``[B, S, S, 1]`` inputs,
        through the stage's compiled predictor (:func:`stnh_tf.modeling.runner.predictor`, built
        on first use and kept)."""
        from stnh_tf.modeling import runner

        if self._predictors[k] is None:
            self._predictors[k] = runner.predictor(self._stages[k], output=self._outputs[k])
        return self._predictors[k](patch_a, patch_b, batch_size)

    def _resolve(self, options, legacy, default=None) -> EstimateOptions:
        """The call's options: ``options``, else ``default`` (``None``: the estimator's
        ``options``), with the deprecated keyword options of earlier versions applied over
        them."""
        default = self.options if default is None else default
        options = self._check_options(default if options is None else options)
        unknown = set(legacy) - set(_LEGACY_OPTIONS)
        if unknown:
            raise TypeError(f"unexpected keyword argument(s) {sorted(unknown)}.")
        if legacy:
            warnings.warn(f"estimate keywords {sorted(legacy)} are deprecated; pass "
                          "options=EstimateOptions(...).", DeprecationWarning, stacklevel=3)
            options = dataclasses.replace(options, **legacy)
        return options

    def _run(self, patch_a, patch_b, context, origin, options, batch_size) -> Estimate:
        """The pipeline on ``[B, S, S, 1]`` pairs (uint8, or float in [0, 1]: checked by
        :func:`~stnh_tf.inference.image_input.check_patches`; ``context``: images holding patch_a
        at ``origin``, else the patches themselves), :data:`CHUNK_PAIRS` (rounded up to a multiple
        of ``batch_size``) at a time, each chunk converted to float32 when it is reached."""
        def take(index):
            a, b = unit_patches(patch_a[index]), unit_patches(patch_b[index])
            if context is None:
                return a, b, [p[..., 0] for p in a]
            return a, b, (context[index] if isinstance(index, slice)
                          else [context[i] for i in index])

        chunk = batch_size * -(-CHUNK_PAIRS // batch_size)
        result = pipeline.estimate_in_chunks(
            lambda k, a, b: self._predict_stage(k, a, b, batch_size), self.num_stages, take,
            len(patch_a), origin if context is not None else (0, 0), options, chunk)
        if result.flat.any():
            _log.warning("HomographyEstimator: %d pair(s) with a flat patch (nothing to align): "
                         "estimate set to the identity", int(result.flat.sum()))
        if any(result.rejected.values()):
            _log.warning("HomographyEstimator: stage predictions skipped as degenerate: %s",
                         result.rejected)
        self._last = result
        return result

    def estimate_with_info(self, patch_a, patch_b, options: EstimateOptions | None = None,
                           batch_size: int = 64, **legacy) -> Estimate:
        """:meth:`estimate`, returning the :class:`~stnh_tf.inference.pipeline.Estimate` (the
        homographies and what the checks, search, refinement and retry found per pair)."""
        _check_batch_size(batch_size)
        options = self._resolve(options, legacy)
        a = check_patches(patch_a, "patch_a")
        b = check_patches(patch_b, "patch_b")
        if len(a) != len(b):
            raise ValueError(f"patch_a and patch_b must hold the same number of patches; received "
                             f"shapes {np.shape(patch_a)} and {np.shape(patch_b)}.")
        return self._run(a, b, None, (0, 0), options, batch_size)

    def estimate(self, patch_a, patch_b, options: EstimateOptions | None = None,
                 batch_size: int = 64, **legacy) -> np.ndarray:
        """Pixel homography between 128 x 128 grayscale patches.

        Args:
          patch_a, patch_b: one pair (``[128, 128]`` or ``[128, 128, 1]``) or a batch
            (``[B, 128, 128]`` or ``[B, 128, 128, 1]``), uint8 (0..255) or float in [0, 1].
          options: what to do beyond the network
            (:class:`~stnh_tf.inference.options.EstimateOptions`; default: the estimator's
            ``options``). ``EstimateOptions.network_only()`` is the paper's network alone.
          batch_size: pairs per model call. Large batches go through the pipeline
            :data:`CHUNK_PAIRS` pairs at a time (rounded up to a multiple of ``batch_size``), so
            memory stays bounded; the result is that of one pass. A pair's estimate depends on
            ``batch_size`` by float32 rounding only (docs/estimate.md, "Batch size").
          **legacy: the keyword options of earlier versions (``search="none"``, ...), applied
            over ``options``; deprecated.
        Returns:
          float64 ``[B, 3, 3]`` ``H_ba``, mapping patch_b pixel coordinates to patch_a pixel
          coordinates (``[2, 2] = 1``; B = 1 for a single pair).
        Raises:
          ValueError: wrong rank, size, channel count or dtype, empty or different-sized
            batches, ``batch_size`` < 1, bad options.
          TypeError: ``options`` that is not an ``EstimateOptions``.
        """
        return self.estimate_with_info(patch_a, patch_b, options, batch_size,
                                       **legacy).homography

    def estimate_images_with_info(self, image_a, image_b, options: EstimateOptions | None = None,
                                  channel_order: str = "rgb", **legacy) -> Estimate:
        """:meth:`estimate_images`, returning the
        :class:`~stnh_tf.inference.pipeline.Estimate` of the pair (B = 1), its homography in the
        images' own pixel frames."""
        # Gate and fill are for bare patches: with the image as context every stage is composed and
        # later stages see zeros beyond the image, as in the paper.
        options = dataclasses.replace(self._resolve(options, legacy, self.image_options),
                                      gate_stages=False, fill="zeros")
        # the feature start may match the images at their own resolution (issue 79)
        wants_start = options.features != "none"
        input_a = input_image(image_a, "image_a", channel_order, wants_start)
        input_b = input_image(image_b, "image_b", channel_order, wants_start)
        (work_a, size_a), (work_b, size_b) = input_a[:2], input_b[:2]
        start = features.start_images(input_a, input_b) if wants_start else None
        del input_a, input_b  # the images at their own size: held by start only
        network = options
        if options.refine == "images":
            # image_refine makes the patch refinement (scored beside the whole images' ECC) and,
            # unless a retry needs the flag first, the ECC check from the same start
            network = dataclasses.replace(options, refine="none",
                                          verify=options.verify if options.retries else "none")
        run = lambda a, b, contexts, opts: self._run(a, b, contexts, PATCH_ORIGIN, opts, 64)  # noqa
        # a deviation (issue 64): a start from SIFT matches for wide baselines
        result = features.estimate(run, work_a, work_b, network, PATCH_ORIGIN, start)
        network_h = result.network_homography
        result = self._finish_images(run, result, work_a, work_b, network, options)
        # what the network alone gave from the identity start, and how far the result is from it
        move = pipeline.network_moves(result.homography, network_h, [np.shape(work_a)],
                                      PATCH_ORIGIN)
        if features.late_wanted(result, options):
            # the finished estimate says the network's was off: the feature start after all
            made = features.candidate(run, work_a, work_b, network, PATCH_ORIGIN, start)
            if made is not None:
                late = self._finish_images(
                    run, dataclasses.replace(made, network_homography=network_h), work_a,
                    work_b, network, options)
                if features.late_better(late, result, work_a, work_b, options, PATCH_ORIGIN):
                    result = pipeline.replacing(late, result)
                    move = pipeline.network_moves(result.homography, network_h,
                                                  [np.shape(work_a)], PATCH_ORIGIN)
        h = patch_to_image_frames(result.homography[0], size_a, size_b)
        return dataclasses.replace(
            result, homography=h[None], options=options, network_move_px=move,
            network_homography=patch_to_image_frames(network_h[0], size_a, size_b)[None])

    @staticmethod
    def _finish_images(run, result, work_a, work_b, network, options):
        """What follows the network and the feature start in :meth:`estimate_images_with_info`
        (one pair, patch frame): the coarse pass or its corner rule, the whole-image refinement,
        the flag's corner-precision and ambiguity checks, and ``image_ncc`` with its alignment
        floor (``thresholds.min_alignment_ncc``; undefined: flagged)."""
        confirmed = bool(result.feature_start[0] and not result.implausible[0])
        if options.coarse != "none" and not confirmed:
            # a deviation (issue 46): motions beyond the trained range
            result = coarse.coarse_pass(run, work_a, work_b, result, network, PATCH_ORIGIN)
        elif options.wide_motions and not confirmed and coarse.needs_pass(result, network):
            # the feature start found nothing better: the corner rule of motions beyond the
            # trained range, as after a coarse pass that finds nothing (issue 64)
            result = coarse.flag(result, network)
        # a deviation (issue 46): refine="images" aligns the whole images
        result = image_refine.refine_images(result, work_a, work_b, options, PATCH_ORIGIN)
        if options.verify == "ecc" and not result.flat[0]:
            # the flag's check (issue 64): how precisely the whole images fix the estimate;
            # where not even at their own scale, the identity takes its place
            std = checks.corner_std(work_a, work_b, result.homography[0], PATCH_ORIGIN,
                                    tile=options.thresholds.corner_std_tile)
            undetermined = std > options.thresholds.undetermined_corner_std
            # and whether another shift of it, or of its tiles, aligns them as well (issue 79)
            gap = ambiguity.ambiguity_gap(work_a, work_b, result.homography[0], PATCH_ORIGIN)
            tile_gap = (ambiguity.tile_ambiguity_gap(work_a, work_b, result.homography[0],
                                                     PATCH_ORIGIN)
                        if options.thresholds.min_tile_ambiguity_gap > 0 else float("nan"))
            if undetermined:  # what is returned is the identity: its own shift and NCC
                result = dataclasses.replace(
                    result, max_corner_shift_px=np.zeros(1), alignment_ncc=np.array([
                        checks.alignment_ncc(work_a, central_patch(work_b)[0, ..., 0], np.eye(3),
                                             PATCH_ORIGIN, options.thresholds.min_overlap)]))
            result = dataclasses.replace(
                result, corner_std_px=np.array([std]), undetermined=np.array([undetermined]),
                homography=np.eye(3)[None] if undetermined else result.homography,
                ambiguity_gap=np.array([gap]), tile_ambiguity_gap=np.array([tile_gap]),
                implausible=(result.implausible | undetermined
                             | (std > options.thresholds.max_corner_std)
                             | (gap < options.thresholds.min_ambiguity_gap)
                             | (tile_gap < options.thresholds.min_tile_ambiguity_gap)))
        t = options.thresholds  # the alignment floor on the whole work images too (issue 79)
        whole = -np.inf if result.flat[0] else coarse.image_ncc(
            work_a, work_b, result.homography[0], PATCH_ORIGIN, t.min_overlap)
        return dataclasses.replace(
            result, image_ncc=np.array([whole if np.isfinite(whole) else np.nan]),
            implausible=result.implausible | bool(not result.flat[0]
                                                  and not whole >= t.min_alignment_ncc))

    def estimate_images(self, image_a, image_b, options: EstimateOptions | None = None,
                        channel_order: str = "rgb", **legacy) -> np.ndarray:
        """Homography between two images of any size and colour, in their own pixel frames.

        Each image is made grayscale and resized to 320 x 240; the central 128 x 128 squares are
        the patch pair; a hierarchy's later stages crop from the warped 320 x 240 image_a
        (context beyond the patch, as in the paper: ``options.gate_stages`` and ``options.fill``,
        which are for bare patches, do not apply: every stage is composed, zeros beyond the
        image). The feature start (``options.features``) matches the images at their own
        resolution (up to 1,600 px on the long side) and its start is mapped into the 320 x 240
        frame; the network and the refinement work at 320 x 240. The rule:
        :mod:`stnh_tf.inference.image_input`.

        Args:
          image_a, image_b: ``[H, W]`` or ``[H, W, C]`` (C = 1, 3, 4), uint8 or float in [0, 1];
            the two may differ in size.
          options: as in :meth:`estimate` (search and refinement align patch_b with the
            320 x 240 image_a; test-time augmentation transforms image_a with its patch);
            ``None``: the estimator's ``image_options`` (by default
            ``EstimateOptions.photographs()``: the feature start, the whole-image refinement
            and the ECC check of the flag; deviations, docs/estimate.md);
            ``options.coarse`` (used here only; opt-in): the coarse pass for motions beyond the
            trained range (:mod:`stnh_tf.inference.coarse`); ``refine="images"``: ECC over the
            whole images at the end (:mod:`stnh_tf.inference.image_refine`).
          channel_order: "rgb" (NumPy/scikit-image) or "bgr" (``cv2.imread``).
          **legacy: as in :meth:`estimate`; deprecated.
        Returns:
          float64 ``[3, 3]`` ``H_ba`` mapping image_b pixel coordinates to image_a pixel
          coordinates (``[2, 2] = 1``).
        Raises:
          ValueError: an image of another shape or dtype, or one too small for the patch
            (under 20 x 15 px: :func:`~stnh_tf.inference.image_input.check_image_size`).
        """
        return self.estimate_images_with_info(image_a, image_b, options, channel_order,
                                              **legacy).homography[0]
