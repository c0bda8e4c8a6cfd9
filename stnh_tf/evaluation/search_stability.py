"""Does the estimator give the same answer on every machine? Its estimates on OpenCV's optimized
and unoptimized code paths (``cv2.setUseOptimized``: the per-CPU SIMD kernels and the portable
ones), and the search of poorly aligned estimates started from slightly moved network estimates
(``experiments.benchmark_search_stability``; numbers in BENCHMARKS.md, "Same answer on every
machine")."""

from __future__ import annotations

import time

import cv2
import numpy as np

from stnh_tf import geometry

DIFFER_PX = 0.1
"""Mean corner distance (px, patch frame) above which two estimates of a pair count as different."""


def _moved(a_from_b, px, rng):
    """``a_from_b`` with each patch corner's image moved by ``px`` in a random direction."""
    corners = geometry.patch_corners()
    angle = rng.uniform(0, 2 * np.pi, size=4)
    moved = geometry.warp_points(a_from_b, corners) + px * np.stack([np.cos(angle),
                                                                     np.sin(angle)], axis=1)
    return geometry.homography_from_points(corners, moved)


def search_stability(estimator, patch_a, patch_b, h_ba, perturbations=(0.01, 0.1, 0.3),
                     seed=0) -> dict:
    """The default ``estimator.estimate`` of float32 ``[B, 128, 128, 1]`` pairs on both OpenCV
    paths, and :func:`stnh_tf.inference.search.search_translations` from the network's estimates
    moved by each of ``perturbations`` px (optimized path).

    Returns a dict: ``pairs``; per path (``optimized``, ``unoptimized``) ``mace``, ``searched``,
    ``found`` and ``seconds``; ``differ_between_paths`` (pairs whose estimates are more than
    :data:`DIFFER_PX` apart); ``searched_network`` (pairs the search takes on from the
    optimized path's network estimates) and ``differ_moved_{px}px`` (those whose search result
    differs by more than :data:`DIFFER_PX` from the unmoved one's; not found counts as the
    network estimate).
    """
    from stnh_tf.inference import checks, search
    from stnh_tf.inference.options import EstimateOptions

    was_optimized = cv2.useOptimized()
    out, estimates = {"pairs": int(len(h_ba))}, {}
    try:
        for path, optimized in (("optimized", True), ("unoptimized", False)):
            cv2.setUseOptimized(optimized)
            start = time.perf_counter()
            result = estimator.estimate_with_info(patch_a, patch_b, EstimateOptions())
            estimates[path] = result.homography
            out[path] = {"mace": float(geometry.mean_corner_error(estimates[path], h_ba)),
                         "searched": int(result.searched.sum()),
                         "found": int(result.found.sum()),
                         "seconds": round(time.perf_counter() - start, 2)}
        out["differ_between_paths"] = int((geometry.corner_errors(
            estimates["optimized"], estimates["unoptimized"]) > DIFFER_PX).sum())
        cv2.setUseOptimized(True)
        options = EstimateOptions(search="none")
        result = estimator.estimate_with_info(patch_a, patch_b, options)
        network, shift, t = result.homography, result.max_corner_shift_px, options.thresholds
        searched = np.flatnonzero(~result.flat & np.isfinite(shift) & checks.beyond(
            result.rejected_stages, shift, result.alignment_ncc, t.search_below_ncc, t))
        out["searched_network"] = int(len(searched))

        def search_all(moved_px, rng):
            results = []
            for i in searched:
                start = network[i] if not moved_px else _moved(network[i], moved_px, rng)
                found = search.search_translations(patch_a[i, ..., 0], patch_b[i, ..., 0],
                                                   start, thresholds=t)
                results.append(network[i] if found is None else found[0])
            return np.array(results).reshape(-1, 3, 3)

        reference = search_all(0.0, None)
        for px in perturbations:
            moved = search_all(px, np.random.default_rng(seed))
            out[f"differ_moved_{px}px"] = int((geometry.corner_errors(moved, reference)
                                               > DIFFER_PX).sum())
    finally:
        cv2.setUseOptimized(was_optimized)
    return out
