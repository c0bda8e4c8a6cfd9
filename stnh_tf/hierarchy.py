"""Hierarchical STN-Homography (paper section 4): stages run one after another with an OpenCV warp
between them, each refining the composed estimate of the ones before.

Conventions (see :mod:`stnh_tf.geometry` and ``docs/conventions.md``):

* Every homography here is a **pixel** ``H_ba`` in the patch frame (patch_b -> patch_a).
* ``context_a`` is the ``(S + 2m) x (S + 2m)`` crop of image_a around the square (``m = 32``),
  so patch_a is ``context_a[m:m+S, m:m+S]`` and a patch-frame point ``p`` lies at ``p + (m, m)``
  in the context.
* Stage k sees ``patch_a_k(p) = patch_a(H_prev @ p)`` with ``H_prev = H_1 @ ... @ H_{k-1}``, read
  from the context (image content, not zeros, beyond the patch border):
  ``warpPerspective(context_a, T_m @ H_prev, (S, S), flags=WARP_INVERSE_MAP | INTER_LINEAR)``.
  Its target is the residual ``H_k* = inv(H_prev) @ H_ba``; the estimate after stage k is
  ``H_prev @ H_k``.

**Degenerate-prediction rule** (one rule, used by evaluation and by stage-data generation), on
the composed estimate ``H = H_prev @ H_k``:

* non-finite, or near-singular (``|det| < 1e-6`` after scaling to ``[2,2] = 1``, or a patch
  corner mapped to ``w <= 0``, behind the camera): the prediction is replaced by the identity,
  the estimate stays ``H_prev`` (reasons ``non_finite``, ``singular``);
* a patch corner mapped outside the stored context (more than ``m`` pixels beyond the patch):
  those corners are clipped onto the context's border and ``H`` is refitted to the four corners
  (``cv2.getPerspectiveTransform``), so a nearly right estimate is kept rather than discarded and
  the next stage never samples beyond the context (reason ``outside_context``; if the refit is
  itself degenerate, the identity rule applies).

Each case is counted by reason. The clipping is post-processing that is not in the paper: it uses
the protocol's knowledge that true corners move at most ``m`` pixels, and lowers hierarchy MACE
slightly. ``clip_to_context=False`` (``experiments.evaluate --no_clip``) keeps such estimates as
they are (still counted as ``outside_context``; the next stage then reads zeros beyond the
context), so MACE can be reported without it.

NumPy/OpenCV only; the stage models are called through a ``predict`` function so that this module
imports no deep-learning backend.
"""

from __future__ import annotations

import concurrent.futures
import os
import threading
from typing import Callable, Sequence

import cv2
import numpy as np

from stnh_tf import geometry

CONTEXT_MARGIN = geometry.MAX_PERTURBATION
"""Margin (pixels) of image_a stored around the square on every side."""

REJECT_REASONS = ("non_finite", "singular", "outside_context")
MIN_SCALE = 1e-12
"""Below this ``|H[2, 2]|`` a composed pixel estimate is ``"non_finite"``
(:func:`rejection_reason`)."""
MIN_DET = 1e-6
"""Below this ``|det H|`` (``H[2, 2] = 1``) a composed pixel estimate is ``"singular"``."""
MIN_W = 1e-9
"""At or below this homogeneous coordinate at a patch corner (the corner maps to infinity or
behind the camera) a composed pixel estimate is ``"singular"``."""


def warp_crop(source: np.ndarray, a_from_b: np.ndarray, origin=(0, 0),
              size: int = geometry.PATCH_SIZE, fill: str = "zeros") -> np.ndarray:
    """``out(p) = source(T @ H @ p)`` on the ``size x size`` grid, ``T`` the translation by
    ``origin`` (where the patch's top-left corner lies in ``source``): bilinear, zero outside
    ``source`` (``fill="zeros"``) or ``source`` mirrored about its border pixels
    (``fill="reflect"``, :data:`stnh_tf.geometry.FILLS`).

    The one inter-stage warp of the hierarchy: with ``source`` the stored context and
    ``origin = (m, m)`` it re-crops ``patch_a_k``; with the whole image and the square's corner it
    is the same warp with all of image_a as context; with the patch itself and ``(0, 0)`` it is
    ``patch(H @ p)``, zero beyond the patch.

    Args:
      source: ``[h, w]`` (uint8 or float) image holding patch_a at ``origin``.
      a_from_b: ``[3, 3]`` pixel ``H_ba`` in the patch frame (patch_b -> patch_a).
    Returns:
      ``[size, size]`` float32, same value range as ``source``.
    """
    border = {"zeros": cv2.BORDER_CONSTANT, "reflect": cv2.BORDER_REFLECT_101}[
        geometry.check_fill(fill)]
    h = geometry.translation(*origin) @ np.asarray(a_from_b, np.float64)
    return cv2.warpPerspective(np.asarray(source, np.float32), h, (size, size),
                               flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR,
                               borderMode=border, borderValue=0)


def crop_warped_context(context_a: np.ndarray, h_prev: np.ndarray, margin: int = CONTEXT_MARGIN,
                        size: int = geometry.PATCH_SIZE) -> np.ndarray:
    """``patch_a_k(p) = patch_a(H_prev @ p)`` read from the stored context (zero beyond it).

    Args:
      context_a: ``[S + 2m, S + 2m]`` (uint8 or float) crop of image_a around the square.
      h_prev: ``[3, 3]`` pixel ``H_ba`` in the patch frame (patch_b -> patch_a).
    Returns:
      ``[S, S]`` float32, same value range as ``context_a``.
    """
    return warp_crop(context_a, h_prev, (margin, margin), size)


def residual_target(h_prev: np.ndarray, h_ba: np.ndarray) -> np.ndarray:
    """``H_k* = inv(H_prev) @ H_ba`` (``[..., 3, 3]``), scaled so ``[2,2] = 1``."""
    return geometry.scale_to_unit(np.linalg.inv(np.asarray(h_prev, np.float64))
                                  @ np.asarray(h_ba, np.float64))


def stage_pair(context_a: np.ndarray, h_ba: np.ndarray, h_prev: np.ndarray,
               margin: int = CONTEXT_MARGIN, size: int = geometry.PATCH_SIZE) -> dict:
    """The next stage's training pair for one stored sample, given the accepted estimate so far.

    ``patch_a_k(p) = patch_a(H_prev @ p)`` re-cropped from the context; the residual target
    ``H_k* = inv(H_prev) @ H_ba`` as ``h_bar`` (normalized with the paper's ``M``); and
    ``patch_a_t_k`` = ``patch_a_k`` warped by ``H_k*`` (zero outside patch_a_k: what the stage's
    spatial transformer sees, so the L1 target matches it). Patches are rounded to uint8, as
    stored in TFRecords. One sample of :func:`stage_pairs`.

    Returns:
      ``{"patch_a": uint8 [S, S], "patch_a_t": uint8 [S, S], "h_bar": float32 [8]}``.
    """
    pairs = stage_pairs(np.asarray(context_a)[None], np.asarray(h_ba, np.float64)[None],
                        np.asarray(h_prev, np.float64)[None], margin, size)
    return {key: value[0] for key, value in pairs.items()}


def stage_pairs(context_a: np.ndarray, h_ba: np.ndarray, h_prev: np.ndarray,
                margin: int = CONTEXT_MARGIN, size: int = geometry.PATCH_SIZE,
                out: dict | None = None) -> dict:
    """:func:`stage_pair` for a batch: the matrix work on the whole batch at once, the two OpenCV
    warps per pair, the patches written into ``out``.

    Args:
      context_a: ``[N, S+2m, S+2m]`` uint8 (0..255, as stored); h_ba, h_prev: ``[N, 3, 3]``
        pixel homographies in the patch frame (patch_b -> patch_a).
      out: arrays to write into (``patch_a``, ``patch_a_t`` uint8 ``[N, S, S]``, ``h_bar``
        float32 ``[N, 8]``, e.g. row slices of larger arrays); new ones when ``None``.
    Returns:
      ``out``: ``{"patch_a": uint8 [N, S, S], "patch_a_t": uint8 [N, S, S], "h_bar": float32
      [N, 8]}``.
    Raises:
      ValueError: a context of another dtype (a float one on [0, 1] became 0/1 patches).
    """
    if np.asarray(context_a).dtype != np.uint8:
        raise ValueError(f"context_a must be uint8 (0..255, as the TFRecords store it); received "
                         f"{np.asarray(context_a).dtype}.")
    n = len(context_a)
    if out is None:
        out = {"patch_a": np.empty((n, size, size), np.uint8),
               "patch_a_t": np.empty((n, size, size), np.uint8),
               "h_bar": np.empty((n, 8), np.float32)}
    residual = residual_target(h_prev, h_ba)
    out["h_bar"][...] = geometry.matrix_to_vector(
        geometry.normalize_homography(residual, size, size))
    for i in range(n):
        patch_a = crop_warped_context(context_a[i], h_prev[i], margin, size)
        patch_a_t = cv2.warpPerspective(patch_a, residual[i], (size, size),
                                        flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR,
                                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        _to_uint8(patch_a, out["patch_a"][i])
        _to_uint8(patch_a_t, out["patch_a_t"][i])
    return out


def _to_uint8(x: np.ndarray, out: np.ndarray) -> None:
    """``out[...] = clip(rint(x), 0, 255)`` as uint8, as TFRecords store patches."""
    np.rint(x, out=x)
    np.clip(x, 0, 255, out=x)
    out[...] = x


def rejection_reason(h_composed: np.ndarray, margin: int = CONTEXT_MARGIN,
                     size: int = geometry.PATCH_SIZE) -> str | None:
    """Why a composed estimate ``[3, 3]`` breaks the degenerate-prediction rule, or ``None``."""
    h = np.asarray(h_composed, np.float64)
    if not np.all(np.isfinite(h)) or abs(h[2, 2]) < MIN_SCALE:
        return "non_finite"
    h = h / h[2, 2]
    corners = np.concatenate([geometry.patch_corners(size), np.ones((4, 1))], axis=1)
    mapped = corners @ h.T
    if abs(np.linalg.det(h)) < MIN_DET or np.any(mapped[:, 2] <= MIN_W):
        return "singular"
    xy = mapped[:, :2] / mapped[:, 2:3]
    if np.any(xy < -margin) or np.any(xy > size + margin):
        return "outside_context"
    return None


def _clip_to_context(h: np.ndarray, margin: int, size: int) -> np.ndarray:
    """Refit ``h`` after clipping the patch corners it maps into ``[-m, S + m]^2``."""
    corners = geometry.patch_corners(size).astype(np.float32)
    mapped = cv2.perspectiveTransform(corners[None].astype(np.float64), h)[0]
    clipped = np.clip(mapped, -margin, size + margin).astype(np.float32)
    return cv2.getPerspectiveTransform(corners, clipped).astype(np.float64)


def accept_or_reject(h_prev: np.ndarray, h_stage: np.ndarray, margin: int = CONTEXT_MARGIN,
                     size: int = geometry.PATCH_SIZE, clip_to_context: bool = True):
    """Apply the degenerate-prediction rule to a batch.

    Args:
      h_prev: ``[N, 3, 3]`` composed estimate so far; h_stage: ``[N, 3, 3]`` this stage's output.
      clip_to_context: refit estimates whose corners leave the context onto its border (default,
        the rule used to generate stage data); ``False`` keeps them unclipped (still reported as
        ``outside_context``).
    Returns:
      ``(h_composed [N, 3, 3], reasons)``: ``h_prev @ h_stage`` (scaled to ``[2,2] = 1``) where
      accepted; refitted to the context where corners left it (unless ``clip_to_context`` is
      False); ``h_prev`` where non-finite or singular. ``reasons`` holds ``None`` or a reason
      from :data:`REJECT_REASONS` per sample.
    """
    h_prev = np.asarray(h_prev, np.float64)
    with np.errstate(all="ignore"):
        composed = h_prev @ np.asarray(h_stage, np.float64)
    out, reasons = [], []
    for prev, h in zip(h_prev, composed):
        reason = rejection_reason(h, margin, size)
        if reason == "outside_context" and clip_to_context:
            h = _clip_to_context(h / h[2, 2], margin, size)
            if rejection_reason(h, margin + 1e-3, size) is not None:
                reason = "singular"
        out.append(prev if reason in ("non_finite", "singular") else h / h[2, 2])
        reasons.append(reason)
    return np.stack(out), reasons


PredictFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``predict(patch_a [N,S,S,1] float32 in [0,1], patch_b [N,S,S,1]) -> pixel H [N,3,3]``."""


def run_hierarchy(stages: Sequence[PredictFn], context_a: np.ndarray, patch_b: np.ndarray,
                  h_init: np.ndarray | None = None, margin: int = CONTEXT_MARGIN,
                  size: int = geometry.PATCH_SIZE, clip_to_context: bool = True) -> dict:
    """Run ``n`` stages on a batch as the paper does (OpenCV warp of the context between stages).

    Args:
      stages: one predict function per stage (each returns the stage's pixel ``H_k``).
      context_a: ``[N, S+2m, S+2m]`` uint8 (0..255) or float in [0, 1].
      patch_b: ``[N, S, S]`` or ``[N, S, S, 1]``, uint8 (0..255) or float in [0, 1] (each input
        is scaled by its own dtype).
      h_init: ``[N, 3, 3]`` estimate to start from (identity when ``None``).
      clip_to_context: see :func:`accept_or_reject` (``False``: no clipping onto the context).
    Returns:
      ``{"h": [N,3,3] composed H_ba after all stages, "per_stage": [n x [N,3,3]] estimate after
      each stage, "rejected": [n x {reason: count}]}``.
    """
    context_a = np.asarray(context_a)
    patch_b = np.asarray(patch_b)
    scale = 255.0 if context_a.dtype == np.uint8 else 1.0
    # Scaled in place (astype already copies): no second [N, S, S] float array per batch.
    scale_b = 255.0 if patch_b.dtype == np.uint8 else 1.0
    patch_b = patch_b.astype(np.float32).reshape(len(context_a), size, size, 1)
    np.divide(patch_b, scale_b, out=patch_b)
    h = (np.repeat(np.eye(3)[None], len(context_a), 0) if h_init is None
         else np.asarray(h_init, np.float64).copy())
    per_stage, rejected = [], []
    for predict in stages:
        patch_a = np.stack([crop_warped_context(c, hp, margin, size)
                            for c, hp in zip(context_a, h)])
        np.divide(patch_a, scale, out=patch_a)
        h_stage = np.asarray(predict(patch_a[..., None], patch_b), np.float64)
        h, reasons = accept_or_reject(h, h_stage, margin, size, clip_to_context)
        per_stage.append(h.copy())
        rejected.append({r: reasons.count(r) for r in REJECT_REASONS})
    return {"h": h, "per_stage": per_stage, "rejected": rejected}


def next_stage_arrays(arrays: dict, stages: Sequence[PredictFn], chunk: int = 1024,
                      margin: int = CONTEXT_MARGIN, size: int = geometry.PATCH_SIZE,
                      threads: int = 0, in_place: bool = False, estimates=None,
                      estimates_dtype=np.float64):
    """Stage-``n+1`` training pairs, in memory, from stage-1 pairs and ``n`` trained stages.

    The in-memory counterpart of ``data_prep.make_stage_dataset`` chained ``n`` times: the stages
    run as at test time (:func:`run_hierarchy`, degenerate-prediction rule included) on each
    pair's ``context_a`` and ``patch_b``, and :func:`stage_pair` builds the pair from the
    composed estimate. For ``n = 1`` the result equals make_stage_dataset's records from the
    stage-1 records; for ``n > 1`` the intermediate ``patch_a`` is not rounded to uint8 between
    stages (as at test time; the TFRecord chain stores rounded patches).

    Args:
      arrays: stage-1 pairs in :func:`stnh_tf.data.batches.stack_samples`' compact form with context
        (``patch_a``, ``patch_b``, ``patch_a_t`` uint8 ``[N, S, S]``, ``h_bar``, ``h_mask``,
        ``context_a`` uint8 ``[N, S+2m, S+2m]``, ``h_ba`` ``[N, 3, 3]``).
      stages: the trained stages 1..n as :data:`PredictFn`
        (e.g. :func:`stnh_tf.modeling.runner.predictor`).
      chunk: pairs per model call batch; threads: chunks processed at once (0: one per core).
      in_place: write the new ``patch_a``, ``patch_a_t`` and ``h_bar`` over those of ``arrays``
        (which the re-making does not read), so no second copy of them is held.
      estimates: ``h_prev [N, 3, 3]`` of an earlier call on the same pairs: the pairs are made
        from it and ``stages`` are not called (``rejected`` then counts nothing).
      estimates_dtype: the composed estimates are rounded to this dtype before the pairs are made
        from them (``np.float32``: as saved for a later call with ``estimates``, which then gives
        the same pairs to the bit).
    Returns:
      ``(pairs, rejected)``: ``pairs`` in the compact form (``patch_a``, ``patch_b``,
      ``patch_a_t``, ``h_bar``, ``h_mask``, plus ``h_prev [N, 3, 3]``, the estimate the pair
      starts from); ``rejected`` counts the degenerate-rule cases of every stage by reason.
    """
    n = len(arrays["patch_b"])
    if estimates is not None and np.shape(estimates) != (n, 3, 3):
        raise ValueError(f"estimates of shape {np.shape(estimates)} for {n} pairs; expected "
                         f"({n}, 3, 3).")
    made = ("patch_a", "patch_a_t", "h_bar")
    out = {key: arrays[key] if in_place or key not in made else np.empty_like(arrays[key])
           for key in ("patch_a", "patch_b", "patch_a_t", "h_bar", "h_mask")}
    out["h_prev"] = np.empty((n, 3, 3))
    lock = threading.Lock()
    stages = [_serialized(predict, lock) for predict in stages]

    def one_chunk(a):
        b = min(a + chunk, n)
        if estimates is None:
            run = run_hierarchy(stages, arrays["context_a"][a:b], arrays["patch_b"][a:b],
                                margin=margin, size=size)
            out["h_prev"][a:b] = run["h"].astype(estimates_dtype)
        else:
            run = {"rejected": []}
            out["h_prev"][a:b] = estimates[a:b]
        stage_pairs(arrays["context_a"][a:b], arrays["h_ba"][a:b], out["h_prev"][a:b], margin,
                    size, out={key: out[key][a:b] for key in made})
        return run["rejected"]

    # Chunks run in threads (OpenCV's warps and NumPy's large array operations release the GIL;
    # the model calls are serialized); each chunk writes its own rows, so the result does not
    # depend on the thread count.
    rejected = dict.fromkeys(REJECT_REASONS, 0)
    with concurrent.futures.ThreadPoolExecutor(threads or os.cpu_count() or 1) as pool:
        for per_stage in pool.map(one_chunk, range(0, n, chunk)):
            for counts in per_stage:
                for reason, count in counts.items():
                    rejected[reason] += count
    return out, rejected


def _serialized(predict: PredictFn, lock) -> PredictFn:
    def call(patch_a, patch_b):
        with lock:
            return predict(patch_a, patch_b)

    return call
