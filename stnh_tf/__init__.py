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
a deep-learning backend.
"""

import importlib

from stnh_tf import _compat

__version__ = "0.1.0"

_LAZY = {
    "SpatialTransformer": "stnh_tf.modeling.layers",
    "HomographyMerge": "stnh_tf.modeling.layers",
    "HomographyEstimator": "stnh_tf.inference.estimator",
}

__all__ = ["geometry", *_LAZY]

# Modules of the flat layout before 0.2 and where they are now (importable for one release).
_compat.install({
    "stnh_tf.layers": "stnh_tf.modeling.layers",
    "stnh_tf.models": "stnh_tf.modeling.models",
    "stnh_tf.losses": "stnh_tf.modeling.losses",
    "stnh_tf.model_kinds": "stnh_tf.training.model_kinds",
    "stnh_tf.runner": "stnh_tf.modeling.runner",
    "stnh_tf.sources": "stnh_tf.data.sources",
    "stnh_tf.pairs": "stnh_tf.data.pairs",
    "stnh_tf.batches": "stnh_tf.data.batches",
    "stnh_tf.pair_datasets": "stnh_tf.data.pair_datasets",
    "stnh_tf.features": "stnh_tf.data.features",
    "stnh_tf.train_config": "stnh_tf.training.config",
    "stnh_tf.run_dir": "stnh_tf.training.run_dir",
    "stnh_tf.train_streams": "stnh_tf.training.streams",
    "stnh_tf.baselines": "stnh_tf.evaluation.baselines",
    "stnh_tf.baseline_tuning": "stnh_tf.evaluation.baseline_tuning",
    "stnh_tf.benchmarks": "stnh_tf.evaluation.benchmarks",
    "stnh_tf.search_stability": "stnh_tf.evaluation.search_stability",
    "stnh_tf.image_input": "stnh_tf.inference.image_input",
    "stnh_tf.model_files": "stnh_tf.inference.model_files",
    "stnh_tf.export": "stnh_tf.inference.export",
    "stnh_tf.alignment": "stnh_tf.inference.image_files",
    "stnh_tf.ecc": "stnh_tf.inference.ecc",
    "stnh_tf.shipped_weights": "stnh_tf.inference.shipped_weights",
    "stnh_tf.reproduce": "stnh_tf.paper.reproduce",
    "stnh_tf.figures": "stnh_tf.paper.figures",
    "stnh_tf.demo": "stnh_tf.paper.demo",
})


def __getattr__(name):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    old = f"stnh_tf.{name}"
    if old in _compat.MOVED or name in ("geometry", "data", "training", "evaluation", "inference"):
        return importlib.import_module(_compat.MOVED.get(old, old))
    raise AttributeError(f"module 'stnh_tf' has no attribute {name!r}")
