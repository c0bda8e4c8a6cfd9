"""ECC image alignment (Evangelidis & Psarakis, 2008) of a homography, coarse to fine, in float64.

The search of poorly aligned estimates (:func:`stnh_tf.inference.search.search_translations`) starts
ECC several pixels from the optimum. There, ``cv2.findTransformECC`` alone is not reproducible
across machines: it warps with bilinear weights quantized to 1/32 px, so its objective is piecewise
constant, and where it stops depends on OpenCV's per-CPU kernels (BENCHMARKS.md, "Same answer on
every machine"). :func:`coarse_to_fine_ecc` therefore aligns on a Gaussian pyramid with
:func:`ecc_homography` (the same update as OpenCV's, with exact float64 bilinear sampling) at the
coarse levels and finishes with ``cv2.findTransformECC`` at full resolution, started within a
fraction of a pixel of the optimum.

Frames: ``source_from_template`` maps template pixel coordinates ``(x, y)`` to source pixel
coordinates (``template(p) ~ source(H @ p)``), pixel centres at integer coordinates as in OpenCV;
this is ``cv2.findTransformECC``'s ``warpMatrix`` with ``templateImage=template`` and
``inputImage=source``. NumPy, SciPy and OpenCV only.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage

from stnh_tf.pixels import unclipped

MIN_INSIDE = 0.25
"""Fraction of the template's pixels that must map inside the source for an ECC iteration."""


def _homography_update(dp: np.ndarray) -> np.ndarray:
    """The 8 parameters ``[h00, h01, h02, h10, h11, h12, h20, h21]`` as a ``[3, 3]`` increment."""
    return np.array([[dp[0], dp[1], dp[2]], [dp[3], dp[4], dp[5]], [dp[6], dp[7], 0.0]])


def gradients(image) -> np.ndarray:
    """The x and y gradients ``[2, h, w]`` (float64) of ``image`` that ECC uses: 3 x 3 Sobel / 8
    (``cv2.findTransformECC``'s)."""
    image = np.asarray(image, np.float64)
    return np.stack([cv2.Sobel(image, cv2.CV_64F, 1, 0, ksize=3) / 8.0,
                     cv2.Sobel(image, cv2.CV_64F, 0, 1, ksize=3) / 8.0])


def homography_jacobian(gx, gy, x, y, u, v, w) -> np.ndarray:
    """``[N, 8]``: the derivative of the source's intensity at ``H p`` with respect to the 8
    entries ``[h00, h01, h02, h10, h11, h12, h20, h21]`` of ``H`` (``H[2, 2] = 1``), for template
    points ``p = (x, y)`` mapped to source points ``(u, v)`` with projective divisor ``w``, where
    the source's gradients there are ``(gx, gy)`` (chain rule through the projective division).

    The array is column-major (each parameter's column contiguous: a transposed ``[8, N]``),
    so that sums over the points run along memory.

    >>> homography_jacobian(*(np.array([v]) for v in (1.0, 0.0, 2.0, 3.0, 2.0, 3.0, 1.0)))[0]
    array([ 2.,  3.,  1.,  0.,  0.,  0., -4., -6.])
    """
    gw = -(gx * u + gy * v)
    out = np.empty((8, len(w)))
    for row, (g, c) in enumerate(((gx, x), (gx, y), (gx, None), (gy, x), (gy, y), (gy, None),
                                  (gw, x), (gw, y))):
        np.divide(g if c is None else np.multiply(g, c, out=out[row]), w, out=out[row])
    return out.T


def bilinear(images, u, v) -> np.ndarray:
    """``images`` ``[C, h, w]`` (float64, ``h, w >= 2``) sampled at the points ``(u, v)``
    (``[N]`` each, x and y, inside ``[0, w - 1] x [0, h - 1]``) with bilinear weights: ``[C, N]``,
    bit for bit what ``scipy.ndimage.map_coordinates(image, [v, u], order=1)`` gives for each
    image (the same products summed in the same order), in one gather for all C images (issue
    64: three such calls were a third of the search's time).

    >>> img = np.arange(12.0).reshape(1, 3, 4)
    >>> bilinear(img, np.array([0.5, 3.0]), np.array([1.25, 2.0]))
    array([[ 5.5, 11. ]])
    """
    height, width = images.shape[1:]
    # the last row / column (u = w - 1) as the far corner of the cell before it, weight 1
    x0 = np.minimum(np.floor(u), width - 2)
    y0 = np.minimum(np.floor(v), height - 2)
    wx1, wy1 = u - x0, v - y0
    wx0, wy0 = 1.0 - wx1, 1.0 - wy1
    flat = images.reshape(len(images), -1)
    top = (y0 * width + x0).astype(np.intp)
    # scipy's order: (c * w_y) * w_x, the x neighbour fastest
    out = flat.take(top, axis=1) * wy0 * wx0
    out += flat.take(top + 1, axis=1) * wy0 * wx1
    out += flat.take(top + width, axis=1) * wy1 * wx0
    out += flat.take(top + width + 1, axis=1) * wy1 * wx1
    return out


def ecc_homography(source, template, source_from_template, iterations: int = 100,
                   eps: float = 1e-6):
    """ECC maximisation of the correlation of ``template`` and ``source`` warped onto it, in float64
    with exact bilinear sampling (:func:`bilinear`).

    The update is ``cv2.findTransformECC``'s (forward additive, ``MOTION_HOMOGRAPHY``, Sobel
    gradients, no pre-filter), run on the template pixels whose position lies inside the source;
    it stops after ``iterations`` or when the correlation changes by less than ``eps``.

    Args:
      source: ``[h, w]`` image.
      template: ``[t, s]`` image (any real scale: ECC ignores gain and offset).
      source_from_template: ``[3, 3]`` start (template pixel -> source pixel).
    Returns:
      ``(H, rho)``: float64 ``[3, 3]`` ``source_from_template`` (``[2, 2] = 1``) and the zero-mean
      normalized correlation at its last evaluation; ``None`` where fewer than
      :data:`MIN_INSIDE` of the template's pixels map inside the source, the images are
      uncorrelated (ECC's step would minimise the correlation) or the update is singular.

    >>> src = cv2.GaussianBlur(np.random.default_rng(0).random((64, 64)), (0, 0), 3)
    >>> tpl = ndimage.shift(src, (-1.0, -2.5), order=1, mode="nearest")  # tpl(p) = src(p + d)
    >>> h, rho = ecc_homography(src, tpl, np.eye(3))
    >>> np.round(h[:2, 2], 2), rho > 0.999
    (array([2.5, 1. ]), True)
    """
    src = np.asarray(source, np.float64)
    tpl = np.asarray(template, np.float64)
    stack = np.concatenate([src[None], gradients(src)])
    ys, xs = np.mgrid[0:tpl.shape[0], 0:tpl.shape[1]].astype(np.float64)
    xs, ys, tpl = xs.ravel(), ys.ravel(), tpl.ravel()
    h = np.asarray(source_from_template, np.float64)
    h = h / h[2, 2]
    rho = previous = -np.inf
    for _ in range(iterations):
        w = h[2, 0] * xs + h[2, 1] * ys + 1.0
        with np.errstate(all="ignore"):
            u = (h[0, 0] * xs + h[0, 1] * ys + h[0, 2]) / w
            v = (h[1, 0] * xs + h[1, 1] * ys + h[1, 2]) / w
        inside = ((w > 1e-6) & (u >= 0) & (u <= src.shape[1] - 1) & (v >= 0)
                  & (v <= src.shape[0] - 1))
        if inside.mean() < MIN_INSIDE:
            return None
        if inside.all():  # (the same values without copying them)
            x, y, t = xs, ys, tpl
        else:
            x, y, u, v, w, t = (a[inside] for a in (xs, ys, u, v, w, tpl))
        warped, gx, gy = bilinear(stack, u, v)
        # d warped / d parameters, row-major: the mean below sums each column in the points' order
        jac = np.ascontiguousarray(homography_jacobian(gx, gy, x, y, u, v, w))
        jac -= jac.mean(axis=0)
        warped -= warped.mean()
        t = t - t.mean()
        warped_norm, t_norm = np.linalg.norm(warped), np.linalg.norm(t)
        if warped_norm < 1e-12 or t_norm < 1e-12:
            return None
        rho = float(warped @ t / (warped_norm * t_norm))
        if abs(rho - previous) < eps:
            break
        previous = rho
        try:
            inv_hessian = np.linalg.inv(jac.T @ jac)
        except np.linalg.LinAlgError:
            return None
        warped_proj, t_proj = jac.T @ warped, jac.T @ t
        numerator = warped_norm ** 2 - warped_proj @ inv_hessian @ warped_proj
        denominator = warped @ t - t_proj @ inv_hessian @ warped_proj
        if denominator <= 0:
            return None
        step = inv_hessian @ (jac.T @ (numerator / denominator * t - warped))
        h = h + _homography_update(step)
    if not np.all(np.isfinite(h)) or abs(h[2, 2]) < 1e-12:
        return None
    return h / h[2, 2], rho


def opencv_ecc(source, template, source_from_template, iterations: int, eps: float):
    """``cv2.findTransformECC`` (``MOTION_HOMOGRAPHY``, no Gaussian pre-filter) of float32 images
    from the start ``source_from_template``: float64 ``[3, 3]`` (``[2, 2] = 1``), or ``None``
    where OpenCV does not converge or the result is not finite. Where a pixel of either image is clipped
    (:func:`stnh_tf.pixels.unclipped`), ``cv2.findTransformECCWithMask`` with both images'
    masks of the pixels not clipped instead."""
    start = np.asarray(source_from_template, np.float64)
    if not np.all(np.isfinite(start)) or abs(start[2, 2]) < 1e-12:
        return None
    template, source = np.asarray(template, np.float32), np.asarray(source, np.float32)
    start = (start / start[2, 2]).astype(np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, iterations, eps)
    masks = [unclipped(template), unclipped(source)]
    try:
        if all(m.all() for m in masks):
            _, warp = cv2.findTransformECC(template, source, start, cv2.MOTION_HOMOGRAPHY,
                                           criteria, None, 1)
        else:  # clipped pixels left out of both images
            _, warp = cv2.findTransformECCWithMask(
                template, source, *(m.astype(np.uint8) for m in masks), start,
                cv2.MOTION_HOMOGRAPHY, criteria, 1)
    except cv2.error:
        return None
    warp = warp.astype(np.float64)
    if not np.all(np.isfinite(warp)) or abs(warp[2, 2]) < 1e-12:
        return None
    return warp / warp[2, 2]


def coarse_to_fine_ecc(source, template, source_from_template, coarse_iterations=(100, 50),
                       fine_iterations: int = 100, eps: float = 1e-6, fine_eps: float = 1e-5):
    """ECC on a Gaussian pyramid: :func:`ecc_homography` on ``len(coarse_iterations)`` levels
    halved by ``cv2.pyrDown`` (coarsest first, that many iterations each), then
    :func:`opencv_ecc` at full resolution.

    A coarse level that fails leaves the estimate as it was for the next level. Pixel ``j`` of a
    level is pixel ``2 j`` of the one below (``cv2.pyrDown``), so level ``L`` aligns
    ``S H S^-1`` with ``S = diag(2^-L, 2^-L, 1)``.

    Args:
      source, template, source_from_template: as in :func:`ecc_homography`.
    Returns:
      float64 ``[3, 3]`` ``source_from_template`` (``[2, 2] = 1``), or ``None`` where the
      full-resolution ECC does not converge.
    """
    sources = [np.asarray(source, np.float64)]
    templates = [np.asarray(template, np.float64)]
    for _ in coarse_iterations:
        sources.append(cv2.pyrDown(sources[-1]))
        templates.append(cv2.pyrDown(templates[-1]))
    h = np.asarray(source_from_template, np.float64)
    for level, iterations in zip(range(len(coarse_iterations), 0, -1), coarse_iterations):
        scale = np.diag([0.5 ** level, 0.5 ** level, 1.0])
        result = ecc_homography(sources[level], templates[level],
                                scale @ h @ np.linalg.inv(scale), iterations, eps)
        if result is not None:
            h = np.linalg.inv(scale) @ result[0] @ scale
            h = h / h[2, 2]
    return opencv_ecc(source, template, h, fine_iterations, fine_eps)
