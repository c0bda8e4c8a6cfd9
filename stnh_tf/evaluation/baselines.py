"""Classical homography baselines: identity, ORB + RANSAC and SIFT + RANSAC (NumPy/OpenCV only).

Convention (see :mod:`stnh_tf.geometry`): every estimator returns ``H_ba`` (``a_from_b``), the
pixel homography mapping **patch_b** coordinates ``(x, y)`` to **patch_a** coordinates, so that
``patch_b(p) = patch_a(H_ba @ p)``. Keypoints ``kp_b`` of patch_b matched to ``kp_a`` of patch_a
give ``H_ba = cv2.findHomography(pts_b, pts_a, RANSAC, thresh)``. Results are scaled so
``H[2, 2] = 1`` and compare directly with the data's ``h_ba`` through
:func:`stnh_tf.geometry.corner_errors`.

Inputs are grayscale ``128 x 128`` patches, one pair ``[128, 128]`` / ``[128, 128, 1]`` or a
batch ``[B, 128, 128]`` / ``[B, 128, 128, 1]``, either ``uint8`` (0..255) or floating point in
``[0, 1]`` (the models' input range; converted with ``round(255 x)``, so a float patch equal to
``uint8 / 255`` gives exactly the uint8 result). Anything else raises ``ValueError``.

When estimation fails (too few keypoints or matches, too few RANSAC inliers, ``findHomography``
returning ``None``, a non-finite or degenerate matrix: a corner mapped behind the camera, a
non-convex or folded corner quadrilateral, an area change beyond ``max_area_ratio``) the
estimator returns the identity with ``ok = False`` (its expected MACE on this protocol:
``docs/conventions.md``).

Settings (:data:`ORB_SETTINGS`, :data:`SIFT_SETTINGS`) were chosen with
``experiments.tune_baselines`` on paper-protocol pairs from the coco_mini **train** photographs,
never the test photographs the baselines are reported on (command and scores: BENCHMARKS.md,
"Baseline settings: the tuning pairs"). OpenCV's ORB defaults (:data:`ORB_DEFAULT_SETTINGS`:
``edgeThreshold = patchSize = 31``, 500 features, 8 levels) leave only the central ~66 px of a
128 px patch for keypoints and are far worse; they are kept as a registered baseline
(``orb_default``) so that the gap stays visible.

RANSAC in OpenCV seeds its own generator on every call, so estimates are deterministic on
OpenCV's optimized path; on its portable path (``cv2.setUseOptimized(False)``) with several
threads SIFT's keypoints can come in another order between calls (estimates then differ by a few
hundredths in H's entries).
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from stnh_tf import geometry, pixels

# --------------------------------------------------------------------------------------------
# Settings
# --------------------------------------------------------------------------------------------
_COMMON = {
    "ratio": 0.8,            # Lowe ratio test: keep a match if d1 < ratio * d2 (None: no test)
    "cross_check": False,    # also require mutual nearest neighbours
    "ransac_method": "RANSAC",  # cv2.RANSAC | cv2.USAC_MAGSAC ... (name of the cv2 constant)
    "ransac_thresh": 3.0,    # RANSAC reprojection threshold, pixels (in patch_a)
    "ransac_max_iters": 2000,
    "ransac_confidence": 0.995,
    "min_matches": 4,        # fewer matches after filtering -> failure (identity)
    "min_inliers": 6,        # fewer RANSAC inliers -> failure (identity)
    "max_area_ratio": 4.0,   # |area(H quad)| / area(patch) outside [1/r, r] -> degenerate
}

ORB_SETTINGS = {
    **_COMMON,
    "nfeatures": 1000,
    "scaleFactor": 1.2,
    "nlevels": 4,
    "edgeThreshold": 10,     # OpenCV default 31: keypoints only in the central 66 px of 128
    "patchSize": 15,         # OpenCV default 31
    "fastThreshold": 5,      # OpenCV default 20
    "WTA_K": 2,
    "ratio": None,           # no Lowe ratio test ...
    "cross_check": True,     # ... but mutual nearest neighbours
}
"""Tuned ORB + RANSAC (BENCHMARKS.md, "Baseline settings: the tuning pairs")."""

ORB_DEFAULT_SETTINGS = {
    **_COMMON,
    "nfeatures": 500, "scaleFactor": 1.2, "nlevels": 8, "edgeThreshold": 31, "patchSize": 31,
    "fastThreshold": 20, "WTA_K": 2,
    "ratio": None, "cross_check": True,   # the classic BFMatcher(NORM_HAMMING, crossCheck=True)
    "ransac_thresh": 5.0,
}
"""OpenCV's ORB defaults with cross-checked Hamming matching and RANSAC at 5 px (reference only)."""

SIFT_SETTINGS = {
    **_COMMON,
    "nfeatures": 0,              # 0: keep every keypoint
    "nOctaveLayers": 3,
    "contrastThreshold": 0.01,   # OpenCV default 0.04
    "edgeThreshold": 10.0,
    "sigma": 1.6,
    "ratio": 0.8,
}
"""Tuned SIFT + RANSAC (BENCHMARKS.md, "Baseline settings: the tuning pairs")."""


def _check_keys(settings: dict, allowed: dict, cls_name: str):
    unknown = sorted(set(settings) - set(allowed))
    if unknown:
        raise ValueError(f"{cls_name}: unknown settings {unknown}; allowed: {sorted(allowed)}.")


# --------------------------------------------------------------------------------------------
# Input handling
# --------------------------------------------------------------------------------------------
def _to_uint8(x, name: str) -> np.ndarray:
    """Patches of any accepted dtype -> uint8 (same shape). Float must lie in [0, 1]."""
    x = np.asarray(x)
    if x.dtype == np.uint8:
        return x
    if np.issubdtype(x.dtype, np.floating):
        if x.size and (not np.all(np.isfinite(x)) or x.min() < 0.0 or x.max() > 1.0):
            lo = float(np.nanmin(x)) if x.size else 0.0
            hi = float(np.nanmax(x)) if x.size else 0.0
            raise ValueError(f"{name}: floating-point patches must lie in [0, 1] (uint8 for "
                             f"0..255); received values in [{lo}, {hi}] with shape {x.shape}.")
        return pixels.to_uint8(x)
    raise ValueError(f"{name}: patches must be uint8 or floating point in [0, 1]; received dtype "
                     f"{x.dtype} with shape {x.shape}.")


def _as_batch(x, name: str, size: int = geometry.PATCH_SIZE) -> np.ndarray:
    """``[B, S, S]`` or ``[B, S, S, 1]`` -> uint8 ``[B, S, S]``."""
    shape = tuple(np.shape(x))
    shape3 = shape[:3] if (len(shape) == 4 and shape[-1] == 1) else shape
    if len(shape3) != 3 or shape3[1:] != (size, size):
        raise ValueError(f"{name} must have shape [B, {size}, {size}] or [B, {size}, {size}, 1]; "
                         f"received shape {shape}.")
    return _to_uint8(np.reshape(x, shape3), name)


def _as_single(x, name: str, size: int = geometry.PATCH_SIZE) -> np.ndarray:
    """``[S, S]`` or ``[S, S, 1]`` -> uint8 ``[S, S]``."""
    shape = tuple(np.shape(x))
    shape2 = shape[:2] if (len(shape) == 3 and shape[-1] == 1) else shape
    if shape2 != (size, size):
        raise ValueError(f"{name} must have shape [{size}, {size}] or [{size}, {size}, 1]; "
                         f"received shape {shape}.")
    return _to_uint8(np.reshape(x, shape2), name)


def _as_image(x, name: str) -> np.ndarray:
    """``[H, W]`` or ``[H, W, 1]`` -> uint8 ``[H, W]``."""
    shape = tuple(np.shape(x))
    shape2 = shape[:2] if (len(shape) == 3 and shape[-1] == 1) else shape
    if len(shape2) != 2 or min(shape2) == 0:
        raise ValueError(f"{name} must be one gray image [H, W] or [H, W, 1]; received shape "
                         f"{shape}.")
    return _to_uint8(np.reshape(x, shape2), name)


# --------------------------------------------------------------------------------------------
# Validity of an estimate
# --------------------------------------------------------------------------------------------
def is_plausible_homography(h, size: int = geometry.PATCH_SIZE,
                            max_area_ratio: float = 4.0, origin=(0.0, 0.0)) -> bool:
    """True if ``h`` ``[3, 3]`` is finite, maps the corners of the ``size`` square at ``origin``
    (``(x0, y0)``; the patch by default) in front of the camera onto a convex quadrilateral with
    the square's orientation, and changes its area by at most ``max_area_ratio`` (either way)."""
    h = np.asarray(h, np.float64)
    if h.shape != (3, 3) or not np.all(np.isfinite(h)) or abs(h[2, 2]) < 1e-12:
        return False
    h = h / h[2, 2]
    corners = geometry.patch_corners(size) + np.asarray(origin, np.float64)
    hom = np.concatenate([corners, np.ones((4, 1))], axis=1) @ h.T
    if np.any(hom[:, 2] <= 1e-6):
        return False
    q = hom[:, :2] / hom[:, 2:3]
    edges = np.roll(q, -1, axis=0) - q
    cross = (edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1]
             - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0])
    if not np.all(cross > 0):  # corners are listed clockwise in image coords (y down): cross > 0
        return False
    area = 0.5 * abs(np.sum(q[:, 0] * np.roll(q[:, 1], -1) - np.roll(q[:, 0], -1) * q[:, 1]))
    ratio = area / float(size * size)
    return 1.0 / max_area_ratio <= ratio <= max_area_ratio


# --------------------------------------------------------------------------------------------
# Estimators
# --------------------------------------------------------------------------------------------
class _Estimator:
    """Shared batch loop. Subclasses implement ``estimate(patch_a, patch_b) -> (H_ba, ok)``."""

    name = "base"
    settings: dict = {}

    def estimate(self, patch_a, patch_b):  # pragma: no cover - abstract
        raise NotImplementedError

    def estimate_batch(self, patches_a, patches_b):
        """Estimate ``H_ba`` for every pair.

        Args:
          patches_a, patches_b: ``[B, 128, 128]`` or ``[B, 128, 128, 1]``, uint8 or float in [0, 1].
        Returns:
          ``(H, ok)``: float64 ``[B, 3, 3]`` (patch_b -> patch_a, ``H[2,2] = 1``, identity where
          estimation failed) and bool ``[B]``.
        """
        a = _as_batch(patches_a, "patches_a")
        b = _as_batch(patches_b, "patches_b")
        if a.shape[0] != b.shape[0]:
            raise ValueError(f"patches_a and patches_b must hold the same number of patches; "
                             f"received shapes {np.shape(patches_a)} and {np.shape(patches_b)}.")
        hs = np.tile(np.eye(3), (a.shape[0], 1, 1))
        oks = np.zeros(a.shape[0], bool)
        for i in range(a.shape[0]):
            hs[i], oks[i] = self._estimate_uint8(a[i], b[i])
        return hs, oks

    def estimate_images(self, image_a, image_b):
        """Estimate ``H_ba`` between two whole gray images (any sizes; e.g. the 320 x 240 ones
        of ``estimate_images``), with the settings used on patches; the plausibility check of
        the result (:func:`is_plausible_homography`) is on a patch-sized square at image_b's
        centre (the settings' area rule is a patch's; before, on the largest square at image_b's
        origin, it refused 41% of the true wide motions and 10% of the paper protocol's on
        whole images: BENCHMARKS.md, "SIFT + RANSAC's check on whole images").

        Args:
          image_a, image_b: ``[H, W]`` or ``[H, W, 1]``, uint8 or float in [0, 1].
        Returns:
          ``(H_ba, ok)``: float64 ``[3, 3]`` mapping image_b pixels to image_a pixels
          (``H[2,2] = 1``, identity if ``ok`` is False).
        Raises:
          ValueError: another rank or channel count, an empty image, a bad dtype or range.
        """
        a, b = (_as_image(x, name) for x, name in ((image_a, "image_a"), (image_b, "image_b")))
        size = min(geometry.PATCH_SIZE, *b.shape)
        return self._estimate_uint8(a, b, size, ((b.shape[1] - size) / 2.0,
                                                 (b.shape[0] - size) / 2.0))

    def _estimate_uint8(self, a, b, size=geometry.PATCH_SIZE, origin=(0.0, 0.0)):
        raise NotImplementedError

    def __repr__(self):
        return f"{type(self).__name__}({self.settings})"


class IdentityBaseline(_Estimator):
    """Predicts ``H_ba = I`` for every pair (``ok`` is always True: it never fails)."""

    name = "identity"

    def __init__(self, **settings):
        _check_keys(settings, {}, type(self).__name__)
        self.settings = {}

    def estimate(self, patch_a, patch_b):
        """Returns ``(I [3, 3] float64, True)`` after checking the shapes."""
        _as_single(patch_a, "patch_a")
        _as_single(patch_b, "patch_b")
        return np.eye(3), True

    def _estimate_uint8(self, a, b, size=geometry.PATCH_SIZE, origin=(0.0, 0.0)):
        return np.eye(3), True


class _FeatureRansac(_Estimator):
    """Keypoints + descriptors on each patch, matching, ``findHomography(pts_b, pts_a, RANSAC)``."""

    _defaults: dict = {}
    _norm = cv2.NORM_L2

    def __init__(self, **settings):
        _check_keys(settings, self._defaults, type(self).__name__)
        self.settings = {**self._defaults, **settings}
        s = self.settings
        if s["ratio"] is None and not s["cross_check"]:
            raise ValueError(f"{type(self).__name__}: set ratio or cross_check (or both).")
        if not hasattr(cv2, str(s["ransac_method"])):
            raise ValueError(f"unknown ransac_method {s['ransac_method']!r} (a cv2 constant name).")
        self._method = getattr(cv2, s["ransac_method"])
        self._detector = self._make_detector()
        self._matcher = cv2.BFMatcher(self._norm, crossCheck=False)

    def _make_detector(self):  # pragma: no cover - abstract
        raise NotImplementedError

    def estimate(self, patch_a, patch_b):
        """Estimate ``H_ba`` (patch_b -> patch_a) for one pair.

        Args:
          patch_a, patch_b: ``[128, 128]`` or ``[128, 128, 1]``, uint8 or float in [0, 1].
        Returns:
          ``(H_ba, ok)``: float64 ``[3, 3]`` with ``H[2,2] = 1`` (identity if ``ok`` is False).
        """
        return self._estimate_uint8(_as_single(patch_a, "patch_a"), _as_single(patch_b, "patch_b"))

    def detect(self, patch):
        """Keypoint coordinates ``[N, 2]`` (x, y) and descriptors of one uint8 patch."""
        kps, desc = self._detector.detectAndCompute(patch, None)
        pts = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        return pts, desc

    def match(self, desc_a, desc_b):
        """Index pairs ``(i_a, i_b)`` passing the ratio test and/or the mutual check."""
        s = self.settings
        if desc_a is None or desc_b is None or len(desc_a) < 2 or len(desc_b) < 2:
            return np.zeros((0, 2), int)
        knn = self._matcher.knnMatch(desc_b, desc_a, k=2)  # query b, train a
        pairs = []
        for m in knn:
            if not m:
                continue
            if s["ratio"] is not None:
                if len(m) < 2 or m[0].distance >= s["ratio"] * m[1].distance:
                    continue
            pairs.append((m[0].trainIdx, m[0].queryIdx))
        if s["cross_check"] and pairs:
            back = self._matcher.match(desc_a, desc_b)  # best b for each a
            best_b = {m.queryIdx: m.trainIdx for m in back}
            pairs = [(ia, ib) for ia, ib in pairs if best_b.get(ia) == ib]
        return np.array(pairs, int).reshape(-1, 2)

    def _estimate_uint8(self, a, b, size=geometry.PATCH_SIZE, origin=(0.0, 0.0)):
        s = self.settings
        pts_a, desc_a = self.detect(a)
        pts_b, desc_b = self.detect(b)
        pairs = self.match(desc_a, desc_b)
        if len(pairs) < max(4, s["min_matches"]):
            return np.eye(3), False
        src = pts_b[pairs[:, 1]].reshape(-1, 1, 2)
        dst = pts_a[pairs[:, 0]].reshape(-1, 1, 2)
        try:
            h, mask = cv2.findHomography(src, dst, self._method, s["ransac_thresh"],
                                         maxIters=s["ransac_max_iters"],
                                         confidence=s["ransac_confidence"])
        except cv2.error:
            return np.eye(3), False
        if h is None or mask is None or int(mask.sum()) < s["min_inliers"]:
            return np.eye(3), False
        if not is_plausible_homography(h, size, max_area_ratio=s["max_area_ratio"],
                                       origin=origin):
            return np.eye(3), False
        return h / h[2, 2], True


class OrbRansac(_FeatureRansac):
    """ORB keypoints, Hamming brute-force matching (ratio test / cross-check), RANSAC.

    Settings: :data:`ORB_SETTINGS` (any key may be overridden by keyword); the ORB keys are
    ``cv2.ORB_create`` arguments.
    """

    name = "orb_ransac"
    _defaults = ORB_SETTINGS
    _norm = cv2.NORM_HAMMING

    def __init__(self, **settings):
        if settings.get("WTA_K", ORB_SETTINGS["WTA_K"]) > 2:
            self._norm = cv2.NORM_HAMMING2
        super().__init__(**settings)

    def _make_detector(self):
        s = self.settings
        return cv2.ORB_create(nfeatures=s["nfeatures"], scaleFactor=s["scaleFactor"],
                              nlevels=s["nlevels"], edgeThreshold=s["edgeThreshold"],
                              firstLevel=0, WTA_K=s["WTA_K"], scoreType=cv2.ORB_HARRIS_SCORE,
                              patchSize=s["patchSize"], fastThreshold=s["fastThreshold"])


class SiftRansac(_FeatureRansac):
    """SIFT keypoints, L2 brute-force matching with Lowe's ratio test, RANSAC.

    Settings: :data:`SIFT_SETTINGS` (any key may be overridden by keyword); the SIFT keys are
    ``cv2.SIFT_create`` arguments.
    """

    name = "sift_ransac"
    _defaults = SIFT_SETTINGS
    _norm = cv2.NORM_L2

    def _make_detector(self):
        s = self.settings
        return cv2.SIFT_create(nfeatures=s["nfeatures"], nOctaveLayers=s["nOctaveLayers"],
                               contrastThreshold=s["contrastThreshold"],
                               edgeThreshold=s["edgeThreshold"], sigma=s["sigma"])


def _orb_default(**settings):
    return OrbRansac(**{**ORB_DEFAULT_SETTINGS, **settings})


SIFT_WIDE_SETTINGS = {**SIFT_SETTINGS, "ransac_method": "USAC_MAGSAC", "max_area_ratio": 16.0}
"""SIFT for wide baselines (issue 64): the tuned SIFT with ``cv2.USAC_MAGSAC`` (the estimator's
feature start's) and area changes up to 16x (zooms up to 4x) instead of 4x, which the tuned
plausibility rule refuses. Not tuned."""


def _sift_wide(**settings):
    return SiftRansac(**{**SIFT_WIDE_SETTINGS, **settings})


BASELINES = {
    "identity": IdentityBaseline,
    "orb_ransac": OrbRansac,
    "sift_ransac": SiftRansac,
    "orb_default": _orb_default,
    "sift_wide": _sift_wide,
}
"""Name -> constructor (keyword settings override the defaults)."""

FIGURE_BASELINES = {"identity": "Identity", "orb_ransac": "ORB + RANSAC",
                    "sift_ransac": "SIFT + RANSAC"}
"""The baselines that the reproduction's Fig. 4 and the demo report, in order: name in
:data:`BASELINES` -> display name (their key in ``results.json`` and their label)."""


def make_baseline(name: str, **settings):
    """Instantiate a registered baseline by name."""
    if name not in BASELINES:
        raise ValueError(f"unknown baseline {name!r}; choose from {sorted(BASELINES)}.")
    return BASELINES[name](**settings)


# --------------------------------------------------------------------------------------------
# Evaluation
# --------------------------------------------------------------------------------------------
def evaluate_baseline(name, patches_a, patches_b, h_true, **settings) -> dict:
    """Run a baseline over a set of pairs and summarize its corner errors.

    Args:
      name: a key of :data:`BASELINES` (or an estimator instance).
      patches_a, patches_b: ``[B, 128, 128(, 1)]`` uint8 or float in [0, 1].
      h_true: true ``H_ba`` (patch_b -> patch_a), ``[B, 3, 3]`` or ``[B, 8]`` pixel homographies.
      **settings: overrides of the baseline's settings.
    Returns:
      dict with ``mace`` (mean of :func:`geometry.corner_errors`, px), ``median``, ``p90``,
      ``p99``, ``failure_rate`` (fraction of pairs where the estimator fell back to identity),
      ``ms_per_pair`` (wall time of the estimation per pair, milliseconds, this process),
      ``count`` and ``worse_than_identity`` (pairs whose error exceeds the identity's).
    """
    est = name if isinstance(name, _Estimator) else make_baseline(name, **settings)
    h_true = geometry.as_matrix(np.asarray(h_true, np.float64))
    n = np.shape(patches_a)[0] if np.ndim(patches_a) >= 3 else -1
    if h_true.ndim != 3 or h_true.shape[0] != n:
        raise ValueError(f"h_true must have shape [B, 3, 3] or [B, 8] with B = {n} pairs; "
                         f"received shape {np.shape(h_true)}.")
    if n == 0:
        raise ValueError("no pairs to evaluate.")
    t0 = time.perf_counter()
    h_pred, ok = est.estimate_batch(patches_a, patches_b)
    elapsed = time.perf_counter() - t0
    errors = np.asarray(geometry.corner_errors(h_pred, h_true), np.float64)
    identity = np.asarray(geometry.corner_errors(np.broadcast_to(np.eye(3), h_true.shape), h_true))
    return {
        "mace": float(errors.mean()),
        "median": float(np.median(errors)),
        "p90": float(np.percentile(errors, 90)),
        "p99": float(np.percentile(errors, 99)),
        "failure_rate": float(1.0 - ok.mean()),
        "ms_per_pair": 1e3 * elapsed / len(errors),
        "count": int(len(errors)),
        "worse_than_identity": int((errors > identity).sum()),
    }
