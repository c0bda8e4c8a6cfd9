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
(:func:`stnh_tf.modeling.register_keras_objects`, run by a post-import hook on ``keras``:
:class:`_AfterKerasImport`), so that after
``import stnh_tf`` a plain ``keras.models.load_model(path)`` opens the shipped models and any
model trained here (docs/weights.md).
"""

import importlib
import importlib.util
import sys

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


def _register_keras_objects(keras_module):
    importlib.import_module("stnh_tf.modeling").register_keras_objects(keras_module)


class _AfterKerasImport:
    """The post-import hook on ``keras``, a finder first on ``sys.meta_path``: the spec of
    ``keras`` as the other finders find it, loaded by Keras' own loader and then
    :func:`stnh_tf.modeling.register_keras_objects` (:class:`_ThenRegister`). Imports nothing
    until ``keras`` is imported."""

    finding = False

    def find_spec(self, name, path=None, target=None):
        if name != "keras" or self.finding:
            return None
        self.finding = True  # (keras' import lock is held: one thread at a time here)
        try:
            spec = importlib.util.find_spec(name)
        finally:
            self.finding = False
        if spec is not None and spec.loader is not None:
            spec.loader = _ThenRegister(spec.loader)
        return spec


class _ThenRegister:
    """A loader: runs ``loader`` and then registers this package's Keras objects; the module keeps
    ``loader`` as its ``__loader__`` and ``__spec__.loader`` (as
    :class:`importlib.util.LazyLoader` leaves them)."""

    def __init__(self, loader):
        self.loader = loader

    def create_module(self, spec):
        return self.loader.create_module(spec)

    def exec_module(self, module):
        module.__loader__ = module.__spec__.loader = self.loader
        self.loader.exec_module(module)
        try:
            _register_keras_objects(module)
        except Exception as e:  # Keras itself must import whatever happens to this package
            import warnings

            warnings.warn(f"stnh_tf could not register its Keras objects ({type(e).__name__}: "
                          f"{e}); keras.models.load_model will not open its models.",
                          RuntimeWarning, stacklevel=2)


# Not wrapt's post-import hook: importing wrapt imports asyncio, ssl, email... (113 modules,
# 44 ms) into every process that imports this package, the data workers too; this, none (1.4 ms).
if "keras" in sys.modules:
    _register_keras_objects(sys.modules["keras"])
else:
    sys.meta_path.insert(0, _AfterKerasImport())
