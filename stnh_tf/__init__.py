"""stnh-tf: STN-Homography (Zhou & Li, 2019) in TensorFlow/Keras.

Conventions live in :mod:`stnh_tf.geometry` (NumPy-only import); Keras pieces are imported
lazily, so data-generation workers that only need geometry never import a deep-learning backend.
"""

import importlib

__version__ = "0.1.0"

_LAZY = {
    "SpatialTransformer": "stnh_tf.layers",
    "HomographyMerge": "stnh_tf.layers",
    "HomographyEstimator": "stnh_tf.inference",
}

__all__ = ["geometry", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    if name in ("geometry", "layers", "data", "models", "training", "evaluation"):
        return importlib.import_module(f"stnh_tf.{name}")
    raise AttributeError(f"module 'stnh_tf' has no attribute {name!r}")
