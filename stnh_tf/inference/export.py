"""Export a :class:`~stnh_tf.inference.estimator.HomographyEstimator` as a TensorFlow SavedModel.

The SavedModel has one serving signature (``serving_default``, also reachable as ``serve``):

* inputs ``patch_a`` and ``patch_b``: ``uint8`` ``[B, 128, 128, 1]`` grayscale patches (0..255),
  the same ``B >= 1`` for both; checked in the graph (:func:`checked_inputs`): any other rank,
  size, channel count, dtype or an empty batch raises ``InvalidArgumentError``;
* output ``homography``: ``float32`` ``[B, 3, 3]`` pixel ``H_ba`` (maps patch_b pixel coordinates
  to patch_a pixel coordinates, ``[2, 2] = 1``; see :mod:`stnh_tf.geometry`).

It is self-contained TensorFlow (no stnh_tf or OpenCV needed to serve it)::

    fn = tf.saved_model.load(path).signatures["serving_default"]
    h = fn(patch_a=a_uint8, patch_b=b_uint8)["homography"]

The SavedModel computes :meth:`HomographyEstimator.estimate` with
``EstimateOptions.network_only()`` (:class:`~stnh_tf.inference.options.EstimateOptions`): the
network's composed estimate, every stage composed, with no search and no flat rule. Single-stage
and sequence models export exactly that computation. A hierarchy exports its stages chained by
the package's :class:`~stnh_tf.modeling.layers.SpatialTransformer` (the warp of the patch itself,
filled beyond it as the options' ``fill`` says: the same geometry as the estimator's OpenCV warp
of a patch); OpenCV's bilinear warp quantizes sampling positions to 1/32 px, so a hierarchy's
SavedModel agrees with the estimate only up to that interpolation difference, while it agrees
with the same TensorFlow computation run before export to float32 rounding (models compute in
float32 as ``HomographyEstimator.load`` rebuilds them by default; one kept in bfloat16 differs
between eager and graph runs by bfloat16 rounding and fails ``verify_export``'s default
tolerance). One difference remains: the estimator skips a stage whose prediction makes the
composition non-finite or singular; the SavedModel returns such a composition as it is.
"""

from __future__ import annotations

import os
import shutil
import tempfile

import numpy as np

from stnh_tf import geometry

SIGNATURE = "serving_default"
OUTPUT = "homography"


def checked_inputs(patch_a, patch_b):
    """``patch_a``, ``patch_b`` after run-time checks in the graph: each of shape
    ``[B, 128, 128, 1]`` (``tf.ensure_shape``) and the same ``B >= 1`` for both (an empty batch
    is refused as ``estimate`` refuses it); anything else raises ``InvalidArgumentError`` when
    the function runs. (A SavedModel signature's declared input
    shape is not enforced when it is called, and the graph is optimized for that shape: without
    these checks a ``[1, 128, 128]`` request aborted the serving process and a ``[1, 64, 64, 1]``
    one returned a homography.) The dtype (uint8) is checked by the signature itself."""
    import tensorflow as tf

    s = geometry.PATCH_SIZE
    patch_a = tf.ensure_shape(patch_a, [None, s, s, 1], name="check_patch_a")
    patch_b = tf.ensure_shape(patch_b, [None, s, s, 1], name="check_patch_b")
    same = tf.debugging.assert_equal(tf.shape(patch_a)[0], tf.shape(patch_b)[0],
                                     message="patch_a and patch_b must hold the same number of "
                                             "patches")
    some = tf.debugging.assert_positive(tf.shape(patch_a)[0],
                                        message="patch_a is an empty batch: patch_a and patch_b "
                                                "must hold at least one patch each")
    with tf.control_dependencies([same, some]):
        return tf.identity(patch_a), tf.identity(patch_b)


def serving_function(estimator):
    """A TensorFlow function ``(patch_a, patch_b) -> {"homography": [B, 3, 3] float32}`` on uint8
    ``[B, 128, 128, 1]`` patches, computing the estimator's ``H_ba`` with its Keras models."""
    from keras import ops

    from stnh_tf.inference.options import EstimateOptions
    from stnh_tf.modeling.layers import SpatialTransformer

    stages, outputs = estimator.stages, estimator.output_names
    warp = SpatialTransformer(fill=EstimateOptions.network_only().fill, dtype="float32",
                              name="hierarchy_warp")

    def serve(patch_a, patch_b):
        patch_a, patch_b = checked_inputs(patch_a, patch_b)
        a = ops.cast(patch_a, "float32") / 255.0
        b = ops.cast(patch_b, "float32") / 255.0
        total, current = None, a
        for model, name in zip(stages, outputs):
            if total is not None:
                current = warp([a, total])  # patch_a(H_1 ... H_{k-1} p), mirrored outside
            h8 = ops.cast(model({"patch_a": current, "patch_b": b}, training=False)[name],
                          "float32")
            h_bar = geometry.vector_to_matrix(h8)
            total = geometry.scale_to_unit(h_bar if total is None else ops.matmul(total, h_bar))
        return {OUTPUT: geometry.denormalize_homography(total)}

    serve.tracked = list(stages)  # the warp layer holds no variables
    return serve


SAVED_MODEL_ENTRIES = ("saved_model.pb", "fingerprint.pb", "variables", "assets")
"""What a SavedModel export writes into its folder: ``overwrite`` replaces these and nothing
else."""


def export_saved_model(estimator, output_dir, overwrite: bool = False) -> str:
    """Write ``estimator`` as a SavedModel to ``output_dir`` (see the module docstring).

    An existing ``output_dir`` is replaced only with ``overwrite=True`` and only if it is a
    SavedModel (holds ``saved_model.pb``) or empty; otherwise ``FileExistsError``. The new export
    is written to a temporary folder beside ``output_dir`` and moved in only when complete; then
    only the entries an export writes (:data:`SAVED_MODEL_ENTRIES`) are replaced, so the user's
    own files in the folder stay, and a failed write (e.g. a full disk) leaves the old export as
    it was and raises ``OSError`` naming the path and the cause.
    """
    output_dir = os.fspath(output_dir)
    if os.path.exists(output_dir) and (not os.path.isdir(output_dir) or os.listdir(output_dir)):
        is_saved_model = os.path.isfile(os.path.join(output_dir, "saved_model.pb"))
        if not overwrite or not is_saved_model:
            why = ("pass overwrite=True (--overwrite) to replace it" if is_saved_model
                   else "it is not a SavedModel; choose another path")
            raise FileExistsError(f"{output_dir} exists and is not empty; {why}.")
    parent = os.path.dirname(os.path.abspath(output_dir))
    os.makedirs(parent, exist_ok=True)
    staging = tempfile.mkdtemp(prefix=f".{os.path.basename(output_dir)}.", dir=parent)
    try:
        try:
            _write_archive(estimator, staging)
        except Exception as e:  # TensorFlow's write errors are not OSErrors
            raise OSError(f"cannot write the SavedModel to {output_dir}: "
                          f"{type(e).__name__}: {e}") from None
        os.makedirs(output_dir, exist_ok=True)
        for name in SAVED_MODEL_ENTRIES:  # the old export's entries, then the new ones moved in
            old = os.path.join(output_dir, name)
            if os.path.isdir(old) and not os.path.islink(old):
                shutil.rmtree(old)
            elif os.path.lexists(old):
                os.remove(old)
        for name in os.listdir(staging):
            os.replace(os.path.join(staging, name), os.path.join(output_dir, name))
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return output_dir


def _write_archive(estimator, path):
    """The SavedModel of :func:`serving_function` written to the new folder ``path``."""
    import keras
    import tensorflow as tf

    serve = serving_function(estimator)
    archive = keras.export.ExportArchive()
    for obj in serve.tracked:
        archive.track(obj)
    spec = [tf.TensorSpec([None, geometry.PATCH_SIZE, geometry.PATCH_SIZE, 1], tf.uint8,
                          name="patch_a"),
            tf.TensorSpec([None, geometry.PATCH_SIZE, geometry.PATCH_SIZE, 1], tf.uint8,
                          name="patch_b")]
    archive.add_endpoint("serve", serve, input_signature=spec)
    archive.write_out(path, verbose=False)


def load_serving_signature(path):
    """The ``serving_default`` signature of the SavedModel at ``path``."""
    import tensorflow as tf

    loaded = tf.saved_model.load(os.fspath(path))
    fn = loaded.signatures[SIGNATURE]
    fn._stnh_owner = loaded  # keep the loaded object (and its variables) alive
    return fn


def run_saved_model(signature_or_path, patch_a, patch_b) -> np.ndarray:
    """Run a SavedModel signature (or the one at a path) on uint8 ``[B, 128, 128, 1]`` patches;
    returns float32 ``[B, 3, 3]``."""
    import tensorflow as tf

    fn = signature_or_path
    if isinstance(fn, (str, os.PathLike)):
        fn = load_serving_signature(fn)
    out = fn(patch_a=tf.constant(np.asarray(patch_a, np.uint8)),
             patch_b=tf.constant(np.asarray(patch_b, np.uint8)))
    return np.asarray(out[OUTPUT])


def verification_pairs(n: int = 8, seed: int = 0):
    """``n`` uint8 ``[n, 128, 128, 1]`` patch pairs (paper protocol: corners moved by up to 32 px)
    cut from photographs bundled with scikit-image, to compare an export with its source."""
    import cv2
    import skimage.data

    photos = [skimage.data.camera(), skimage.data.astronaut(), skimage.data.coffee(),
              skimage.data.chelsea(), skimage.data.rocket()]
    rng = np.random.default_rng(seed)
    s, rho = geometry.PATCH_SIZE, geometry.MAX_PERTURBATION
    size = (geometry.IMAGE_WIDTH, geometry.IMAGE_HEIGHT)
    pa, pb = [], []
    for i in range(n):
        img = photos[i % len(photos)]
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        x0 = int(rng.integers(rho, size[0] - rho - s + 1))
        y0 = int(rng.integers(rho, size[1] - rho - s + 1))
        square = geometry.patch_corners(s) + [x0, y0]
        h = geometry.homography_from_points(square, square + rng.uniform(-rho, rho, (4, 2)))
        warped = cv2.warpPerspective(img, h, size, flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
        pa.append(img[y0:y0 + s, x0:x0 + s])
        pb.append(warped[y0:y0 + s, x0:x0 + s])
    return np.stack(pa)[..., None], np.stack(pb)[..., None]


def verify_export(path, estimator, patch_a=None, patch_b=None, tolerance: float = 1e-3) -> dict:
    """Reload the SavedModel at ``path`` and compare it with ``estimator`` on uint8 patch pairs
    (default: :func:`verification_pairs`).

    Returns a dict with ``max_abs_diff`` (SavedModel vs the same TensorFlow computation run on the
    in-memory Keras models), ``max_abs_diff_estimate`` (SavedModel vs
    :meth:`HomographyEstimator.estimate` with ``EstimateOptions.network_only()``), ``tolerance`` and
    ``ok``.
    ``ok`` requires ``max_abs_diff <= tolerance``, and for single-stage and sequence models
    (where both compute the same thing) also ``max_abs_diff_estimate <= tolerance``; for a
    hierarchy the latter measures OpenCV-vs-TensorFlow interpolation and is reported only.
    Differences are on the entries of the pixel ``H_ba``.
    """
    import tensorflow as tf

    if patch_a is None or patch_b is None:
        patch_a, patch_b = verification_pairs()
    patch_a, patch_b = np.asarray(patch_a, np.uint8), np.asarray(patch_b, np.uint8)
    saved = run_saved_model(path, patch_a, patch_b).astype(np.float64)
    eager = np.asarray(
        serving_function(estimator)(tf.constant(patch_a), tf.constant(patch_b))[OUTPUT],
        np.float64)
    from stnh_tf.inference.options import EstimateOptions

    estimate = estimator.estimate(patch_a, patch_b, EstimateOptions.network_only())
    diff = float(np.max(np.abs(saved - eager)))
    diff_estimate = float(np.max(np.abs(saved - estimate)))
    ok = diff <= tolerance and (estimator.kind == "hierarchy" or diff_estimate <= tolerance)
    return {"max_abs_diff": diff, "max_abs_diff_estimate": diff_estimate, "tolerance": tolerance,
            "pairs": int(len(patch_a)), "kind": estimator.kind, "ok": bool(ok)}
