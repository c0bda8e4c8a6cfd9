"""The Keras side of the model: layers (:mod:`~stnh_tf.modeling.layers`), the Functional models
(:mod:`~stnh_tf.modeling.models`), losses and metrics (:mod:`~stnh_tf.modeling.losses`), and the
one way to load and run a trained model (:mod:`~stnh_tf.modeling.runner`). Besides training and
inference, the only place that imports Keras."""
