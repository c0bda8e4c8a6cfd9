"""Pixel values: the one scaling between uint8 (0..255) and float in [0, 1] that every module
uses (NumPy only).

    >>> to_uint8(to_unit(np.array([0, 128, 255], np.uint8)))
    array([  0, 128, 255], dtype=uint8)
    >>> unclipped(to_unit(np.array([0, 1, 128, 254, 255], np.uint8)))
    array([False,  True,  True,  True, False])
    >>> unclipped(np.array([0.0, 128.0, 255.0]))  # not on the [0, 1] scale
    array([ True,  True,  True])
"""

from __future__ import annotations

import numpy as np


def to_unit(values, out=None) -> np.ndarray:
    """``values`` (uint8 0..255, or any real array on that scale) as float32 in [0, 1]:
    ``values / 255`` computed in float32 (the same values as ``astype(float32) / 255``), in one
    pass; written into ``out`` (float32, same shape) if given."""
    values = np.asarray(values)
    if out is None:
        out = np.empty(values.shape, np.float32)
    return np.divide(values, np.float32(255.0), out=out, dtype=np.float32)


def to_uint8(unit) -> np.ndarray:
    """Float values in [0, 1] as uint8 0..255: ``round(255 x)`` computed in float64, clipped."""
    return np.clip(np.rint(np.asarray(unit, np.float64) * 255.0), 0, 255).astype(np.uint8)


CLIP_MARGIN = 0.5 / 255
"""How near 0 or 1 a value in [0, 1] is clipped: within half a grey level of uint8."""


BINARY_SHARE = 0.02
"""Where fewer than this share of an image's values are unclipped, the image is binary (a scan,
a mask, text without anti-aliasing): its content is its 0s and 1s, and none is left out."""


def unclipped(unit) -> np.ndarray:
    """bool mask of the values of an image on the [0, 1] scale more than :data:`CLIP_MARGIN`
    from 0 and 1. A clipped pixel (black, or saturated by an exposure change) holds no intensity
    that gain and offset relate to the other image's, so the alignment measures leave it out. An
    array with values beyond [0, 1] (by more than float rounding) is on another scale, where
    nothing is known to be clipped: all True; so is a binary image (fewer than
    :data:`BINARY_SHARE` of its values unclipped), whose content the clipped values are.

    >>> bool(unclipped(np.array([0.0, 1.0] * 50)).all())  # black and white only: all kept
    True
    """
    unit = np.asarray(unit)
    if unit.size and not -1e-6 <= unit.min() <= unit.max() <= 1.0 + 1e-6:
        return np.ones(unit.shape, bool)
    mask = (unit > CLIP_MARGIN) & (unit < 1.0 - CLIP_MARGIN)
    if mask.size and mask.mean() < BINARY_SHARE:
        return np.ones(unit.shape, bool)
    return mask
