"""Uncertainty of a mean corner error at the level the data varies: the photograph.

The pairs of a test set come several to a photograph (``data_prep.make_dataset``'s
``--samples_per_image``, 3 in the paper), and the pairs of one photograph share its texture, so
their errors are not independent: the standard error over pairs (``mace_se`` of
:func:`stnh_tf.evaluation.mace.error_summary`) understates how much the MACE would change on
other photographs. :func:`by_photograph` resamples whole photographs instead.
"""

from __future__ import annotations

import numpy as np

BOOTSTRAP_RESAMPLES = 2000
"""Bootstrap resamples of :func:`by_photograph`: the Monte Carlo error of its standard error is
about ``1 / sqrt(2 * 2000)``, 1.6 % of it, and that of its 2.5 and 97.5 percentiles about as
small against the interval's width."""

BOOTSTRAP_SEED = 0
"""The seed of :func:`by_photograph`'s resamples (fixed: the same pairs give the same interval)."""

_DRAWS_PER_CHUNK = 1 << 22  # photograph draws held in memory at once (32 MiB of int64)


def by_photograph(errors, photograph_ids, resamples: int = BOOTSTRAP_RESAMPLES,
                  seed: int = BOOTSTRAP_SEED) -> dict:
    """Percentile-bootstrap 95 % interval and standard error of the mean of ``errors``, with the
    photograph as the unit resampled.

    What is resampled: the P distinct photographs (``photograph_ids``) are drawn P times with
    replacement, and every draw brings all of that photograph's pairs; the statistic of a
    resample is the mean error over the pairs it holds (photographs with more pairs weigh more,
    as in the MACE itself). ``resamples`` such means, from ``numpy.random.default_rng(seed)``,
    give the standard error (their standard deviation, ``ddof=1``) and the interval (their 2.5th
    and 97.5th percentiles, NumPy's linear interpolation). With one pair per photograph this is
    the ordinary bootstrap over pairs; its standard error then approaches the plug-in
    ``std(errors, ddof=0) / sqrt(N)``, i.e. ``mace_se`` times ``sqrt((N - 1) / N)``.

    Args:
      errors: per-pair corner errors (px), ``[N]``.
      photograph_ids: the photograph of each pair, ``[N]`` (any hashable dtype NumPy sorts:
        the stored ``image_id`` strings).
      resamples: bootstrap resamples (>= 2).
      seed: the resamples' seed.
    Returns:
      ``{"photographs": P, "mace_se_by_photograph": float, "mace_ci95_by_photograph": [lo, hi]}``;
      both ``None`` with fewer than 2 photographs (nothing to resample).
    Raises:
      ValueError: ``errors`` and ``photograph_ids`` of different shapes or not 1-D, no pairs, or
        ``resamples`` < 2.
    """
    errors = np.asarray(errors, np.float64)
    ids = np.asarray(photograph_ids)
    if errors.ndim != 1 or ids.shape != errors.shape:
        raise ValueError(f"errors and photograph_ids must be 1-D of one length; received shapes "
                         f"{errors.shape} and {ids.shape}.")
    if errors.size == 0:
        raise ValueError("no pairs to evaluate.")
    if resamples < 2:
        raise ValueError(f"resamples must be >= 2; received {resamples}.")
    _, photograph = np.unique(ids, return_inverse=True)
    sums = np.bincount(photograph, weights=errors)
    counts = np.bincount(photograph).astype(np.float64)
    p = len(sums)
    if p < 2:
        return {"photographs": p, "mace_se_by_photograph": None, "mace_ci95_by_photograph": None}
    rng = np.random.default_rng(seed)
    chunk = max(1, _DRAWS_PER_CHUNK // p)
    means = []
    for start in range(0, resamples, chunk):
        draws = rng.integers(0, p, size=(min(chunk, resamples - start), p))
        means.append(sums[draws].sum(axis=1) / counts[draws].sum(axis=1))
    means = np.concatenate(means)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return {"photographs": p, "mace_se_by_photograph": float(means.std(ddof=1)),
            "mace_ci95_by_photograph": [float(lo), float(hi)]}
