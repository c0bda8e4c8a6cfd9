"""Whether another alignment of the two images scores about as well as the estimate: a repeated
pattern (a checkerboard, a tiled wall, a facade's windows, blinds) aligns as well one period off,
where the NCC and the corner precision call a wrong estimate good (issue 79, item 3). Two views
of it: shifts of the whole warped image (:func:`ambiguity_gap`; a pattern seen head-on) and shifts
of each 80 x 80 tile of it (:func:`tile_ambiguity_gap`; a pattern seen in perspective, whose
period changes across the image so that no single shift aligns it). NumPy and OpenCV only.
"""

from __future__ import annotations

import cv2
import numpy as np

from stnh_tf import geometry
from stnh_tf.inference.checks import warped_onto

AMBIGUITY_SHIFT_PX = 80
""":func:`ambiguity_gap`'s reach, px at the 320 x 240 work size (a longer period is not seen)."""
AMBIGUITY_MIN_SHIFT_PX = 8
"""A peak nearer the estimate than this is its own peak's shoulder."""
AMBIGUITY_MIN_SHARE = 0.5
"""A shift counts where it compares this share of the estimate's pixels."""
TILE_PX, TILE_SHIFT_PX = 80, 32
""":func:`tile_ambiguity_gap`'s tiles (px at the work size) and their reach."""
TILE_MIN_NCC, TILE_VALLEY = 0.5, 0.2
""":func:`tile_ambiguity_gap`: a tile counts where it aligns with NCC at least ``TILE_MIN_NCC``
under the estimate; another peak counts where the NCC between the two dips ``TILE_VALLEY`` below
the estimate's (a smooth tile, aligned about as well by every shift, has no second peak)."""


def overlap_ncc(image, covered, template, reach: int) -> tuple:
    """Masked NCC (Padfield 2012; OpenCV's ``matchTemplate`` masks the template alone):
    ``score[reach + dy, reach + dx]`` is the NCC of ``template(p)`` with
    ``image(p + (reach + dx, reach + dy))`` over the ``p`` of the template where ``covered`` holds
    there, ``count`` their number.

    Args:
      template: ``[h, w]``.
      image, covered: ``[h + 2 reach, w + 2 reach]``, the template's frame with a margin of
        ``reach`` on every side (zeros with ``covered`` False where nothing lies there); covered
        is bool, the image's valid pixels.
      reach: the largest shift along each axis, px.
    Returns:
      ``(score, count)``, float64 ``[2 reach + 1, 2 reach + 1]``; the score is NaN where either
      side is constant over the pixels compared or none is.

    >>> img = np.random.default_rng(0).random((60, 80))
    >>> score, count = overlap_ncc(np.pad(img, 5), np.pad(np.ones((60, 80), bool), 5),
    ...                            np.roll(img, 3, axis=1), 5)
    >>> round(float(score[5, 2]), 6), int(count[5, 2]), bool(score[5, 5] < 0.2)
    (1.0, 4620, True)
    """
    h, w = np.shape(template)
    covered = np.asarray(covered, bool)
    if not covered.any():
        return np.full((2 * reach + 1,) * 2, np.nan), np.zeros((2 * reach + 1,) * 2)
    image, template = np.asarray(image, np.float32), np.asarray(template, np.float32)
    values = image[covered]  # standardized: float32 sums keep the NCC's digits
    # a circular correlation over this size wraps nothing around within the reach
    size = (cv2.getOptimalDFTSize(h + 2 * reach), cv2.getOptimalDFTSize(w + 2 * reach))
    a, mask, b = (np.zeros(size, np.float32) for _ in range(3))
    a[:h + 2 * reach, :w + 2 * reach] = np.where(
        covered, (image - values.mean()) / (values.std() or 1.0), 0)
    mask[:h + 2 * reach, :w + 2 * reach] = covered
    b[:h, :w] = (template - template.mean()) / (template.std() or 1.0)
    spectra = [cv2.dft(x) for x in (a, mask, b, b * b)]

    def correlate(i, j):  # sum over p of x_i(p + k) x_j(p), at k = reach + s within the reach
        c = cv2.idft(cv2.mulSpectrums(spectra[i], spectra[j], 0, conjB=True),
                     flags=cv2.DFT_SCALE | cv2.DFT_REAL_OUTPUT)
        return c[:2 * reach + 1, :2 * reach + 1].astype(np.float64)

    def box_sums(x):  # the sum over every h x w window of x
        s = cv2.integral(x[:h + 2 * reach, :w + 2 * reach], sdepth=cv2.CV_64F)
        return s[h:, w:] - s[:-h, w:] - s[h:, :-w] + s[:-h, :-w]

    count, sum_a, sum_aa = box_sums(mask), box_sums(a), box_sums(a * a)
    sum_ab, sum_b, sum_bb = correlate(0, 2), correlate(1, 2), correlate(1, 3)
    with np.errstate(all="ignore"):
        cov = sum_ab - sum_a * sum_b / count
        var = (sum_aa - sum_a ** 2 / count) * (sum_bb - sum_b ** 2 / count)
        score = np.where(var > 1e-9 * count ** 2, cov / np.sqrt(var), np.nan)
    return score, np.rint(count)


def _warped(work_a, work_b, a_from_b, origin):
    """``(work_b as float32, warped, covered)`` (:func:`~stnh_tf.inference.checks.warped_onto`),
    or ``None`` where the estimate maps the patch to no finite place."""
    with np.errstate(all="ignore"):
        if not np.isfinite(geometry.patch_to_image(a_from_b, *origin)).all():
            return None
    b = np.asarray(work_b, np.float32)
    return (b, *warped_onto(work_a, a_from_b, origin, b.shape))


def _peaks(scores, count, reach):
    """The distinct other peaks of a score map: local maxima (5 x 5) at least
    :data:`AMBIGUITY_MIN_SHIFT_PX` from the centre comparing at least :data:`AMBIGUITY_MIN_SHARE`
    of the centre's pixels; ``[k, 2]`` indices."""
    ys, xs = np.mgrid[-reach:reach + 1, -reach:reach + 1]
    filled = np.where(np.isfinite(scores), scores, -np.inf).astype(np.float32)
    return np.argwhere((filled == cv2.dilate(filled, np.ones((5, 5), np.uint8)))
                       & (np.hypot(xs, ys) >= AMBIGUITY_MIN_SHIFT_PX) & np.isfinite(scores)
                       & (count >= AMBIGUITY_MIN_SHARE * count[reach, reach]))


def ambiguity_gap(work_a, work_b, a_from_b, origin=(0, 0), min_overlap: float = 0.3) -> float:
    """How much better the patch-frame ``a_from_b`` aligns ``work_b`` with ``work_a`` than
    any distinct other shift of it: work_a is warped onto work_b's frame by the estimate and
    the NCC of work_b with it, each time over the pixels that the warped work_a covers, is taken
    at every shift up to :data:`AMBIGUITY_SHIFT_PX` (:func:`overlap_ncc`); the result is the NCC
    at the estimate (the best within 1 px) less the highest local maximum (5 x 5) at least
    :data:`AMBIGUITY_MIN_SHIFT_PX` away among the shifts that compare at least
    :data:`AMBIGUITY_MIN_SHARE` as many pixels as the estimate. A repeated pattern, which aligns
    as well one period off, gives about 0 (below 0 where another shift aligns better: the estimate
    is a period off); a photograph, whose NCC falls away from the estimate, 0.1 or more.

    Args:
      work_a, work_b: ``[h, w]`` images; the patch has its top-left corner at ``origin`` in both.
      a_from_b: ``[3, 3]`` pixel ``H_ba`` in the patch frame.
      min_overlap: the share of work_b that work_a must cover under the estimate.
    Returns:
      The gap (NCC units, at most 2); NaN where the estimate covers less than ``min_overlap``,
      is not finite, or the NCC at it is undefined (a flat image); 1.0 where no other peak exists.

    >>> ys, xs = np.mgrid[0:240, 0:320]
    >>> board = ((xs // 16 + ys // 16) % 2).astype(np.float64)
    >>> abs(ambiguity_gap(board, board, np.eye(3), (96, 56))) < 1e-4
    True
    >>> smooth = cv2.GaussianBlur(np.random.default_rng(0).random((240, 320)), (0, 0), 2)
    >>> ambiguity_gap(smooth, smooth, np.eye(3), (96, 56)) > 0.5
    True
    """
    if (warp := _warped(work_a, work_b, a_from_b, origin)) is None:
        return float("nan")
    b, warped, covered = warp
    if covered.mean() < min_overlap:
        return float("nan")
    r = AMBIGUITY_SHIFT_PX
    scores, count = overlap_ncc(np.pad(warped, r), np.pad(covered, r), b, r)
    own = scores[r - 1:r + 2, r - 1:r + 2]
    if not np.isfinite(own).any():
        return float("nan")
    peaks = _peaks(scores, count, r)
    return (float(np.nanmax(own)) - float(scores[tuple(peaks.T)].max()) if len(peaks)
            else 1.0)


def tile_ambiguity_gap(work_a, work_b, a_from_b, origin=(0, 0)) -> float:
    """:func:`ambiguity_gap` tile by tile: the median over work_b's :data:`TILE_PX` square tiles
    (a grid from the top-left corner) of how much better the estimate aligns the tile than the
    best other shift (up to :data:`TILE_SHIFT_PX`) that a valley of the NCC separates from it.
    A pattern in perspective repeats at a period that changes across the image: no one shift of
    the whole aligns it one period off, each tile's does. Tiles count where work_a covers 90% of
    them under the estimate, they are not constant and they align with NCC at least
    :data:`TILE_MIN_NCC`.

    Args:
      work_a, work_b, a_from_b, origin: as :func:`ambiguity_gap`.
    Returns:
      The median gap (NCC units; a tile without a second peak counts 1.0); NaN where fewer than
      3 tiles count or the estimate is not finite.

    >>> ys, xs = np.mgrid[0:240, 0:320]
    >>> stripes = np.sin(2 * np.pi * (xs + 0.002 * xs * ys) / 20)  # a period growing downwards
    >>> float(tile_ambiguity_gap(stripes, stripes, np.eye(3), (96, 56))) < 0.05
    True
    """
    if (warp := _warped(work_a, work_b, a_from_b, origin)) is None:
        return float("nan")
    b, warped, covered = warp
    r, t = TILE_SHIFT_PX, TILE_PX
    warped, covered = np.pad(warped, r), np.pad(covered, r)
    steps = np.linspace(0.0, 1.0, 24)
    gaps = []
    for y in range(0, b.shape[0] - t + 1, t):
        for x in range(0, b.shape[1] - t + 1, t):
            tile = b[y:y + t, x:x + t]
            if covered[y + r:y + r + t, x + r:x + r + t].mean() < 0.9 or tile.std() == 0:
                continue
            scores, count = overlap_ncc(warped[y:y + t + 2 * r, x:x + t + 2 * r],
                                        covered[y:y + t + 2 * r, x:x + t + 2 * r], tile, r)
            own = scores[r - 1:r + 2, r - 1:r + 2]
            own = own[np.isfinite(own)].max(initial=-np.inf)
            if not own >= TILE_MIN_NCC:  # (a tile flat in either image: none aligns)
                continue
            other = -np.inf
            for py, px in _peaks(scores, count, r):
                line = scores[np.rint(r + steps * (py - r)).astype(int),
                              np.rint(r + steps * (px - r)).astype(int)]
                if own - np.nanmin(line) >= TILE_VALLEY:  # a second peak, not a ridge
                    other = max(other, scores[py, px])
            gaps.append(own - other if np.isfinite(other) else 1.0)
    return float(np.median(gaps)) if len(gaps) >= 3 else float("nan")
