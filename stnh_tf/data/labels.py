"""Which training pairs keep their ground truth: the seeded label draw of ``label_fraction``.

The paper keeps the L1 photometric loss so that training can go on where a pair has no ground-
truth ``H_bar`` (section 4.2): such a pair gets ``h_mask`` 0 and trains on the L1 term alone.
A run with ``label_fraction=F`` keeps the label of pair ``i`` (its global ``index``: the
TFRecords' ``index`` feature, :class:`stnh_tf.data.batches.PairBatches`' sample index, the same
for the same images and seed) iff

    draw(seed, i) < round(F * 2**32),

``draw`` being a fixed 32-bit integer hash (:func:`label_draws`). The decision is per pair and
stateless: the same pairs on resume, in any batch order, from TFRecords or from generated pairs
(fresh pairs of the same image slot share its decision), the sets nested in ``F``
(``F = 0.1``'s labeled pairs are among ``F = 0.2``'s). The labeled share of ``N`` pairs is ``F``
up to the binomial spread ``sqrt(F (1 - F) / N)`` (0.2 % of 21,900 pairs at ``F = 0.1``);
``F = 1`` labels every pair, ``F = 0`` none.

NumPy only; :func:`tf_labeled` is the same function in TensorFlow (imported when called), for
``tf.data`` pipelines. Both compute in int64 with every value below ``2**32`` and multipliers
below ``2**31``, so no product overflows and the two agree bit for bit.

    >>> int(labeled(0, np.arange(10_000), 0.1).sum())  # of 10,000 pairs, seed 0
    1012
    >>> bool(labeled(0, np.arange(8), 1.0).all()), bool(labeled(0, np.arange(8), 0.0).any())
    (True, False)
"""

from __future__ import annotations

import math

import numpy as np

MASK32 = 0xFFFFFFFF
_SALT = 0x6C61626C  # "labl": the label draw is not the pair generator's RNG stream
_MUL1, _MUL2 = 0x7FEB352D, 0x6C8E9CF5  # odd, < 2**31


def _mix(x, xor, shr):
    """A 32-bit integer mix (xor-shift-multiply, the structure of Wellons' lowbias32) of int64
    values in ``[0, 2**32)``; ``xor`` and ``shr`` are the backend's bitwise operations."""
    x = xor(x, shr(x, 16))
    x = (x * _MUL1) % (MASK32 + 1)
    x = xor(x, shr(x, 15))
    x = (x * _MUL2) % (MASK32 + 1)
    return xor(x, shr(x, 16))


def _np_xor(a, b):
    return np.bitwise_xor(a, b)


def _np_shr(a, n):
    return np.right_shift(a, n)


def label_draws(seed: int, index) -> np.ndarray:
    """The draws ``draw(seed, i)`` of pair indices ``index`` (any int array): int64 in
    ``[0, 2**32)``, a pure function of ``(seed, i mod 2**32)``."""
    s = _mix(np.int64((int(seed) ^ _SALT) & MASK32), _np_xor, _np_shr)
    i = np.asarray(index, np.int64) & MASK32
    return _mix(_mix(np.bitwise_xor(i, s), _np_xor, _np_shr), _np_xor, _np_shr)


def threshold(fraction: float) -> int:
    """``round(fraction * 2**32)``: a draw below it is labeled (``2**32`` labels every draw).

    Raises:
      ValueError: ``fraction`` is not a finite number in [0, 1].
    """
    f = float(fraction)
    if not (math.isfinite(f) and 0.0 <= f <= 1.0):
        raise ValueError(f"label_fraction must be a number in [0, 1]; received {fraction!r}.")
    return int(round(f * (MASK32 + 1)))


def labeled(seed: int, index, fraction: float) -> np.ndarray:
    """Whether pairs ``index`` keep their label under ``fraction`` and ``seed``: bool array of
    ``index``'s shape (see the module docstring)."""
    return label_draws(seed, index) < threshold(fraction)


def tf_labeled(seed: int, index, fraction: float):
    """:func:`labeled` in TensorFlow: ``index`` an integer tensor (any shape) -> bool tensor,
    equal to :func:`labeled` on the same values (for ``tf.data`` maps and filters)."""
    import tensorflow as tf

    xor, shr = tf.bitwise.bitwise_xor, tf.bitwise.right_shift
    s = int(_mix(np.int64((int(seed) ^ _SALT) & MASK32), _np_xor, _np_shr))
    i = tf.bitwise.bitwise_and(tf.cast(index, tf.int64), tf.constant(MASK32, tf.int64))
    draws = _mix(_mix(xor(i, tf.constant(s, tf.int64)), xor, shr), xor, shr)
    return draws < tf.constant(threshold(fraction), tf.int64)
