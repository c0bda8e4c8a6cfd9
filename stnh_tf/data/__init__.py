"""Data: image sources (:mod:`~stnh_tf.data.sources`), the paper's pair protocol
(:mod:`~stnh_tf.data.pairs`), batches generated from images and their Keras datasets
(:mod:`~stnh_tf.data.batches`, :mod:`~stnh_tf.data.pair_datasets`; NumPy/OpenCV only; their worker
pools' helpers in :mod:`~stnh_tf.data.pools`), and the
TFRecord side: the feature spec (:mod:`~stnh_tf.data.features`), reading
(:mod:`~stnh_tf.data.tfrecords`), the sharded writer and the stage-1 / stage-k dataset libraries
behind ``python -m data_prep.*`` (:mod:`~stnh_tf.data.writer`, :mod:`~stnh_tf.data.metadata`,
:mod:`~stnh_tf.data.stage1`, :mod:`~stnh_tf.data.stage_k`), and realistic camera pairs with their
files (:mod:`~stnh_tf.data.camera_motions`, :mod:`~stnh_tf.data.camera_pair_files`).

Importing a submodule imports no deep-learning backend unless that submodule needs one.
"""

__all__ = ["load_split"]


def __getattr__(name):
    # ``load_split`` is imported on first use: the TFRecord reader imports TensorFlow, the pair
    # generators must not (tests/test_layout.py).
    if name == "load_split":
        from stnh_tf.data.tfrecords import load_split
        return load_split
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
