"""stnh-tf: STN-Homography (Zhou & Li, 2019) in TensorFlow/Keras.

The layers of the package, each importing only the ones above it (``tests/test_layout.py``):

* the NumPy core at the top: :mod:`stnh_tf.geometry` (every convention), :mod:`stnh_tf.pixels`,
  :mod:`stnh_tf.paths`, :mod:`stnh_tf.hierarchy`, and :mod:`stnh_tf.startup` for the binaries;
* :mod:`stnh_tf.modeling`: Keras layers, models, losses, model kinds, and the one way to run a
  model;
* :mod:`stnh_tf.data.tfrecords`: image sources, the pair protocol, generated batches, TFRecords;
* :mod:`stnh_tf.training.loop`: the run's configuration, folder, input streams and loop;
* :mod:`stnh_tf.inference.estimator`: the estimator for users, its inputs, model files and export;
* :mod:`stnh_tf.evaluation.mace`: MACE, the classical baselines, benchmarks;
* :mod:`stnh_tf.paper`: the paper's tables and figures, and the demo.

Keras is imported lazily, so data-generation workers that only need the NumPy core never import
a deep-learning backend. Once Keras is imported (before or after this package), this package's
layers, losses and metric are registered with it
(:func:`stnh_tf.modeling.register_keras_objects`, a post-import hook), so that after
``import stnh_tf`` a plain ``keras.models.load_model(path)`` opens the shipped models and any
model trained here (docs/weights.md).
"""

import importlib

import wrapt

__version__ = "0.1.0"

_LAZY = {
    "SpatialTransformer": "stnh_tf.modeling.layers",
    "HomographyMerge": "stnh_tf.modeling.layers",
    "HomographyEstimator": "stnh_tf.inference.estimator",
}
_SUBPACKAGES = ("geometry", "data", "training", "evaluation", "inference")

__all__ = ["geometry", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    if name in _SUBPACKAGES:
        return importlib.import_module(f"stnh_tf.{name}")
    raise AttributeError(f"module 'stnh_tf' has no attribute {name!r}")


# (wrapt: installed with TensorFlow; the hook imports stnh_tf.modeling only once Keras is imported)
wrapt.register_post_import_hook("stnh_tf.modeling:register_keras_objects", "keras")
