"""The Keras side of the model: layers (:mod:`~stnh_tf.modeling.layers`), the Functional models
(:mod:`~stnh_tf.modeling.models`), losses and metrics (:mod:`~stnh_tf.modeling.losses`), and the
one way to load and run a trained model (:mod:`~stnh_tf.modeling.runner`). Besides training and
inference, the only place that imports Keras."""

import importlib

KERAS_OBJECT_MODULES = ("stnh_tf.modeling.layers", "stnh_tf.modeling.losses")
"""The modules defining every class and function this package registers with
``keras.saving.register_keras_serializable(package="stnh_tf")``: the layers, and the losses and
metric. Neither imports the other, so either may be importing Keras when Keras' import ends and
:func:`register_keras_objects` runs (a half-imported one finishes its own registration)."""


def register_keras_objects(keras_module) -> None:
    """Register this package's Keras objects (import :data:`KERAS_OBJECT_MODULES`), so that
    ``keras.models.load_model`` opens any model it saved, the shipped ``.keras`` files included.

    ``import stnh_tf`` calls it once Keras is imported (a post-import hook on ``keras``, or at
    once if Keras already is), without importing Keras itself, with ``keras_module`` the module
    imported as ``keras``. A stand-in without Keras' saving API (``keras.saving``: no model
    opens with it), such as the data tests' module giving ``keras.utils.PyDataset`` alone, has
    nothing to register with: nothing is imported then (the Keras layers would import a
    backend).
    """
    if not hasattr(keras_module, "saving"):
        return
    for name in KERAS_OBJECT_MODULES:
        importlib.import_module(name)
