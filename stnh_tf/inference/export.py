"""Export a :class:`~stnh_tf.inference.estimator.HomographyEstimator` as a TensorFlow SavedModel.

The SavedModel has one serving signature (``serving_default``, also reachable as ``serve``):

* inputs ``patch_a`` and ``patch_b``: ``uint8`` ``[B, 128, 128, 1]`` grayscale patches (0..255),
  the same ``B >= 1`` for both; checked in the graph
  (:func:`stnh_tf.inference.serving.checked_inputs`): any other rank, size, channel count, dtype
  or an empty batch raises ``InvalidArgumentError``;
* output ``homography``: ``float32`` ``[B, 3, 3]`` pixel ``H_ba`` (maps patch_b pixel coordinates
  to patch_a pixel coordinates, ``[2, 2] = 1``; see :mod:`stnh_tf.geometry`).

Beside ``saved_model.pb`` the export writes ``signature.json`` and ``README.md``
(:mod:`stnh_tf.inference.export_contract`): the signature, the output's frame, how to cut patches
from photographs (with a runnable snippet) and the model card's numbers. On ``overwrite`` an
earlier export's copies are replaced; files of those names that no export wrote are kept (and
the export's own not written; a warning says so).

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
tolerance). Both skip a stage whose prediction makes the composition non-finite or singular,
keeping the estimate before it (the identity before the first stage): the graph applies the
estimator's degenerate-prediction rule (:func:`stnh_tf.inference.serving.kept_unless_degenerate`),
so that an under-trained model's export computes what ``estimate`` does.

Writing (:func:`export_saved_model`; :func:`export_and_verify` for ``experiments.export``):

* **One export at a time per output.** The export holds the output folder's lock
  (``<output>/.stnh_tf_export.lock``, :func:`stnh_tf.paths.exclusive_lock`, as make_dataset
  holds its split's) from its checks to its end (with :func:`export_and_verify`, through the
  verification too): a second export to the same output, in this process or another, is
  refused at once with ``FileExistsError`` naming the folder, so neither can report success
  with the other's files.
* **Verified, then marked.** :func:`export_and_verify` checks the new SavedModel in its
  staging folder, before it replaces anything: one that fails its check replaces no earlier
  export (it is moved in only into an output holding none, for inspection, unmarked). It writes
  :data:`VERIFIED_FILE` (atomically: the check's report and :func:`saved_model_digest`) only
  after the check passed, and an export removes the old one before it replaces anything: a
  folder an export was killed in (``kill -9``) after its swap has none. Loading an export
  (:func:`load_serving_signature`) logs a warning where it is missing or its digest is not the
  files', and a re-export without ``overwrite`` says the folder was never verified
  (:func:`verified_problem`).
* **Atomic.** The SavedModel is written to a hidden staging folder inside the output
  (``<output>/.stnh_tf_export_staging.xxxxxxxx``, holding the marker file
  ``.stnh_tf_export_staging``: on the output's own file system, wherever a link or a mount
  puts it) and moved in only when complete: the old export's entries are first moved aside
  into the staging folder, and put back if a move fails, so that a failed write or move leaves
  the old export as it was. One left by a killed export (``kill -9``) is removed by the next
  export to the same output, under the lock (so no live export owns it); a kill in the instant
  of the swap itself can leave the old export there, in that hidden folder. The code before
  this placed the staging folder beside the output (``.<output name>.xxxxxxxx``): those
  holding the marker naming this output are removed too. No other folder is touched.
"""

from __future__ import annotations

import logging
import os

import numpy as np

from stnh_tf import geometry, paths
from stnh_tf.inference import export_contract, serving
from stnh_tf.inference.export_folder import (VERIFIED_FILE, VERIFIED_FORMAT, output_lock,
                                             saved_model_digest, staging, swap_in,
                                             verified_problem)

_log = logging.getLogger(__name__)


def export_saved_model(estimator, output_dir, overwrite: bool = False) -> str:
    """Write ``estimator`` as a SavedModel to ``output_dir`` (see the module docstring).

    An existing ``output_dir`` is replaced only with ``overwrite=True`` and only if it is a
    SavedModel (holds ``saved_model.pb``) or empty; otherwise ``FileExistsError``; another
    export writing to it holds its lock, and this one is refused with ``FileExistsError``
    (:func:`~stnh_tf.inference.export_folder.output_lock`). The new export is written to a
    hidden staging folder inside ``output_dir`` and moved in only when complete; then only the
    entries an export writes (:data:`~stnh_tf.inference.export_folder.SAVED_MODEL_ENTRIES`) are
    replaced, so the user's own files in the folder stay, and a
    failed write (e.g. a full disk) leaves the old export as it was and raises ``OSError``
    naming the path and the cause.
    """
    _check_backend()
    with output_lock(output_dir, overwrite):
        _write_export(estimator, os.fspath(output_dir))
        return os.fspath(output_dir)


def export_and_verify(estimator, output_dir, overwrite: bool = False, check_pairs: int = 8,
                      tolerance: float = 1e-3) -> dict:
    """:func:`export_saved_model` with :func:`verify_export` on :func:`verification_pairs`
    (``check_pairs`` of them) run on the new SavedModel in its staging folder, holding the
    output's lock through both, so the report is about this export's files. Where the check
    passed, the export is moved in and :data:`VERIFIED_FILE` written last (atomically); where
    it failed, an earlier export in ``output_dir`` is kept as it was (``kept_earlier_export``
    True, nothing written), and into an output holding none the unchecked export is moved for
    inspection, unmarked. Returns ``verify_export``'s dict with ``documents`` (the paths of
    the ``README.md`` and ``signature.json`` written), ``kept_user_files`` (files of those
    names that the export did not write, kept in their place), ``kept_earlier_export`` and
    ``verified_file`` (the marker's path, ``None`` where the check failed). Raises as
    ``export_saved_model``."""
    _check_backend()
    with output_lock(output_dir, overwrite):
        patch_a, patch_b = verification_pairs(check_pairs)
        report = {}

        def check(folder):  # the new SavedModel, before it replaces anything
            report.update(verify_export(folder, estimator, patch_a, patch_b, tolerance))
            return report["ok"]

        kept = _write_export(estimator, os.fspath(output_dir), check)
        marker = None
        if kept is None:  # failed its check beside an earlier export: that one stays
            return {**report, "documents": [], "kept_user_files": [],
                    "kept_earlier_export": True, "verified_file": None}
        if report["ok"]:
            marker = os.path.join(os.fspath(output_dir), VERIFIED_FILE)
            paths.atomic_write_json(marker, {"format": VERIFIED_FORMAT,
                                             "saved_model_sha256": saved_model_digest(output_dir),
                                             "report": report})
    written = [os.path.join(os.fspath(output_dir), name) for name in export_contract.DOC_FILES
               if os.path.join(os.fspath(output_dir), name) not in kept]
    return {**report, "documents": written, "kept_user_files": kept,
            "kept_earlier_export": False, "verified_file": marker}


def _check_backend():
    """``ValueError`` unless Keras runs on TensorFlow: the serving graph is TensorFlow's (under
    another backend its trace fails deep inside, and was reported as a write error)."""
    import keras

    if keras.backend.backend() != "tensorflow":
        raise ValueError(f"the SavedModel export needs Keras on TensorFlow; this process runs "
                         f"Keras on {keras.backend.backend()!r}: run it with "
                         "KERAS_BACKEND=tensorflow (nothing was written).")


def _write_export(estimator, output_dir, check=None) -> list | None:
    """The write of :func:`export_saved_model`, its output's lock held; returns the paths of the
    files named like the export's documents (``README.md``, ``signature.json``) that an export
    did not write, kept in place of the export's own (a warning is logged for each). ``check``
    (the staging folder -> passed) runs before the swap: where it fails and ``output_dir``
    holds an earlier SavedModel, nothing is moved in and ``None`` is returned."""
    with staging(output_dir) as folder:
        try:
            _write_archive(estimator, folder)
            export_contract.write_files(estimator, folder)
        except Exception as e:  # TensorFlow's write errors are not OSErrors
            raise OSError(f"cannot write the SavedModel to {output_dir}: "
                          f"{type(e).__name__}: {e}") from None
        if check is not None and not check(folder) and os.path.isfile(
                os.path.join(output_dir, "saved_model.pb")):
            return None
        kept = swap_in(folder, output_dir)
    for path in kept:
        _log.warning("export: kept %s (not written by an export); the export's own %s is not "
                     "written", path, os.path.basename(path))
    return kept


def _write_archive(estimator, path):
    """The SavedModel of :func:`stnh_tf.inference.serving.serving_function` written to the new
    folder ``path``."""
    import keras
    import tensorflow as tf

    serve = serving.serving_function(estimator)
    archive = keras.export.ExportArchive()
    for obj in serve.tracked:
        archive.track(obj)
    spec = [tf.TensorSpec([None, geometry.PATCH_SIZE, geometry.PATCH_SIZE, 1], tf.uint8,
                          name="patch_a"),
            tf.TensorSpec([None, geometry.PATCH_SIZE, geometry.PATCH_SIZE, 1], tf.uint8,
                          name="patch_b")]
    archive.add_endpoint("serve", serve, input_signature=spec)
    archive.write_out(path, verbose=False)


def load_serving_signature(path, check_verified: bool = True):
    """The ``serving_default`` signature of the SavedModel at ``path``; with
    ``check_verified``, a warning is logged where the export is not known to be verified
    (:func:`verified_problem`)."""
    import tensorflow as tf

    problem = verified_problem(path) if check_verified else None
    if problem:
        _log.warning("export: %s; its output was not compared with its model: export it again "
                     "with --overwrite (experiments.export).", problem)
    loaded = tf.saved_model.load(os.fspath(path))
    fn = loaded.signatures[serving.SIGNATURE]
    fn._stnh_owner = loaded  # keep the loaded object (and its variables) alive
    return fn


def signature_inputs(patch_a, patch_b):
    """The patches :meth:`HomographyEstimator.estimate` accepts (one pair ``[128, 128]`` or
    ``[128, 128, 1]``, or a batch; uint8 0..255 or float in [0, 1]; checked by
    :func:`~stnh_tf.inference.image_input.check_patch_pair`, ``ValueError`` as there) as the
    signature's uint8 ``[B, 128, 128, 1]``: floats rounded to the nearest of the 256 levels
    (``round(255 x)``: exact for uint8 / 255, else within 0.5 / 255 of what ``estimate`` feeds
    the network).

        >>> a = np.full((128, 128), 0.5)
        >>> signature_inputs(a, a)[0].shape, signature_inputs(a, a)[0][0, 0, 0, 0]
        ((1, 128, 128, 1), np.uint8(128))
    """
    from stnh_tf import pixels
    from stnh_tf.inference.image_input import check_patch_pair

    return tuple(p if p.dtype == np.uint8 else pixels.to_uint8(p)
                 for p in check_patch_pair(patch_a, patch_b))


def run_saved_model(signature_or_path, patch_a, patch_b) -> np.ndarray:
    """Run a SavedModel signature (or the one at a path) on patches as
    :meth:`HomographyEstimator.estimate` takes them (:func:`signature_inputs`: uint8, or float in
    [0, 1] rounded to uint8; ``ValueError`` for anything else, e.g. float on the 0..255 scale);
    returns float32 ``[B, 3, 3]``."""
    import tensorflow as tf

    patch_a, patch_b = signature_inputs(patch_a, patch_b)
    fn = signature_or_path
    if isinstance(fn, (str, os.PathLike)):
        fn = load_serving_signature(fn)
    out = fn(patch_a=tf.constant(patch_a), patch_b=tf.constant(patch_b))
    return np.asarray(out[serving.OUTPUT])


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
    """Reload the SavedModel at ``path`` and compare it with ``estimator`` on patch pairs
    (:func:`signature_inputs`; default: :func:`verification_pairs`).

    Returns a dict with ``max_abs_diff`` (SavedModel vs the same TensorFlow computation run on the
    in-memory Keras models), ``max_abs_diff_estimate`` (SavedModel vs
    :meth:`HomographyEstimator.estimate` with ``EstimateOptions.network_only()``) and
    ``max_corner_diff_px_estimate`` (the same comparison as the largest mean distance of the patch
    corners, px), ``tolerance`` and ``ok``.
    ``ok`` requires ``max_abs_diff <= tolerance``, and for single-stage and sequence models
    (where both compute the same thing) also ``max_abs_diff_estimate <= tolerance``; for a
    hierarchy the latter measures OpenCV-vs-TensorFlow interpolation and is reported only.
    Differences are on the entries of the pixel ``H_ba``.
    """
    import tensorflow as tf

    if patch_a is None or patch_b is None:
        patch_a, patch_b = verification_pairs()
    patch_a, patch_b = signature_inputs(patch_a, patch_b)
    signature = load_serving_signature(path, check_verified=False)  # (being verified)
    saved = run_saved_model(signature, patch_a, patch_b).astype(np.float64)
    eager = np.asarray(
        serving.serving_function(estimator)(tf.constant(patch_a),
                                            tf.constant(patch_b))[serving.OUTPUT],
        np.float64)
    from stnh_tf.inference.options import EstimateOptions

    estimate = estimator.estimate(patch_a, patch_b, EstimateOptions.network_only())
    diff = float(np.max(np.abs(saved - eager)))
    diff_estimate = float(np.max(np.abs(saved - estimate)))
    corners_estimate = float(np.max(geometry.corner_errors(saved, estimate)))
    ok = diff <= tolerance and (estimator.kind == "hierarchy" or diff_estimate <= tolerance)
    return {"max_abs_diff": diff, "max_abs_diff_estimate": diff_estimate,
            "max_corner_diff_px_estimate": corners_estimate, "tolerance": tolerance,
            "pairs": int(len(patch_a)), "kind": estimator.kind, "ok": bool(ok)}


def verification_line(report) -> str:
    """One line that says what :func:`verify_export` (``report``) compared and whether the
    export passed.

        >>> print(verification_line({"max_abs_diff": 7.72e-05, "max_abs_diff_estimate": 0.0533,
        ...     "max_corner_diff_px_estimate": 0.021, "tolerance": 1e-3, "pairs": 8,
        ...     "kind": "hierarchy", "ok": True}))  # doctest: +NORMALIZE_WHITESPACE
        export check passed: the reloaded SavedModel vs the same TensorFlow computation on the
        Keras models, 8 photograph pairs: max |dH| 7.7e-05 <= tolerance 0.001: ok. Against
        HomographyEstimator.estimate(EstimateOptions.network_only()): max |dH| 0.053 (0.021 px at
        the patch corners), not checked for a hierarchy: OpenCV's warp between its stages samples
        on a 1/32 px grid, the SavedModel's TensorFlow warp does not.
    """
    tol, diff, other = report["tolerance"], report["max_abs_diff"], report["max_abs_diff_estimate"]
    head = ("export check passed" if report["ok"] else "export check FAILED") + (
        f": the reloaded SavedModel vs the same TensorFlow computation on the Keras models, "
        f"{report['pairs']} photograph pairs: max |dH| {diff:.2g} "
        f"{'<=' if diff <= tol else '>'} tolerance {tol:.3g}: "
        f"{'ok' if diff <= tol else 'too large'}. Against "
        f"HomographyEstimator.estimate(EstimateOptions.network_only()): max |dH| {other:.2g} "
        f"({report.get('max_corner_diff_px_estimate', float('nan')):.2g} px at the patch corners)")
    if report["kind"] == "hierarchy":
        return head + (", not checked for a hierarchy: OpenCV's warp between its stages samples "
                       "on a 1/32 px grid, the SavedModel's TensorFlow warp does not.")
    return head + (f" {'<=' if other <= tol else '>'} tolerance {tol:.3g}: "
                   f"{'ok' if other <= tol else 'too large'}.")
