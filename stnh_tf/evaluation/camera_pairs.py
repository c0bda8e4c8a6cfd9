"""The benchmark on realistic camera pairs (:mod:`stnh_tf.data.camera_motions`, issue 46), the
library core of ``experiments.benchmark_camera_pairs``.

Per group of motion size, each method's corner error, success rate and time per pair:

* ``"estimator"``: ``HomographyEstimator.estimate_images_with_info``
  (:mod:`stnh_tf.inference.estimator`) on the two gray images (the shipped default
  weights and options unless given others), and its implausibility flag as a detector of
  estimates more than ``flag_error_px`` off;
* ``"sift_ransac"``, ``"orb_ransac"``: :mod:`stnh_tf.evaluation.baselines` on the same whole
  images (``estimate_images``; their settings as on patches);
* ``"identity"``.

Errors (px), all in the frame the pairs are made in (each image's own: 320 x 240, or
``320 s x 240 s`` for a set made at ``scale`` ``s``, issue 79):
``error`` is the mean distance over the image's four corners ``(0, 0), (w, 0), (w, h),
(0, h)`` between the estimate's and the true ``h_ba``'s images of them (the MACE of the whole
image); ``patch_error`` the same over the corners of the central 128 x 128 patch of the
320 x 240 frame (both homographies brought there, :func:`work_frame`), in the patch frame (the
training's MACE). In the paper's-protocol groups
(:data:`stnh_tf.data.paper_motions.PATCH_FRAME_GROUPS`) ``error`` is ``patch_error``, the paper's
MACE: their image corners can lie beyond the horizon. Success: ``error < success_px``. The
flag's recall is the share of estimates with ``error > flag_error_px`` that are flagged
implausible; its false-alarm rate the share of the others that are flagged (``flag_patch_frame``: the same with ``patch_error``).
Times are wall-clock seconds per call (``time.perf_counter``), the estimator's after one untimed
warm-up call.
"""

from __future__ import annotations

import time

import numpy as np

from stnh_tf import geometry
from stnh_tf.data import camera_motions, camera_pair_files, paper_motions, sources
from stnh_tf.evaluation import baselines

METHODS = ("estimator", "sift_ransac", "orb_ransac", "identity", "sift_wide")
"""The methods :func:`benchmark` can run (``sift_wide``:
:data:`stnh_tf.evaluation.baselines.SIFT_WIDE_SETTINGS`, for the wide-baseline groups)."""
DEFAULT_METHODS = METHODS[:4]
"""The methods :func:`benchmark` runs by default."""
SUCCESS_PX = 3.0
FLAG_ERROR_PX = 5.0


def image_errors(h_pred, h_true, size=camera_motions.WORK_SIZE) -> np.ndarray:
    """Mean corner error ``[B]`` (px) over the corners ``(0,0), (w,0), (w,h), (0,h)`` of a
    ``size = (w, h)`` image, for image-frame ``H_ba`` ``[B, 3, 3]`` (``inf`` where not finite)."""
    w, h = size
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64)
    with np.errstate(all="ignore"):
        diff = (geometry.warp_points(np.asarray(h_pred, np.float64), corners)
                - geometry.warp_points(np.asarray(h_true, np.float64), corners))
        out = np.linalg.norm(diff, axis=-1).mean(axis=-1)
    return np.where(np.isfinite(out), out, np.inf)


def work_frame(h_ba, size) -> np.ndarray:
    """Image-frame ``H_ba`` ``[..., 3, 3]`` of two ``size = (w, h)`` images in the 320 x 240
    frame: ``R @ H @ inv(R)``, ``R`` :func:`stnh_tf.data.sources.resize_matrix` from ``size`` to
    320 x 240 (``H`` itself at that size)."""
    h_ba = np.asarray(h_ba, np.float64)
    if tuple(size) == camera_motions.WORK_SIZE:
        return h_ba
    r = sources.resize_matrix(size, camera_motions.WORK_SIZE)
    return r @ h_ba @ np.linalg.inv(r)


def patch_errors(h_pred, h_true, size=camera_motions.WORK_SIZE) -> np.ndarray:
    """Mean corner error ``[B]`` (px) of the central 128 x 128 patch
    (:data:`stnh_tf.data.camera_motions.PATCH_ORIGIN`) of the 320 x 240 frame in the patch
    frame, for image-frame ``H_ba`` ``[B, 3, 3]`` of ``size`` images (:func:`work_frame`)."""
    h_pred, h_true = work_frame(h_pred, size), work_frame(h_true, size)
    t = geometry.translation(*camera_motions.PATCH_ORIGIN)
    to_patch = lambda h: np.linalg.inv(t) @ np.asarray(h, np.float64) @ t  # noqa: E731
    with np.errstate(all="ignore"):
        out = np.asarray(geometry.corner_errors(to_patch(h_pred), to_patch(h_true)))
    return np.where(np.isfinite(out), out, np.inf)


def pair_errors(h_pred, h_true, groups, size=camera_motions.WORK_SIZE) -> tuple:
    """The benchmark's scoring of image-frame ``H_ba`` ``h_pred`` against ``h_true`` (both
    ``[B, 3, 3]``) for pairs of ``size = (w, h)`` images in ``groups`` ``[B]``:
    ``(error, patch_error)``, float64 ``[B]`` (px; ``inf`` where not finite): ``patch_error``
    :func:`patch_errors`; ``error`` :func:`image_errors`, or ``patch_error`` in the
    paper's-protocol groups (:data:`stnh_tf.data.paper_motions.PATCH_FRAME_GROUPS`)."""
    patch = patch_errors(h_pred, h_true, size)
    in_patch_frame = np.isin(np.asarray(groups), paper_motions.PATCH_FRAME_GROUPS)
    return np.where(in_patch_frame, patch, image_errors(h_pred, h_true, size)), patch


def run_estimator(estimator, pairs, options=None, warm_up: bool = True) -> dict:
    """``estimate_images_with_info`` on each pair (after one untimed call on the first, unless
    ``warm_up`` is False). Returns per pair: ``h`` ``[B, 3, 3]``, ``seconds``, ``implausible``,
    ``searched``, ``found``, ``alignment_ncc``, ``verify_move_px``, ``move_confirmed``,
    ``corner_std_px`` (NaN where the estimate has none), ``undetermined``, ``ambiguity_gap``,
    ``tile_ambiguity_gap`` and ``image_ncc`` (NaN where none)."""
    if warm_up:
        estimator.estimate_images_with_info(pairs[0].image_a, pairs[0].image_b, options)
    fields = ("implausible", "searched", "found", "alignment_ncc", "verify_move_px",
              "move_confirmed", "corner_std_px", "undetermined", "ambiguity_gap",
              "tile_ambiguity_gap", "image_ncc")
    out = {k: [] for k in ("h", "seconds") + fields}
    for p in pairs:
        t0 = time.perf_counter()
        est = estimator.estimate_images_with_info(p.image_a, p.image_b, options)
        out["seconds"].append(time.perf_counter() - t0)
        out["h"].append(est.homography[0])
        for k in fields:
            value = getattr(est, k, None)
            out[k].append(np.nan if value is None else value[0])
    return {k: np.asarray(v) for k, v in out.items()}


def run_baseline(name, pairs, warm_up: bool = True) -> dict:
    """A :data:`stnh_tf.evaluation.baselines.BASELINES` method's ``estimate_images`` on each pair
    (after one untimed call on the first, as :func:`run_estimator`, unless ``warm_up`` is False).
    Returns per pair ``h`` ``[B, 3, 3]``, ``seconds`` and ``ok`` (False: it fell back to the
    identity)."""
    method = baselines.make_baseline(name)
    if warm_up:  # (OpenCV's first call allocates; the estimator's first call is untimed too)
        method.estimate_images(pairs[0].image_a, pairs[0].image_b)
    out = {"h": [], "seconds": [], "ok": []}
    for p in pairs:
        t0 = time.perf_counter()
        h, ok = method.estimate_images(p.image_a, p.image_b)
        out["seconds"].append(time.perf_counter() - t0)
        out["h"].append(h)
        out["ok"].append(ok)
    return {k: np.asarray(v) for k, v in out.items()}


def json_ready(x):
    """JSON-ready: NaN as ``None``, an infinity as ``"inf"`` (strict JSON has neither),
    containers converted inside."""
    if isinstance(x, dict):
        return {k: json_ready(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_ready(v) for v in x]
    if isinstance(x, float) and not np.isfinite(x):
        return None if np.isnan(x) else "inf" if x > 0 else "-inf"
    return x


def _rate(num, den):
    return float(num / den) if den else None


def flag_detection(flagged, errors, flag_error_px=FLAG_ERROR_PX) -> dict:
    """The flag ``[B]`` as a detector of ``errors > flag_error_px``: ``recall`` (flagged among
    those), ``false_alarm_rate`` (flagged among the rest; ``None`` where a set is empty) and the
    counts.

    >>> flag_detection(np.array([True, False, True]), np.array([9.0, 7.0, 1.0]))["recall"]
    0.5
    """
    flagged, bad = np.asarray(flagged, bool), np.asarray(errors) > flag_error_px
    return {"bad": int(bad.sum()), "flagged": int(flagged.sum()),
            "flagged_bad": int((flagged & bad).sum()), "flagged_good": int((flagged & ~bad).sum()),
            "recall": _rate((flagged & bad).sum(), bad.sum()),
            "false_alarm_rate": _rate((flagged & ~bad).sum(), (~bad).sum())}


def summarize(run: dict, errors, patch_errs, success_px=SUCCESS_PX,
              flag_error_px=FLAG_ERROR_PX, identity_errors=None) -> dict:
    """One method's numbers on a set of pairs (``run``: :func:`run_estimator`'s or
    :func:`run_baseline`'s arrays restricted to the set); given the identity's errors on the same
    pairs, also ``worse_than_identity`` (the pairs whose error exceeds the identity's)."""
    out = {"count": int(len(errors)), "mace": float(np.mean(errors)),
           "median": float(np.median(errors)),
           "success_rate": float(np.mean(errors < success_px)),
           "patch_mace": float(np.mean(patch_errs)),
           "ms_per_pair": 1e3 * float(np.mean(run["seconds"])),
           "median_ms_per_pair": 1e3 * float(np.median(run["seconds"]))}
    if identity_errors is not None:
        out["worse_than_identity"] = int((np.asarray(errors) > identity_errors).sum())
    if "ok" in run:
        out["failure_rate"] = float(1.0 - np.mean(run["ok"]))
    if "implausible" in run:
        out.update(searched=float(np.mean(run["searched"])), found=float(np.mean(run["found"])),
                   flag=flag_detection(run["implausible"], errors, flag_error_px),
                   flag_patch_frame=flag_detection(run["implausible"], patch_errs, flag_error_px))
    return out


def benchmark(pairs, methods=DEFAULT_METHODS, estimator=None, options=None, success_px=SUCCESS_PX,
              flag_error_px=FLAG_ERROR_PX, per_pair=False) -> dict:
    """Every method of ``methods`` on ``pairs`` (:class:`~stnh_tf.data.camera_motions.CameraPair`),
    summarized per group (:data:`stnh_tf.data.camera_motions.ALL_GROUPS`, those present) and over
    ``"all"`` (:func:`summarize`, with ``worse_than_identity``). The identity, the reference of
    every summary, is run whether ``methods`` names it or not.

    Args:
      estimator: what ``"estimator"`` runs (an object with ``estimate_images_with_info``;
        ``None``: ``HomographyEstimator.load()``, the shipped default).
      options: its ``EstimateOptions`` (``None``: the estimator's own).
      per_pair: also return each pair's errors (and the estimator's flag) under ``"pairs"``.
    Raises:
      ValueError: no pairs, or an unknown method.
    """
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not len(pairs):
        raise ValueError(f"methods must be among {METHODS} (received {list(methods)}) and pairs "
                         f"must not be empty (received {len(pairs)}).")
    sizes = {p.image_a.shape[::-1] for p in pairs} | {p.image_b.shape[::-1] for p in pairs}
    if len(sizes) != 1:
        raise ValueError(f"the pairs' images must all have one size; received {sorted(sizes)}.")
    size = sizes.pop()
    h_true = np.stack([p.h_ba for p in pairs])
    groups = np.array([p.group for p in pairs])
    runs = {}
    for m in list(methods) + ([] if "identity" in methods else ["identity"]):
        if m == "estimator":
            if estimator is None:
                from stnh_tf.inference.estimator import HomographyEstimator

                estimator = HomographyEstimator.load()
            runs[m] = run_estimator(estimator, pairs, options)
        else:
            runs[m] = run_baseline(m, pairs)
    scored = {m: pair_errors(r["h"], h_true, groups, size) for m, r in runs.items()}
    errors = {m: error for m, (error, _) in scored.items()}
    patch = {m: patch_error for m, (_, patch_error) in scored.items()}
    result = {"count": len(pairs), "success_px": success_px, "flag_error_px": flag_error_px,
              "image_size": list(size),
              "error_frame": f"{size[0]} x {size[1]} image frame: mean over the image's 4 corners"
                             " (patch_mace: the central 128 x 128 patch's corners of the 320 x "
                             "240 frame, patch frame; in the groups "
                             f"{', '.join(paper_motions.PATCH_FRAME_GROUPS)} the error is "
                             "patch_mace, the paper's)",
              "groups": {}}
    for g in [g for g in camera_motions.ALL_GROUPS if g in groups] + ["all"]:
        sel = np.ones(len(pairs), bool) if g == "all" else groups == g
        result["groups"][g] = {m: summarize({k: v[sel] for k, v in r.items()}, errors[m][sel],
                                            patch[m][sel], success_px, flag_error_px,
                                            None if m == "identity" else errors["identity"][sel])
                               for m, r in runs.items()}
    if per_pair:
        result["pairs"] = [
            {"index": p.index, "group": p.group, "kind": p.kind, "offset_px": p.offset_px,
             **{f"{m}_error": float(errors[m][i]) for m in runs},
             **({"implausible": bool(runs["estimator"]["implausible"][i]),
                 "alignment_ncc": float(runs["estimator"]["alignment_ncc"][i]),
                 "verify_move_px": float(runs["estimator"]["verify_move_px"][i]),
                 "move_confirmed": bool(runs["estimator"]["move_confirmed"][i]),
                 "corner_std_px": float(runs["estimator"]["corner_std_px"][i]),
                 "undetermined": bool(runs["estimator"]["undetermined"][i]),
                 "ambiguity_gap": float(runs["estimator"]["ambiguity_gap"][i]),
                 "tile_ambiguity_gap": float(
                     runs["estimator"]["tile_ambiguity_gap"][i]),
                 "image_ncc": float(runs["estimator"]["image_ncc"][i])}
                if "estimator" in runs else {})}
            for i, p in enumerate(pairs)]
    return json_ready(result)  # (NaN measures: null; a non-finite homography's error: "inf")


def benchmark_folder(folder, methods=DEFAULT_METHODS, model=None, options=None, max_pairs: int = 0,
                     per_pair: bool = False) -> dict:
    """:func:`benchmark` on the pairs of a folder written by
    :func:`stnh_tf.data.camera_motions.write_pairs` (the first ``max_pairs``; 0: all), the
    estimator loaded from ``model`` (``None``: the shipped default); with the set's seed and
    counts and :func:`stnh_tf.evaluation.benchmarks.machine_info`."""
    from stnh_tf.evaluation import benchmarks

    manifest, pairs = camera_pair_files.load_pairs(folder)
    pairs = pairs[:max_pairs] if max_pairs else pairs
    estimator = None
    if "estimator" in methods:
        from stnh_tf.inference.estimator import HomographyEstimator

        estimator = HomographyEstimator.load(model)
    result = benchmark(pairs, methods, estimator, options, per_pair=per_pair)
    options = (options or estimator.image_options) if estimator is not None else None
    return {"folder": folder, "seed": manifest["seed"], "set_counts": manifest["counts"],
            "model": getattr(estimator, "source", None),
            "options": options.to_json() if options is not None else None, **result,
            "machine": benchmarks.machine_info()}
