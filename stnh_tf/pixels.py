"""Pixel values: the one scaling between uint8 (0..255) and float in [0, 1] that every module
uses (NumPy only).

    >>> to_uint8(to_unit(np.array([0, 128, 255], np.uint8)))
    array([  0, 128, 255], dtype=uint8)
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
