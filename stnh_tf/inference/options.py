"""What :class:`~stnh_tf.inference.estimator.HomographyEstimator` does beyond the network, as one
value: :class:`EstimateOptions` (the steps, each named from a table) holding :class:`Thresholds`
(every number the steps use). Standard library and NumPy only.

Presets: ``EstimateOptions()``, the estimator's default on patches (the stage gate, the mirror
fill and the search of poorly aligned pairs: deviations from the paper, docs/estimate.md);
:meth:`EstimateOptions.photographs`, its default on whole images, ``estimate_images`` (also wider
motions, whole-image refinement, a stricter flag); :meth:`EstimateOptions.network_only`, the
network's composed estimate alone: what the paper's evaluation, the tables and the exported
SavedModel compute.

    >>> EstimateOptions().search, EstimateOptions.network_only().search
    ('ecc', 'none')
    >>> EstimateOptions(tta="dihedral").tta_symmetries[:2]
    ('identity', 'flip_x')
    >>> EstimateOptions(search="sift")
    Traceback (most recent call last):
    ...
    ValueError: search must be one of ('none', 'ecc'); received 'sift'.
"""

from __future__ import annotations

import dataclasses
import math
import numbers

import numpy as np

from stnh_tf import geometry

REFINES = ("none", "ecc", "images")
"""What the estimator does after the network: ``"none"`` (the paper), ``"ecc"`` (polish each
estimate with OpenCV's ECC alignment of patch_b started from it,
:func:`stnh_tf.inference.search.ecc_refine`; a deviation) or ``"images"`` (as ``"ecc"``; then, in
``estimate_images``, ECC over the whole 320 x 240 images, :mod:`stnh_tf.inference.image_refine`;
a deviation, issue 46)."""

SEARCHES = ("none", "ecc")
"""What the estimator does with a pair its estimate aligns poorly: ``"ecc"`` tries
:func:`stnh_tf.inference.search.search_translations` (a deviation); ``"none"`` keeps the
network's estimate."""

VERIFIES = ("none", "ecc")
"""How the estimator double-checks its final estimate before flagging it: ``"none"`` (the
checks alone) or ``"ecc"`` (an estimate that ECC alignment started from it moves by more than
``Thresholds.max_verify_move``, or from which ECC does not converge, is flagged implausible,
unless the whole images bring the move back: ``Estimate.move_confirmed``; the estimate is kept;
a deviation, issue 46)."""

COARSES = {
    "none": ((0.0, 1.0),),
    "rotations": tuple((float(angle), zoom) for zoom in (1.0, 0.7, 1.4)
                       for angle in (0, -15, 15, -30, 30, -45, 45)),
}
"""The coarse pass of ``estimate_images`` by name (:mod:`stnh_tf.inference.coarse`; a deviation,
issue 46): its starts as ``(angle in degrees, zoom)`` of ``a_from_b`` about the image centre, the
identity first. ``"none"`` (the default): no coarse pass. ``"rotations"``: in-plane rotations by
multiples of 15 degrees up to 45 and zooms 0.7 / 1 / 1.4, 21 starts; a motion inside that range
is at most 7.5 degrees and a zoom factor of 1.2 from a start, which moves the patch corners by
about 12 and 18 px: inside the trained range (32 px)."""

FEATURES = ("none", "fallback", "always")
"""A feature-based start in ``estimate_images`` (:mod:`stnh_tf.inference.features`; a deviation,
issue 64): ``"none"``; ``"fallback"``: where the network's estimate fails the coarse pass's
trigger (:func:`stnh_tf.inference.coarse.needs_pass`), OpenCV SIFT matched with
``cv2.USAC_MAGSAC`` gives a start ``G``, the network's stages estimate the rest from image_a
warped by ``G``, and the result replaces the network's where it aligns the work images better;
``"always"``: the same for every pair, as one more candidate scored by the same measure.
Neither runs where a central patch is flat (the flat rule's identity, flagged:
:func:`stnh_tf.inference.features.wanted`).
``EstimateOptions.photographs()`` (``estimate_images``' default) uses ``"fallback"``, which
tries the start before the search (:func:`stnh_tf.inference.features.estimate`)."""

TTAS = {"none": ("identity",),
        "flips": ("identity", "flip_x", "flip_y", "rotate_180"),
        "dihedral": tuple(geometry.DIHEDRAL)}
"""Test-time augmentation by name (a deviation from the paper): the symmetries
(:data:`stnh_tf.geometry.DIHEDRAL`) the stages also run on; ``"none"`` (the paper) runs them
once."""


WHOLE_NUMBER_TYPES = ("int",)
"""The annotations of :class:`Thresholds`' fields that hold whole numbers (counts, sizes in px);
the others take any real number."""


@dataclasses.dataclass(frozen=True)
class Thresholds:
    """The numbers of the estimator's checks, search and refinement (px are of the 128 x 128
    patch frame; NCC is :func:`stnh_tf.inference.checks.alignment_ncc`). How each was chosen:
    docs/estimate.md and BENCHMARKS.md.

    Attributes:
      implausible_corner_shift: a corner moved more than this flags the estimate implausible (the
        models were trained on corners moved by up to 32 px).
      min_alignment_ncc: an alignment NCC below this (or undefined) flags it implausible; in
        ``estimate_images`` also the whole work images' (``Estimate.image_ncc``).
      min_patch_std: a patch whose intensities (on [0, 1]) vary less than this is flat: its pair
        gets the identity, flagged implausible (0: no flat rule).
      min_overlap: the fraction of patch_b's pixels that must land inside patch_a's source for
        the NCC to be defined.
      search_below_ncc: ``search="ecc"`` searches a pair aligned below this (or implausible).
      verified_ncc: a search result must align the pair at least this well to be kept (the
        search's own sizes and iteration limits: :mod:`stnh_tf.inference.search`' constants).
      refine_iterations, refine_eps: ``cv2.findTransformECC``'s iteration limit and
        convergence threshold in ``refine="ecc"`` (no Gaussian pre-filter).
      max_refine_move: a refinement moving the corners by more than this on average is dropped.
      max_verify_move: with ``verify="ecc"``, an estimate that ECC (the refinement's settings)
        moves by more than this is flagged implausible: px, mean over the corners of the frame
        the estimate is made in (the patch; the 320 x 240 image in ``estimate_images``), in
        image_b's pixels where the estimate zooms out beyond the trained range
        (:func:`stnh_tf.inference.checks.verify_move`; issue 64); with ``refine="images"`` in
        ``estimate_images``, not where ECC over the whole images brings the move back to
        within this of an estimate that aligns them at least as well as where ECC moved it
        (:func:`stnh_tf.inference.image_refine.move_confirmed`).
      coarse_corner_shift: with ``coarse`` or ``features`` other than ``"none"``
        (``EstimateOptions.wide_motions``), this replaces ``implausible_corner_shift`` in the
        implausibility rule of ``estimate_images`` where the network's estimate aligns poorly
        (a patch corner moved further is beyond what the coarse pass handles: 4x the trained
        range). An estimate made from the
        feature start (``features``) has no corner rule: its checks are the alignment's.
      max_corner_std: with ``verify="ecc"`` in ``estimate_images``, an estimate that the two
        work images fix less precisely than this at image_b's corners (the predicted standard
        deviation, px, :func:`stnh_tf.inference.checks.corner_std`) is flagged implausible:
        where image_a covers little of image_b (a zoom out), a good alignment of the overlap
        can be far off at the corners.
      corner_std_tile: the side (px) of the squares of image_b over which that standard
        deviation's covariance is cluster-robust (``checks.corner_std``'s ``tile``; issue 64):
        residuals correlated within a square count as they spread the estimate; 0: the
        classical covariance of independent pixels (``max_corner_std`` 1 px before).
      resolution_sigma: with ``refine="images"``, the whole-image refinement first brings the two
        work images to one resolution (:func:`stnh_tf.inference.image_refine.equal_resolution`):
        where the estimate maps image_b's centre at scale ``s`` (a zoom), the sharper image is
        blurred by ``resolution_sigma * sqrt(s**2 - 1)`` px (``s`` or ``1 / s``; under 0.41 px,
        bilinear interpolation's own blur, left out): a camera's blur of this many px, as seen
        at the other zoom. The whole-image ECC and the scores that choose between its results
        see the blurred pair; the patch ECC and the flag's measures the images as they are.
        0: off.
      undetermined_corner_std: with ``verify="ecc"`` in ``estimate_images``, where that
        predicted standard deviation exceeds this (the 400 px diagonal of the 320 x 240 work
        image), the images leave the estimate undetermined at their own scale: the identity is
        returned in its place, flagged (``Estimate.undetermined``), as SIFT + RANSAC returns
        the identity where it finds no model.
      min_ambiguity_gap: with ``verify="ecc"`` in ``estimate_images``, an estimate under which
        image_b aligns with image_a warped by it at another shift (8 to 80 px at the work size,
        a distinct peak of the NCC over shifts) within this much of the estimate's own NCC is
        flagged implausible (``Estimate.ambiguity_gap``,
        :func:`stnh_tf.inference.ambiguity.ambiguity_gap`): a repeated pattern aligns as well one
        period off (issue 79). 0.005: a near-perfect repetition only.
      min_tile_ambiguity_gap: the same tile by tile (``Estimate.tile_ambiguity_gap``,
        :func:`stnh_tf.inference.ambiguity.tile_ambiguity_gap`, the median over 80 x 80 tiles of
        the gap to a second peak that a valley separates): a pattern in perspective (a facade,
        blinds) aligns one period off tile by tile, by no single shift. 0: off.
      late_start_below_ncc: with ``features="fallback"`` in ``estimate_images``, a finished
        estimate (not the feature start's, not flagged) under which the two work images align
        below this (:func:`stnh_tf.inference.coarse.image_ncc`) gets the feature start after
        all (:func:`stnh_tf.inference.features.late_wanted`), whose finished estimate replaces
        it where unflagged and aligning them better
        (:func:`~stnh_tf.inference.features.late_better`): a facade one period off aligns its
        patch well and the whole images less so (issue 79). 0: off (flagged estimates only).
    """

    implausible_corner_shift: float = 1.5 * geometry.MAX_PERTURBATION
    min_alignment_ncc: float = 0.7
    min_patch_std: float = 0.5 / 255
    min_overlap: float = 0.25
    search_below_ncc: float = 0.9
    verified_ncc: float = 0.95
    refine_iterations: int = 50
    refine_eps: float = 1e-5
    max_refine_move: float = 16.0
    max_verify_move: float = 5.0
    coarse_corner_shift: float = 4 * geometry.MAX_PERTURBATION
    max_corner_std: float = 1.5
    corner_std_tile: int = 8
    undetermined_corner_std: float = 400.0
    min_ambiguity_gap: float = 0.005
    min_tile_ambiguity_gap: float = 0.1
    resolution_sigma: float = 0.8
    late_start_below_ncc: float = 0.95

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if (isinstance(value, bool) or not isinstance(value, numbers.Real)
                    or not math.isfinite(value) or value < 0):
                raise ValueError(f"Thresholds.{f.name} must be finite and >= 0; received "
                                 f"{value!r}.")
            if f.type in WHOLE_NUMBER_TYPES and not isinstance(value, numbers.Integral):
                raise ValueError(f"Thresholds.{f.name} must be a whole number (a count or a "
                                 f"size in px); received {value!r}.")
        if self.min_overlap > 1:
            raise ValueError(f"Thresholds.min_overlap is a fraction of patch_b's pixels, in "
                             f"[0, 1]; received {self.min_overlap!r}.")


@dataclasses.dataclass(frozen=True)
class EstimateOptions:
    """What the estimator does beyond the network (cf. ``cv2.UsacParams``): a frozen value,
    checked when made (``ValueError`` naming the field). ``dataclasses.replace(options, ...)``
    makes a variant.

    Attributes:
      search: a key of :data:`SEARCHES`. ``"ecc"`` (default, a deviation): a pair whose estimate
        aligns it below ``thresholds.search_below_ncc``, or is implausible, gets the result of
        :func:`~stnh_tf.inference.search.search_translations` where one aligns it at
        ``thresholds.verified_ncc`` or better. ``"none"``: the network's estimate.
      refine: a key of :data:`REFINES` (``"ecc"``: ECC started from the final estimate; dropped
        where it fails or moves the corners by more than ``thresholds.max_refine_move``;
        ``"images"``: the same, then in ``estimate_images`` ECC over the whole images, kept where
        it aligns them better).
      tta: a key of :data:`TTAS`: the stages also run on each pair mirrored (and rotated); each
        pair keeps the estimate, mapped back, that aligns it best.
      retry_tta: a key of :data:`TTAS` with more symmetries than ``tta``: a pair flagged
        implausible (not flat) is estimated again with it and keeps that estimate. One with no
        more symmetries than ``tta`` does nothing.
      gate_stages: in a hierarchy, keep a later stage's update of a pair only where it does not
        lower the pair's alignment NCC (a deviation for bare patches); False composes every stage.
      fill: in a hierarchy on bare patches, what later stages see of patch_a beyond the patch
        (:data:`stnh_tf.geometry.FILLS`): ``"reflect"`` (default, a deviation) or ``"zeros"``.
        With image context (``estimate_images``) the context is used instead.
      thresholds: the numbers of the checks, the search and the refinement.
      verify: a key of :data:`VERIFIES`. ``"ecc"`` (a deviation): ECC alignment is started from
        each final estimate (not flat, finite); where it fails or moves the estimate by more than
        ``thresholds.max_verify_move`` at the frame's corners on average, the estimate is
        flagged implausible (it is not replaced: ``refine="ecc"`` does that), unless the whole
        images bring that move back (``Estimate.move_confirmed``, with ``refine="images"`` in
        ``estimate_images``). ``"none"``: no such check.
      coarse: a key of :data:`COARSES`, used by ``estimate_images`` only (a deviation, issue 46):
        ``"rotations"`` tries a pair that its estimate aligns poorly again from coarse rotations
        and zooms (:mod:`stnh_tf.inference.coarse`), for motions beyond the trained range; where
        the pass ran, the flag's corner rule uses ``thresholds.coarse_corner_shift``.
        ``"none"`` (default, and ``photographs()``'s since issue 64): no coarse pass.
      features: a key of :data:`FEATURES`, used by ``estimate_images`` only (a deviation, issue
        64): a start from OpenCV SIFT matches (:mod:`stnh_tf.inference.features`) refined by the
        network's stages, kept where it aligns the work images better; ``"fallback"`` for pairs
        the network's estimate aligns poorly, ``"always"`` for every pair (but a flat one:
        :data:`FEATURES`). ``"none"`` (default; ``photographs()``: ``"fallback"``): none.
    """

    search: str = "ecc"
    refine: str = "none"
    tta: str = "none"
    retry_tta: str = "none"
    gate_stages: bool = True
    fill: str = "reflect"
    thresholds: Thresholds = Thresholds()
    verify: str = "none"
    coarse: str = "none"
    features: str = "none"

    def __post_init__(self):
        for name, table in (("search", SEARCHES), ("refine", REFINES), ("tta", tuple(TTAS)),
                            ("retry_tta", tuple(TTAS)), ("fill", geometry.FILLS),
                            ("verify", VERIFIES), ("coarse", tuple(COARSES)),
                            ("features", FEATURES)):
            value = getattr(self, name)
            if not isinstance(value, str) or value not in table:
                raise ValueError(f"{name} must be one of {tuple(table)}; received {value!r}.")
        if not isinstance(self.gate_stages, (bool, np.bool_)) and not (
                isinstance(self.gate_stages, numbers.Integral) and self.gate_stages in (0, 1)):
            raise ValueError(f"gate_stages must be a bool; received {self.gate_stages!r}.")
        object.__setattr__(self, "gate_stages", bool(self.gate_stages))
        if not isinstance(self.thresholds, Thresholds):
            raise ValueError(f"thresholds must be a Thresholds; received {self.thresholds!r}.")

    @classmethod
    def network_only(cls, **changes) -> "EstimateOptions":
        """The network's composed estimate alone: every stage composed (no gate), no search, no
        flat rule; what the exported SavedModel computes (with the mirror fill of bare patches,
        as the export does), and the paper's evaluation for one stage (a hierarchy's later
        stages see the stored context there: docs/estimate.md). ``changes`` override fields.
        """
        return cls(**{"search": "none", "gate_stages": False,
                      "thresholds": Thresholds(min_patch_std=0.0), **changes})

    @classmethod
    def photographs(cls, **changes) -> "EstimateOptions":
        """``estimate_images``' default, for real photographs (issues 46 and 64; deviations from
        the paper): ``EstimateOptions()`` with the whole-image refinement (``refine="images"``),
        the ECC check of the flag (``verify="ecc"``) and the feature start where the network's
        estimate aligns poorly (``features="fallback"``), which takes motions beyond the trained
        range (``wide_motions``); the coarse pass (``coarse="rotations"``) is opt-in since the
        feature start (issue 64). ``changes`` override fields.

        >>> o = EstimateOptions.photographs()
        >>> o.coarse, o.refine, o.verify, o.search, o.features, o.wide_motions
        ('none', 'images', 'ecc', 'ecc', 'fallback', True)
        """
        return cls(**{"refine": "images", "verify": "ecc", "features": "fallback", **changes})

    @property
    def wide_motions(self) -> bool:
        """Whether ``estimate_images`` takes motions beyond the trained range (the coarse pass or
        the feature start): its flag's corner rule is then ``thresholds.coarse_corner_shift``."""
        return self.coarse != "none" or self.features != "none"

    @property
    def tta_symmetries(self) -> tuple:
        """The symmetries the stages run on (:data:`TTAS` of ``tta``)."""
        return TTAS[self.tta]

    @property
    def retries(self) -> bool:
        """Whether ``retry_tta`` adds symmetries to ``tta`` (else a retry would change nothing)."""
        return set(TTAS[self.retry_tta]) > set(TTAS[self.tta])

    def to_json(self) -> dict:
        """The options as a JSON-ready dict (thresholds nested)."""
        return dataclasses.asdict(self)
