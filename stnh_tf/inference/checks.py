"""The estimator's checks of an estimate: how far it moves the patch corners, how well it aligns
the pair (:func:`alignment_ncc`), flat patches, and the rule that flags an estimate implausible
(:func:`beyond`). NumPy and OpenCV only; the numbers come from
:class:`~stnh_tf.inference.options.Thresholds`.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from stnh_tf import geometry, hierarchy
from stnh_tf.inference import ecc
from stnh_tf.inference.options import Thresholds
from stnh_tf.pixels import unclipped

_DEFAULT = Thresholds()


def corner_shift(a_from_b) -> np.ndarray:
    """Largest displacement ``|H c - c|`` (px) of the four 128 x 128 patch corners ``c`` under each
    ``a_from_b`` ``[B, 3, 3]`` (patch frame); ``inf`` where a corner maps to infinity or NaN.
    Returns float64 ``[B]``.

    >>> corner_shift(geometry.translation(3.0, -4.0)[None])
    array([5.])
    """
    corners = geometry.patch_corners(geometry.PATCH_SIZE)
    with np.errstate(all="ignore"):
        moved = geometry.warp_points(np.asarray(a_from_b, np.float64), corners)
        shift = np.linalg.norm(moved - corners, axis=-1).max(axis=-1)
    return np.where(np.isfinite(shift), shift, np.inf)


def frame_corner_distance(a_from_b, other, source_shape, origin=(0, 0)) -> float:
    """Mean distance (px) between where two patch-frame ``a_from_b`` ``[3, 3]`` map the corners
    ``(0, 0), (w, 0), (w, h), (0, h)`` of ``source_a``'s ``[h, w]`` frame (the patch has its
    top-left corner at ``origin`` there): their corner error in the frame the estimate is made
    in (the patch itself, or the 320 x 240 image of ``estimate_images``). ``inf`` where a corner
    maps to infinity.

    >>> frame_corner_distance(np.eye(3), geometry.translation(3.0, 4.0), (240, 320), (96, 56))
    5.0
    """
    height, width = source_shape[:2]
    return point_distance(a_from_b, other, [(0, 0), (width, 0), (width, height), (0, height)],
                          origin)


def point_distance(a_from_b, other, points, origin=(0, 0)) -> float:
    """Mean distance (px) between where two patch-frame ``a_from_b`` ``[3, 3]`` map ``points``
    (``(u, v)`` of the frame whose patch has its top-left corner at ``origin``); ``inf`` where
    a point maps to infinity.

    >>> point_distance(np.eye(3), geometry.translation(3.0, 4.0), [(96, 56)], (96, 56))
    5.0
    """
    t = geometry.translation(*origin)
    points = np.asarray(points, np.float64)
    with np.errstate(all="ignore"):
        d = (geometry.warp_points(t @ np.asarray(a_from_b, np.float64) @ np.linalg.inv(t), points)
             - geometry.warp_points(t @ np.asarray(other, np.float64) @ np.linalg.inv(t), points))
        out = float(np.linalg.norm(d, axis=-1).mean())
    return out if np.isfinite(out) else float("inf")


TRAINED_ZOOM = 1.0 + geometry.MAX_PERTURBATION / (geometry.PATCH_SIZE / 2)
"""The largest zoom out of the trained range (1.5): every corner of the 128 x 128 patch moved
outwards by 32 px in x and in y."""


def verify_move(optimum, a_from_b, source_shape, origin=(0, 0)) -> float:
    """``verify="ecc"``'s move (px): how far ``optimum``, the ECC alignment started from the
    patch-frame ``a_from_b`` (both ``[3, 3]``), lies from it in image_a at the points where
    :func:`corner_std` measures the precision (:func:`precision_corners`: the corners of the
    ``[h, w]`` frame, or the patch's where a frame corner maps beyond image_a's horizon, where
    any two estimates lie infinitely far apart; issue 79), or, where ``a_from_b`` zooms out beyond
    the trained range (:func:`~stnh_tf.geometry.centre_scale` above :data:`TRAINED_ZOOM`), in
    image_b, the coarser image, at the frame's four corners (against where ``a_from_b``'s
    inverse maps ``optimum``'s images of them back): there one pixel of image_b spans several of image_a's and
    ECC fixes the alignment no finer than that (issue 64). ``inf`` where ECC failed
    (``optimum`` None) or a corner maps to infinity.

    >>> zoom_out = np.diag([2.0, 2.0, 1.0])  # image_b sees image_a at half its size
    >>> round(verify_move(zoom_out @ geometry.translation(1.0, 0.0), zoom_out, (240, 320)), 6)
    1.0
    """
    if optimum is None:
        return float("inf")
    h, optimum = np.asarray(a_from_b, np.float64), np.asarray(optimum, np.float64)
    height, width = source_shape[:2]
    h_image = geometry.patch_to_image(h, *origin)
    if not geometry.centre_scale(h_image, (width, height)) > TRAINED_ZOOM:
        return point_distance(optimum, h, precision_corners(h_image, source_shape, origin),
                              origin)
    return frame_corner_distance(np.linalg.inv(h) @ optimum, np.eye(3), source_shape, origin)


def moved(verify_move_px, move_confirmed=None,
          thresholds: Thresholds = _DEFAULT) -> np.ndarray:
    """``verify="ecc"``'s part of the flag, per pair: the move ``verify_move_px`` ``[B]`` is
    above ``thresholds.max_verify_move`` (or ``inf``: ECC did not converge) and
    ``move_confirmed`` ``[B]`` (``None``: none) does not excuse it; False where not verified
    (NaN).

    >>> moved(np.array([1.0, 9.0, 9.0, np.inf, np.nan]), np.array([0, 0, 1, 0, 0], bool))
    array([False,  True, False,  True, False])
    """
    move = np.asarray(verify_move_px, np.float64)
    out = ~np.isnan(move) & ~(move <= thresholds.max_verify_move)
    if move_confirmed is not None:
        out &= ~np.asarray(move_confirmed, bool)
    return out


MIN_SQUARES_PER_PARAMETER = 4
""":func:`corner_std` with ``tile``: over fewer squares than this many per parameter (32 for the
8 of a homography) the cluster-robust covariance is not estimable (its rank is at most the
number of squares) and the classical one is used."""


@functools.lru_cache(maxsize=4)
def _pixel_grid(height: int, width: int) -> np.ndarray:
    """``[3, h * w]`` float64 ``(x, y, 1)`` of every pixel, row by row (read-only, made once per
    shape: :func:`corner_std` runs on every pair)."""
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    grid = np.stack([xs.ravel(), ys.ravel(), np.ones(height * width)])
    grid.flags.writeable = False
    return grid


@functools.lru_cache(maxsize=4)
def _squares(height: int, width: int, tile: int) -> np.ndarray:
    """``[h * w]`` the square of :func:`corner_std`'s ``tile`` x ``tile`` grid each pixel lies in,
    row by row (read-only, made once per shape and tile)."""
    ys, xs = np.mgrid[0:height, 0:width]
    square = ((ys // tile) * (width // tile + 1) + xs // tile).ravel().astype(np.intp)
    square.flags.writeable = False
    return square


def precision_corners(a_from_b, image_b_shape, origin=(0, 0)) -> list:
    """The points ``(u, v)`` of image_b at which :func:`corner_std` measures how precisely the
    images fix the image-frame ``a_from_b`` ``[3, 3]``: image_b's corners ``(0, 0), (w, 0),
    (w, h), (0, h)`` (``[h, w]`` frame) where ``a_from_b`` maps them all in front of image_a's
    horizon, on the side of the patch's centre (the patch's top-left corner at ``origin``); else
    the patch's own corners (``origin`` + those of the 128 x 128 square), the paper's frame: a
    corner beyond the horizon has no position in image_a, and its precision is infinite for any
    estimate, right or wrong (issue 79).

    >>> precision_corners(np.eye(3), (240, 320), (96, 56))
    [(0.0, 0.0), (320.0, 0.0), (320.0, 240.0), (0.0, 240.0)]
    >>> tilted = np.array([[1.0, 0, 0], [0, 1.0, 0], [-0.004, 0, 1.0]])  # horizon at u = 250
    >>> precision_corners(tilted, (240, 320), (96, 56))
    [(96.0, 56.0), (224.0, 56.0), (224.0, 184.0), (96.0, 184.0)]
    """
    h = np.asarray(a_from_b, np.float64)
    height, width = image_b_shape[:2]
    x0, y0 = float(origin[0]), float(origin[1])
    size = float(geometry.PATCH_SIZE)
    side = np.sign(h[2] @ [x0 + size / 2, y0 + size / 2, 1.0]) or 1.0
    if geometry.in_front(side * h, (width + 1, height + 1)):  # its corner pixels: (w, h) here
        return [(0.0, 0.0), (float(width), 0.0), (float(width), float(height)),
                (0.0, float(height))]
    return [(x0, y0), (x0 + size, y0), (x0 + size, y0 + size), (x0, y0 + size)]


MIN_UNCLIPPED = 100
"""Fewest pixels, overlapping and clipped in neither image, that an alignment NCC is measured
over (:func:`alignment_ncc`, :func:`stnh_tf.inference.coarse.image_ncc`)."""


def corner_std(source_a, image_b, a_from_b, origin=(0, 0), min_pixels: int = 100,
               tile: int = 0) -> float:
    """How precisely the two images fix ``a_from_b`` at ``image_b``'s corners: the predicted
    standard deviation (px, mean over the corners ``(0, 0), (w, 0), (w, h), (0, h)`` of
    ``image_b``'s ``[h, w]`` frame, or, where some of them map beyond image_a's horizon, over
    the patch's corners: :func:`precision_corners`) of where the homography maps them, from the
    Gauss-Newton
    covariance of the least-squares alignment of ``image_b`` with ``source_a`` warped by it.

    Over every pixel ``q`` of ``image_b`` that lands inside ``source_a`` (1 px from its border),
    ``image_b(q) ~ g source_a(H q) + o`` (gain and offset fitted); the residual variance
    ``s2`` and the Jacobian ``J`` of the warped intensities with respect to the 8 entries of
    ``H`` (``H[2, 2] = 1``; ECC's gradients and Jacobian, :mod:`stnh_tf.inference.ecc`) give
    the covariance ``s2 (J^T J)^-1``, propagated to the corners. Where image_a covers little of image_b, or is
    featureless there, a small alignment error at the overlap becomes a large one at the corners:
    the number says so. A statistical lower bound, not the error (independent pixel noise).
    With ``tile`` > 0 the covariance is the cluster-robust (sandwich) one over squares of
    ``tile`` x ``tile`` pixels of ``image_b``, ``A^-1 (sum_t s_t s_t^T) A^-1`` (``A = g^2 J^T J``,
    ``s_t`` the sum of ``g J^T r`` over square ``t``): residuals correlated within a square
    (blur, JPEG blocks, noise filtered by the camera, a misfit of the model) count as they
    spread the estimate, not as independent pixels.

    Args:
      source_a: ``[h_a, w_a]`` image holding patch_a with its top-left corner at ``origin``.
      image_b: ``[h, w]`` image holding patch_b at ``origin`` (the same frame convention).
      a_from_b: ``[3, 3]`` pixel ``H_ba`` in the patch frame.
      min_pixels: fewer pixels of image_b inside source_a, clipped in neither image
        (:func:`stnh_tf.pixels.unclipped`: they are left out): ``inf``.
      tile: side (px) of the squares of the cluster-robust covariance; 0, or fewer squares
        than :data:`MIN_SQUARES_PER_PARAMETER` per parameter inside source_a: the classical
        one.
    Returns:
      The predicted standard deviation (px); ``inf`` where it is undefined (too few pixels, a
      singular system, a corner mapped to infinity).

    >>> a = cv2.GaussianBlur(np.random.default_rng(0).random((240, 320)), (0, 0), 2)
    >>> noisy = a + np.random.default_rng(1).normal(0, 0.01, a.shape)
    >>> bool(corner_std(a, a, np.eye(3)) < 1e-6 < corner_std(a, noisy, np.eye(3)) < 0.1)
    True
    """
    a = np.asarray(source_a, np.float64)
    b = np.asarray(image_b, np.float64)
    t = geometry.translation(*origin)
    with np.errstate(all="ignore"):
        h = t @ np.asarray(a_from_b, np.float64) @ np.linalg.inv(t)
    if not np.isfinite(h).all() or abs(h[2, 2]) < 1e-12:
        return float("inf")
    h = h / h[2, 2]
    centre = np.add(origin, geometry.PATCH_SIZE / 2)
    if h[2] @ [centre[0], centre[1], 1.0] < 0:
        h = -h  # the same homography, its scale positive at the patch's centre (issue 79)
    height, width = b.shape[:2]
    grid = _pixel_grid(height, width)
    u, v = grid[0], grid[1]
    p = h @ grid
    w = p[2]
    inside = w > 1e-9
    with np.errstate(all="ignore"):
        x, y = p[0] / w, p[1] / w
    inside &= (x >= 1) & (x < a.shape[1] - 2) & (y >= 1) & (y < a.shape[0] - 2)
    if inside.sum() < min_pixels:
        return float("inf")
    maps = [np.where(inside, c, -10.0).astype(np.float32).reshape(height, width) for c in (x, y)]
    # image_a and its two gradients sampled in one call, as three channels
    channels = np.dstack([a, *ecc.gradients(a)]).astype(np.float32)
    sampled = cv2.remap(channels, *maps, cv2.INTER_LINEAR).reshape(-1, 3)[inside]
    a_q, gx, gy = sampled.T.astype(np.float64)
    b_q = b.ravel()[inside]
    kept = unclipped(a_q) & unclipped(b_q)
    if kept.sum() < min_pixels:
        return float("inf")
    if not kept.all():
        inside[inside] = kept
        a_q, gx, gy, b_q = a_q[kept], gx[kept], gy[kept], b_q[kept]
    a_c = a_q - a_q.mean()
    gain = float(a_c @ (b_q - b_q.mean())) / max(float(a_c @ a_c), 1e-300)  # least squares
    residual = b_q - b_q.mean() - gain * a_c
    u, v, x, y, w = u[inside], v[inside], x[inside], y[inside], w[inside]
    jac = ecc.homography_jacobian(gx, gy, u, v, x, y, w)  # (b's points map to a's)
    try:
        a_inv = np.linalg.inv(gain * gain * (jac.T @ jac))
    except np.linalg.LinAlgError:
        return float("inf")
    cov = float(np.var(residual)) * a_inv
    if tile > 0:  # the scores summed per square of image_b, then their outer products
        square = _squares(height, width, tile)[inside]
        present = np.bincount(square) > 0
        if present.sum() >= MIN_SQUARES_PER_PARAMETER * jac.shape[1]:
            index = (np.cumsum(present) - 1)[square]  # the squares numbered in order, as unique's
            weighted = np.multiply(jac, gain, out=jac)  # gain * jac * residual, in place
            weighted *= residual[:, None]
            # bincount adds in the pixels' order, as np.add.at would (the same sums), 10x faster
            scores = np.stack([np.bincount(index, weights=weighted[:, k])
                               for k in range(jac.shape[1])], axis=1)
            cov = a_inv @ (scores.T @ scores) @ a_inv
    stds = []
    for cu, cv in precision_corners(h, b.shape, origin):
        pc = h @ [cu, cv, 1.0]
        if abs(pc[2]) < 1e-12:
            return float("inf")
        cx, cy = pc[0] / pc[2], pc[1] / pc[2]
        j_x = np.array([cu, cv, 1.0, 0.0, 0.0, 0.0, -cx * cu, -cx * cv]) / pc[2]
        j_y = np.array([0.0, 0.0, 0.0, cu, cv, 1.0, -cy * cu, -cy * cv]) / pc[2]
        stds.append(np.sqrt(max(float(j_x @ cov @ j_x), 0.0) + max(float(j_y @ cov @ j_y), 0.0)))
    out = float(np.mean(stds))
    return out if np.isfinite(out) else float("inf")


def warped_onto(work_a, a_from_b, origin, shape_b) -> tuple:
    """``work_a`` warped onto image_b's ``[h, w]`` frame (``shape_b``) by the patch-frame
    ``a_from_b`` (the patch's top-left corner at ``origin`` in both): ``(warped, covered)``,
    float32 ``[h, w]`` ``warped(p) = work_a(H p)`` (bilinear, 0 beyond work_a) and the bool mask
    of the pixels whose source lies inside work_a (``H`` the image-frame estimate,
    :func:`~stnh_tf.geometry.patch_to_image`)."""
    h = geometry.patch_to_image(a_from_b, *origin)
    size = (shape_b[1], shape_b[0])
    flags = cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR
    a = np.asarray(work_a, np.float32)
    warped = cv2.warpPerspective(a, h, size, flags=flags)
    return warped, cv2.warpPerspective(np.ones_like(a), h, size, flags=flags) > 0.999


def alignment_ncc(source_a, patch_b, a_from_b, origin=(0, 0),
                  min_overlap: float = _DEFAULT.min_overlap) -> float:
    """Normalized cross-correlation between ``patch_b`` and patch_a warped onto it by ``a_from_b``,
    over the pixels whose position ``a_from_b @ p`` lies inside ``source_a``.

    Args:
      source_a: ``[h, w]`` image holding patch_a with its top-left corner at ``origin`` (the patch
        itself with ``(0, 0)``, or the image it was cut from as context).
      patch_b: ``[S, S]`` (any real scale; NCC ignores gain and offset).
      a_from_b: ``[3, 3]`` pixel ``H_ba`` in the patch frame.
      min_overlap: the fraction of the pixels that must overlap.
    Returns:
      NCC in [-1, 1] over the overlapping pixels clipped in neither image
      (:func:`stnh_tf.pixels.unclipped`): 1 for a perfect alignment up to gain and offset, about
      0 for unrelated content; NaN where fewer than ``min_overlap`` of the pixels overlap, fewer
      than :data:`MIN_UNCLIPPED` of them are not clipped, or either side is constant there.

    >>> p = np.random.default_rng(0).random((128, 128))
    >>> round(alignment_ncc(p, 2 * p + 1, np.eye(3)), 6)
    1.0
    """
    size = np.shape(patch_b)[0]
    warped = hierarchy.warp_crop(source_a, a_from_b, origin, size).astype(np.float64)
    inside = hierarchy.warp_crop(np.ones(np.shape(source_a), np.float32), a_from_b, origin,
                                 size) > 0.999
    if inside.mean() < min_overlap:
        return float("nan")
    inside &= unclipped(patch_b) & unclipped(warped)
    if inside.sum() < MIN_UNCLIPPED:
        return float("nan")
    x = warped[inside] - warped[inside].mean()
    y = np.asarray(patch_b, np.float64)[inside]
    y = y - y.mean()
    norm = np.sqrt((x * x).sum() * (y * y).sum())
    return float((x * y).sum() / norm) if norm > 1e-12 else float("nan")


def alignment_nccs(sources, patches_b, a_from_b, origin, min_overlap=_DEFAULT.min_overlap):
    """:func:`alignment_ncc` of each pair (``patches_b`` ``[B, S, S, 1]``) as float64 ``[B]``,
    NaN (undefined) as ``-inf`` so that it ranks below every defined NCC."""
    return np.nan_to_num([alignment_ncc(src, b[..., 0], h, origin, min_overlap)
                          for src, b, h in zip(sources, patches_b, a_from_b)], nan=-np.inf)


def beyond(rejected_stages, shift, ncc, min_ncc, thresholds: Thresholds = _DEFAULT):
    """Per pair ``[B]``: a stage was skipped as degenerate, a corner moved beyond
    ``thresholds.implausible_corner_shift``, or the alignment NCC is below ``min_ncc`` or
    undefined. With ``min_ncc = thresholds.min_alignment_ncc`` it is the implausibility rule,
    with ``thresholds.search_below_ncc`` the search's trigger.

    >>> beyond(np.array([0, 1, 0]), np.array([1.0, 1.0, 60.0]), np.array([0.9, 0.9, 0.9]), 0.7)
    array([False,  True,  True])
    """
    return ((np.asarray(rejected_stages) > 0) | (shift > thresholds.implausible_corner_shift)
            | ~(ncc >= min_ncc))


def flat_pairs(patch_a, patch_b, min_std: float = _DEFAULT.min_patch_std) -> np.ndarray:
    """Per pair ``[B]`` of float ``[B, S, S, 1]`` patches on [0, 1]: patch_a or patch_b varies less
    than ``min_std`` (it holds nothing to align)."""
    return (patch_a.std(axis=(1, 2, 3)) < min_std) | (patch_b.std(axis=(1, 2, 3)) < min_std)
