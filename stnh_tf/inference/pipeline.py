"""The estimator's pipeline as small steps, each a function of arrays (tested alone in
``tests/test_inference.py``): the stages of a hierarchy (:func:`run_hierarchy`), with test-time
augmentation (:func:`run_network`), the checks (:func:`check`), the search (:func:`search`), the
refinement (:func:`refine`), and the retry of implausible pairs (:func:`estimate_pairs`); the
result is an :class:`Estimate`. NumPy and OpenCV only: the network comes in as a function.

Frames: every homography is a pixel ``H_ba`` (``a_from_b``) in the 128 x 128 patch frame
(:mod:`stnh_tf.geometry`); ``sources`` are the images patch_a lies in, its top-left corner at
``origin`` (the patches themselves with ``(0, 0)``, or the 320 x 240 images as context).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from stnh_tf import geometry, hierarchy
from stnh_tf.inference import checks
from stnh_tf.inference import search as search_lib
from stnh_tf.inference.options import EstimateOptions

PredictStage = Callable[[int, np.ndarray, np.ndarray], np.ndarray]
"""``predict(k, patch_a, patch_b)``: stage k's pixel ``H_ba`` ``[B, 3, 3]`` for float32
``[B, S, S, 1]`` inputs."""

REASONS = ("non_finite", "singular")
"""Why a stage prediction is skipped as degenerate (:func:`stnh_tf.hierarchy.accept_or_reject`)."""


@dataclasses.dataclass(frozen=True)
class Estimate:
    """The estimate of B pairs and what the estimator found out about each (arrays of length B).

    Attributes:
      homography: float64 ``[B, 3, 3]`` ``H_ba`` (``[2, 2] = 1``): patch frame from
        ``estimate_with_info``, the images' own frames from ``estimate_images_with_info``.
      implausible: a stage was skipped as degenerate, a corner moved beyond the trained range,
        the alignment NCC is below ``thresholds.min_alignment_ncc`` or undefined (in
        ``estimate_images_with_info`` also that of the whole work images), a patch is flat, or (``verify="ecc"``) ECC moved the estimate by more than
        ``thresholds.max_verify_move`` (unless ``move_confirmed``) or did not converge (with
        ``coarse`` in ``estimate_images_with_info``: a corner moved beyond
        ``thresholds.coarse_corner_shift`` instead, :func:`stnh_tf.inference.coarse.flag`).
      alignment_ncc: NCC of patch_b and patch_a warped by the estimate (NaN: undefined, flat).
      max_corner_shift_px: the largest displacement of a 128 x 128 patch corner.
      flat: patch_a or patch_b varies less than ``thresholds.min_patch_std`` (the identity).
      searched: the search looked at the pair, also where the estimate returned is another
        that replaced the one it was run for (the feature start's, the coarse pass's:
        :func:`replacing`).
      found: the estimate is the search's result.
      refined: the estimate is the ECC refinement.
      retried: the pair was estimated again with ``retry_tta`` (every other field is the retry's).
      tta_choice: the symmetry whose estimate was kept (``"identity"`` without ``tta``).
      non_finite_stages, singular_stages: stage predictions skipped as degenerate, by reason.
      gated_stages: later stages whose update the stage gate did not keep.
      options: the options that made it.
      verify_move_px: with ``verify="ecc"``, how far ECC started from the estimate moved it
        (mean over the corners of the patch, or of the 320 x 240 image in
        ``estimate_images_with_info``, there the patch's where a corner of the image maps beyond
        image_a's horizon: :func:`~stnh_tf.inference.checks.precision_corners`; in image_b's
        pixels where the estimate zooms out beyond
        the trained range: :func:`~stnh_tf.inference.checks.verify_move`; ``inf``: it did not
        converge); NaN where not verified.
      move_confirmed: in ``estimate_images_with_info`` with ``verify="ecc"`` and
        ``refine="images"``, ECC moved the estimate by more than ``thresholds.max_verify_move``,
        but ECC over the whole images, started from where it moved it, comes back to within
        that of the estimate, and the whole images align at least as well under the estimate
        as where ECC moved it (issue 79; before, at ``thresholds.verified_ncc`` or better): the
        move is patch_b's own optimum, not a sign of another alignment, and does
        not flag the estimate (:func:`stnh_tf.inference.image_refine.move_confirmed`; issue
        64). False elsewhere.
      network_homography: float64 ``[B, 3, 3]``: the network's own estimate (the stages
        composed, with ``options.tta``; before the flat rule, the search, the refinement, the
        coarse pass and the feature start), in the frame of ``homography``.
      network_move_px: how far ``homography`` lies from ``network_homography``: the mean
        distance (px) between where the two map the corners of the frame the estimate is made in
        (the 128 x 128 patch; the 320 x 240 work image in ``estimate_images_with_info``;
        :func:`~stnh_tf.inference.checks.frame_corner_distance`); 0 where nothing beyond the
        network changed the estimate, ``inf`` where a corner maps to infinity. What the steps
        beyond the paper's network contributed, in one number.
      feature_start: the estimate was made from the feature start (``options.features``,
        :mod:`stnh_tf.inference.features`): its flag has no corner rule.
      corner_std_px: in ``estimate_images_with_info`` with ``verify="ecc"``, how precisely the
        two work images fix the estimate at image_b's corners (the predicted standard deviation,
        px, :func:`~stnh_tf.inference.checks.corner_std`); above
        ``thresholds.max_corner_std`` the estimate is flagged. NaN elsewhere.
      undetermined: in ``estimate_images_with_info`` with ``verify="ecc"``, the corner standard
        deviation exceeded ``thresholds.undetermined_corner_std``: ``homography`` is the
        identity in place of the estimate (flagged), ``max_corner_shift_px``,
        ``alignment_ncc`` and ``image_ncc`` the identity's; the fields of the steps
        (``refined``, ``found``, ``feature_start``, ``network_move_px``, ``verify_move_px``,
        ``move_confirmed``, ``corner_std_px``, the ambiguity gaps) stay those of the estimate it
        replaced, which they explain. False elsewhere.
      ambiguity_gap: in ``estimate_images_with_info`` with ``verify="ecc"``, how much better
        the estimate aligns image_b's centre than the best other shift of it
        (:func:`~stnh_tf.inference.ambiguity.ambiguity_gap`); under
        ``thresholds.min_ambiguity_gap`` the estimate is flagged. NaN elsewhere.
      tile_ambiguity_gap: the same tile by tile
        (:func:`~stnh_tf.inference.ambiguity.tile_ambiguity_gap`); under
        ``thresholds.min_tile_ambiguity_gap`` the estimate is flagged. NaN elsewhere.
      image_ncc: in ``estimate_images_with_info``, the NCC of the two whole work images under the
        estimate (:func:`~stnh_tf.inference.coarse.image_ncc`; NaN: undefined, flat); below
        ``thresholds.min_alignment_ncc`` the estimate is flagged, below
        ``thresholds.late_start_below_ncc`` it gets the late feature start. NaN elsewhere.
    """

    homography: np.ndarray
    implausible: np.ndarray
    alignment_ncc: np.ndarray
    max_corner_shift_px: np.ndarray
    flat: np.ndarray
    searched: np.ndarray
    found: np.ndarray
    refined: np.ndarray
    retried: np.ndarray
    tta_choice: np.ndarray
    non_finite_stages: np.ndarray
    singular_stages: np.ndarray
    gated_stages: np.ndarray
    options: EstimateOptions
    verify_move_px: np.ndarray = None
    move_confirmed: np.ndarray = None
    network_homography: np.ndarray = None
    network_move_px: np.ndarray = None
    feature_start: np.ndarray = None
    corner_std_px: np.ndarray = None
    undetermined: np.ndarray = None
    ambiguity_gap: np.ndarray = None
    tile_ambiguity_gap: np.ndarray = None
    image_ncc: np.ndarray = None

    def __len__(self):
        return len(self.homography)

    @property
    def rejected_stages(self) -> np.ndarray:
        """Stage predictions skipped as degenerate per pair ``[B]``."""
        return self.non_finite_stages + self.singular_stages

    @property
    def rejected(self) -> dict:
        """Stage predictions skipped as degenerate over the batch, by reason."""
        return {r: int(getattr(self, f"{r}_stages").sum()) for r in REASONS}

    def info(self) -> dict:
        """The per-pair fields under the keys of the deprecated ``last_info`` dict."""
        names = ("implausible", "max_corner_shift_px", "rejected_stages", "gated_stages",
                 "alignment_ncc", "flat", "searched", "refined", "tta_choice", "retried")
        return {**{n: getattr(self, n) for n in names}, "search_found": self.found}


def run_hierarchy(predict: PredictStage, num_stages, patch_a, patch_b, sources, origin,
                  options: EstimateOptions) -> dict:
    """The stages one after another, later ones on patch_a warped by the estimate so far (cropped
    from ``sources``, ``options.fill`` beyond them); a non-finite or singular composition keeps
    the estimate so far; with ``options.gate_stages`` a later stage's update of a pair is kept only
    where it does not lower its alignment NCC. Returns ``{"total", "non_finite", "singular",
    "gated", "ncc"}`` (``ncc``: the gate's NCC of ``total``, ``None`` without a gate)."""
    n = len(patch_a)
    out = {"total": np.broadcast_to(np.eye(3), (n, 3, 3)).copy(), "gated": np.zeros(n, np.int64),
           "ncc": None, **{r: np.zeros(n, np.int64) for r in REASONS}}
    gate = options.gate_stages and num_stages > 1
    nccs = lambda h: checks.alignment_nccs(sources, patch_b, h, origin,  # noqa: E731
                                           options.thresholds.min_overlap)
    current = patch_a
    for k in range(num_stages):
        if k:
            current = np.stack([hierarchy.warp_crop(src, h, origin, patch_a.shape[1], options.fill)
                                for src, h in zip(sources, out["total"])])[..., None]
        proposed, reasons = hierarchy.accept_or_reject(out["total"], predict(k, current, patch_b),
                                                       margin=np.inf)
        for i, reason in enumerate(reasons):
            if reason:
                out[reason][i] += 1
        if gate and k:
            ncc_proposed = nccs(proposed)
            lowered = ncc_proposed < out["ncc"]
            out["gated"] += lowered
            out["total"] = np.where(lowered[:, None, None], out["total"], proposed)
            out["ncc"] = np.where(lowered, out["ncc"], ncc_proposed)
        else:
            out["total"] = proposed
            out["ncc"] = nccs(proposed) if gate else None
    return out


def run_network(predict: PredictStage, num_stages, patch_a, patch_b, sources, origin,
                options: EstimateOptions) -> dict:
    """:func:`run_hierarchy` on the pairs transformed by each symmetry of ``options.tta``, each
    estimate mapped back (``inv(G) @ H' @ G``); per pair the one with the highest alignment NCC is
    kept (the first listed on a tie). Returns :func:`run_hierarchy`'s dict with ``"choice"`` (the
    index of the kept symmetry)."""
    names = options.tta_symmetries
    if len(names) > 1 and len({np.shape(src) for src in sources}) > 1:
        raise ValueError("tta needs contexts of one size.")
    size, (height, width) = patch_a.shape[1], np.shape(sources[0])
    chosen = None
    for j, name in enumerate(names):
        # Pixel p of the patch (source) lands at g_patch @ p (g_source @ p) once transformed.
        g_patch = geometry.dihedral_matrix(name, size, size)
        g_source = geometry.dihedral_matrix(name, width, height)
        t_origin = tuple((g_source @ [origin[0], origin[1], 1.0] - g_patch @ [0.0, 0.0, 1.0])[:2])
        run = run_hierarchy(
            predict, num_stages,
            *(np.ascontiguousarray(geometry.dihedral_image(p, name, axes=(1, 2)))
              for p in (patch_a, patch_b)),
            [np.ascontiguousarray(geometry.dihedral_image(src, name)) for src in sources],
            t_origin, options)
        run["total"] = geometry.scale_to_unit(np.linalg.inv(g_patch) @ run["total"] @ g_patch)
        run["choice"] = np.full(len(patch_a), j)
        if len(names) > 1:  # the same alignment measured in the pairs' own frame
            run["ncc"] = checks.alignment_nccs(sources, patch_b, run["total"], origin,
                                               options.thresholds.min_overlap)
        if chosen is None:
            chosen = run
        else:
            better = run["ncc"] > chosen["ncc"]
            chosen = {key: np.where(better.reshape((-1,) + (1,) * (np.ndim(value) - 1)), value,
                                    chosen[key]) for key, value in run.items()}
    return chosen


def check(run: dict, patch_a, patch_b, sources, origin, options: EstimateOptions) -> dict:
    """The checks of a network estimate: a flat pair gets the identity (``"flat"``), and
    ``"ncc"`` becomes each estimate's alignment NCC (reused from the gate where measured; NaN for
    flat pairs and corners mapped to infinity). Returns a new dict."""
    t = options.thresholds
    run = dict(run, total=run["total"].copy())
    run["flat"] = checks.flat_pairs(patch_a, patch_b, t.min_patch_std)
    run["total"][run["flat"]] = np.eye(3)
    shift = checks.corner_shift(run["total"])
    valid = np.isfinite(shift) & ~run["flat"]
    if run["ncc"] is not None:
        run["ncc"] = np.where(np.isfinite(run["ncc"]) & valid, run["ncc"], np.nan)
    else:
        run["ncc"] = np.array([checks.alignment_ncc(src, b[..., 0], h, origin, t.min_overlap)
                               if ok else np.nan
                               for src, b, h, ok in zip(sources, patch_b, run["total"], valid)])
    return run


def search(run: dict, patch_b, sources, origin, options: EstimateOptions) -> dict:
    """With ``options.search == "ecc"``: each pair that is not flat, has finite corners and is
    beyond ``thresholds.search_below_ncc`` (:func:`stnh_tf.inference.checks.beyond`) gets
    :func:`~stnh_tf.inference.search.search_translations`' result where there is one. Adds
    ``"searched"`` and ``"found"``; returns a new dict."""
    t, n = options.thresholds, len(run["total"])
    run = dict(run, total=run["total"].copy(), ncc=run["ncc"].copy(),
               searched=np.zeros(n, bool), found=np.zeros(n, bool))
    if options.search != "ecc":
        return run
    shift = checks.corner_shift(run["total"])
    run["searched"] = (~run["flat"] & np.isfinite(shift) & checks.beyond(
        run["non_finite"] + run["singular"], shift, run["ncc"], t.search_below_ncc, t))
    for i in np.flatnonzero(run["searched"]):
        result = search_lib.search_translations(sources[i], patch_b[i, ..., 0], run["total"][i],
                                                origin, t)
        if result is not None:
            (run["total"][i], run["ncc"][i]), run["found"][i] = result, True
    return run


def refine(run: dict, patch_b, sources, origin, options: EstimateOptions) -> dict:
    """With ``options.refine`` ``"ecc"`` or ``"images"``: each finite estimate of a pair that is
    not flat and not found by the search (an ECC optimum already) is replaced by its ECC
    refinement, unless that fails or moves the corners by more than
    ``thresholds.max_refine_move`` on average (the whole-image step of ``"images"`` is
    :mod:`stnh_tf.inference.image_refine`'s). Adds ``"refined"``; returns a new dict."""
    t = options.thresholds
    run = dict(run, total=run["total"].copy(), ncc=run["ncc"].copy(),
               refined=np.zeros(len(run["total"]), bool))
    if options.refine == "none":
        return run
    candidates = ~run["flat"] & ~run["found"] & np.isfinite(run["total"]).all(axis=(1, 2))
    for i in np.flatnonzero(candidates):
        h = search_lib.ecc_refine(sources[i], patch_b[i, ..., 0], run["total"][i], origin, t)
        if h is not None and float(geometry.corner_errors(
                h[None], run["total"][i][None])[0]) <= t.max_refine_move:
            run["total"][i], run["refined"][i] = h, True
            run["ncc"][i] = checks.alignment_ncc(sources[i], patch_b[i, ..., 0], h, origin,
                                                 t.min_overlap)
    return run


def verify(run: dict, patch_b, sources, origin, options: EstimateOptions) -> dict:
    """With ``options.verify == "ecc"``: ECC (:func:`~stnh_tf.inference.search.ecc_refine`, the
    refinement's settings) is started from each finite estimate of a pair that is not flat, and
    how far it moves the estimate is recorded: the mean distance at the corners of the source's
    frame (the patch for bare patches, the 320 x 240 image with context, there the patch's where
    a corner of the image maps beyond image_a's horizon;
    :func:`~stnh_tf.inference.checks.verify_move`), ``inf`` where ECC fails. The estimates are
    not changed. An estimate away from the nearest alignment optimum is likely wrong where its alignment NCC
    still looks good (issue 46). Adds ``"verify_move"`` (float64 ``[B]``, NaN where not
    verified); returns a new dict."""
    t = options.thresholds
    run = dict(run, verify_move=np.full(len(run["total"]), np.nan))
    if options.verify != "ecc":
        return run
    for i in np.flatnonzero(~run["flat"] & np.isfinite(run["total"]).all(axis=(1, 2))):
        h = search_lib.ecc_refine(sources[i], patch_b[i, ..., 0], run["total"][i], origin, t)
        run["verify_move"][i] = checks.verify_move(h, run["total"][i], np.shape(sources[i]),
                                                   origin)
    return run


def finish(run: dict, options: EstimateOptions) -> Estimate:
    """The :class:`Estimate` of a run through the steps: corner shifts and NCC of the final
    estimates, and the implausibility flag."""
    t = options.thresholds
    shift = checks.corner_shift(run["total"])
    ncc = np.where(np.isfinite(shift) & ~run["flat"], run["ncc"], np.nan)
    rejected = run["non_finite"] + run["singular"]
    move = run.get("verify_move", np.full(len(shift), np.nan))
    moved = checks.moved(move, None, t)
    # a run that did not record the network's own estimate: the final one (patch frames)
    network = run.get("network", run["total"])
    frames = run.get("frames", [(geometry.PATCH_SIZE,) * 2] * len(shift))
    return Estimate(
        homography=run["total"], alignment_ncc=ncc, max_corner_shift_px=shift,
        implausible=(checks.beyond(rejected, shift, ncc, t.min_alignment_ncc, t) | run["flat"]
                     | moved),
        flat=run["flat"], searched=run["searched"], found=run["found"], refined=run["refined"],
        retried=np.zeros(len(shift), bool),
        tta_choice=np.array(options.tta_symmetries)[run["choice"]],
        non_finite_stages=run["non_finite"], singular_stages=run["singular"],
        gated_stages=run["gated"], options=options, verify_move_px=move,
        move_confirmed=np.zeros(len(shift), bool),
        network_homography=network,
        network_move_px=network_moves(run["total"], network, frames, run.get("origin", (0, 0))),
        feature_start=np.zeros(len(shift), bool), corner_std_px=np.full(len(shift), np.nan),
        undetermined=np.zeros(len(shift), bool), ambiguity_gap=np.full(len(shift), np.nan),
        tile_ambiguity_gap=np.full(len(shift), np.nan), image_ncc=np.full(len(shift), np.nan))


def replacing(kept: Estimate, replaced: Estimate) -> Estimate:
    """``kept``, which takes the place of ``replaced`` (the estimates of the same pairs), with
    ``searched`` also set where the search looked at a pair in ``replaced``: the field says what
    the estimator did with the pair, whichever estimate it returns.
    """
    return dataclasses.replace(kept, searched=kept.searched | replaced.searched)


def network_moves(a_from_b, network, frame_shapes, origin) -> np.ndarray:
    """``Estimate.network_move_px``: per pair, the mean distance (px) between where the final
    ``a_from_b`` and the network's own estimate ``network`` (``[B, 3, 3]``, patch frame) map the
    corners of its ``(h, w)`` frame of ``frame_shapes`` holding the patch at ``origin``
    (:func:`~stnh_tf.inference.checks.frame_corner_distance`). Returns float64 ``[B]``.

    >>> network_moves(np.eye(3)[None], geometry.translation(3.0, 4.0)[None], [(128, 128)], (0, 0))
    array([5.])
    """
    return np.array([checks.frame_corner_distance(h, n, shape, origin)
                     for h, n, shape in zip(a_from_b, network, frame_shapes)],
                    np.float64).reshape(-1)


def estimate_once(predict: PredictStage, num_stages, patch_a, patch_b, sources, origin,
                  options: EstimateOptions) -> Estimate:
    """The network (with ``options.tta``) -> checks -> search -> refinement -> verification,
    without retry."""
    run = run_network(predict, num_stages, patch_a, patch_b, sources, origin, options)
    # the network's own estimate, and the frame its move is measured in (the source's: the patch,
    # or the 320 x 240 image holding it)
    run = dict(run, network=run["total"].copy(), origin=origin,
               frames=[np.shape(src)[:2] for src in sources])
    run = check(run, patch_a, patch_b, sources, origin, options)
    run = search(run, patch_b, sources, origin, options)
    run = refine(run, patch_b, sources, origin, options)
    run = verify(run, patch_b, sources, origin, options)
    return finish(run, options)


Take = Callable[[object], tuple]
"""``take(index) -> (patch_a, patch_b, sources)``: the pairs at ``index`` (a slice, or an array of
positions) as float32 ``[b, S, S, 1]`` patches in [0, 1] and their ``b`` sources."""


def concatenate(parts) -> Estimate:
    """The :class:`Estimate` of the pairs of ``parts`` (Estimates made with the same options), in
    order."""
    if len(parts) == 1:
        return parts[0]
    return Estimate(**{f.name: np.concatenate([getattr(p, f.name) for p in parts])
                       for f in dataclasses.fields(Estimate) if f.name != "options"},
                    options=parts[0].options)


def estimate_in_chunks(predict: PredictStage, num_stages, take: Take, num_pairs: int, origin,
                       options: EstimateOptions, chunk: int) -> Estimate:
    """:func:`estimate_pairs` on ``num_pairs`` pairs loaded by ``take``, at most ``chunk`` at a
    time, so that memory does not grow with the number of pairs: :func:`estimate_once` on
    consecutive chunks, then the retry on the flagged pairs of all chunks, ``chunk`` at a time.

    ``predict`` therefore sees the pairs in the order and groups one call over all of them would
    give it, cut only at multiples of ``chunk``: when ``predict`` runs its network in batches of
    ``n`` and ``chunk`` is a multiple of ``n``, every network batch, and so the result, is the
    same as with a single chunk."""
    chunk = max(int(chunk), 1)
    first = concatenate([estimate_once(predict, num_stages, *take(slice(i, i + chunk)), origin,
                                       options)
                         for i in range(0, num_pairs, chunk)] or
                        [estimate_once(predict, num_stages, *take(slice(0, 0)), origin, options)])
    retry = np.flatnonzero(first.implausible & ~first.flat) if options.retries else []
    if not len(retry):
        return first
    retry_options = dataclasses.replace(options, tta=options.retry_tta)
    again = concatenate([estimate_once(predict, num_stages, *take(retry[i:i + chunk]), origin,
                                       retry_options)
                         for i in range(0, len(retry), chunk)])
    merged = {}
    for f in dataclasses.fields(Estimate):
        if f.name == "options":
            continue
        value, new = getattr(first, f.name), getattr(again, f.name)
        value = value.astype(np.result_type(value, new))  # (tta_choice names may be longer)
        value[retry] = True if f.name == "retried" else new
        merged[f.name] = value
    return Estimate(**merged, options=options)


def estimate_pairs(predict: PredictStage, num_stages, patch_a, patch_b, sources, origin,
                   options: EstimateOptions, chunk: int | None = None) -> Estimate:
    """:func:`estimate_once`; then, where ``options.retries``, each pair flagged implausible (not
    flat) is estimated again with ``tta=options.retry_tta`` and keeps that estimate and its
    fields (``retried``). ``chunk``: at most this many pairs at a time
    (:func:`estimate_in_chunks`; default: all at once)."""
    def take(index):
        picked = (sources[index] if isinstance(index, slice)
                  else [sources[i] for i in index])
        return patch_a[index], patch_b[index], picked

    n = len(patch_a)
    return estimate_in_chunks(predict, num_stages, take, n, origin, options, chunk or max(n, 1))
