"""Every geometric convention of stnh-tf, in one place.

Conventions (shared by data generation, layers, models, evaluation and tests):

* Points are ``(x, y)``: x is the column, y the row. Pixel centres sit at integer coordinates,
  exactly as in OpenCV (``cv2.warpPerspective``, ``cv2.getPerspectiveTransform``).
* Images are NHWC; a stacked pair is ``[B, 128, 128, 2]`` (channel 0 = patch_a, 1 = patch_b).
* **Direction.** ``H_ba`` (named ``a_from_b`` in code) maps pixel coordinates of patch_b to pixel
  coordinates of patch_a: ``p_a ~ H_ba @ p_b``. A warp "by H" produces ``out(p) = src(H @ p)``,
  i.e. ``cv2.warpPerspective(src, H, size, flags=WARP_INVERSE_MAP)``; the spatial transformer
  samples the same way.
* **Normalization** uses the paper's matrix ``M = [[2/W, 0, -1], [0, 2/H, -1], [0, 0, 1]]`` (not
  kornia's ``2x/(W-1) - 1``): ``H_bar = M @ H @ inv(M)``, scaled so that ``H_bar[2, 2] = 1``. The
  network regresses the first eight entries of the flattened ``H_bar``.
* The four corners of a ``S x S`` patch are ``(0,0), (S,0), (S,S), (0,S)`` (the square's corners as
  perturbed in data generation); the four-point parameterization lists, for each corner ``c``,
  the offset ``H_ba @ c - c`` (where patch_b's corners lie in patch_a).
* Patch and image frames: a patch whose top-left corner is ``(x0, y0)`` in its image has
  ``H_patch = inv(T) @ H_image @ T`` with ``T`` the translation by ``(x0, y0)``.
* Composition (hierarchy and sequence): ``H = H_1 @ H_2 @ ... @ H_n``; normalized matrices compose
  the same way because the ``M`` factors cancel.
* Mean corner error (MACE): mean over the four corners (and samples) of
  ``|| dehom(H_pred @ c) - dehom(H_true @ c) ||_2`` in pixels.

Every function accepts NumPy arrays (and then computes in NumPy, without importing TensorFlow)
or backend tensors (and then uses ``keras.ops``, so it runs inside TensorFlow graphs and under the
JAX backend). Leading batch dimensions are arbitrary (written ``[...]`` below).
"""

from __future__ import annotations

import math

import numpy as np

PATCH_SIZE = 128
"""Side of the square patches, in pixels."""
IMAGE_WIDTH = 320
IMAGE_HEIGHT = 240
"""Size every source image is resized to before sampling (the paper's 320x240)."""
MAX_PERTURBATION = 32
"""Largest corner perturbation (pixels) and the width of the excluded image border."""
FILLS = ("zeros", "reflect")
"""What a warp samples where ``H @ p`` falls outside its source image: ``"zeros"`` (OpenCV's
``BORDER_CONSTANT`` 0; the paper's spatial transformer) or ``"reflect"`` (the source mirrored
about its first and last pixels, OpenCV's ``BORDER_REFLECT_101``)."""


def check_fill(fill: str) -> str:
    """``fill`` if it is one of :data:`FILLS`, else ``ValueError``."""
    if fill not in FILLS:
        raise ValueError(f"fill must be one of {FILLS}; received {fill!r}.")
    return fill


# --------------------------------------------------------------------------------------------
# NumPy / keras.ops dispatch
# --------------------------------------------------------------------------------------------
class _NumpyOps:
    """The subset of ``keras.ops`` this module needs, implemented with NumPy."""

    matmul = staticmethod(np.matmul)
    concatenate = staticmethod(np.concatenate)
    stack = staticmethod(np.stack)
    reshape = staticmethod(np.reshape)
    ones_like = staticmethod(np.ones_like)
    zeros_like = staticmethod(np.zeros_like)
    inv = staticmethod(np.linalg.inv)
    solve = staticmethod(np.linalg.solve)
    sqrt = staticmethod(np.sqrt)
    sum = staticmethod(np.sum)
    mean = staticmethod(np.mean)
    shape = staticmethod(np.shape)
    expand_dims = staticmethod(np.expand_dims)
    broadcast_to = staticmethod(np.broadcast_to)

    @staticmethod
    def convert(x, like):
        return np.asarray(x, dtype=like.dtype)

    @staticmethod
    def dtype(x):
        return x.dtype


class _KerasOps:
    def __init__(self):
        from keras import ops  # imported lazily: NumPy callers never import a backend

        self.k = ops
        for name in ("matmul", "concatenate", "stack", "reshape", "ones_like", "zeros_like",
                     "inv", "solve", "sqrt", "sum", "mean", "shape", "expand_dims",
                     "broadcast_to"):
            setattr(self, name, getattr(ops, name))

    def convert(self, x, like):
        return self.k.convert_to_tensor(x, dtype=self.dtype(like))

    def dtype(self, x):
        import keras

        return keras.backend.standardize_dtype(x.dtype)


_NP = _NumpyOps()
_KERAS = None


def _ops(*arrays):
    """NumPy ops if every argument is a NumPy array (or scalar/list), else ``keras.ops``."""
    global _KERAS
    if all(isinstance(a, (np.ndarray, np.generic, list, tuple, float, int)) for a in arrays):
        return _NP
    if _KERAS is None:
        _KERAS = _KerasOps()
    return _KERAS


def _as_float_array(x):
    if isinstance(x, (list, tuple, float, int)):
        x = np.asarray(x, dtype=np.float64)
    if isinstance(x, np.ndarray) and not np.issubdtype(x.dtype, np.floating):
        x = x.astype(np.float64)
    return x


def _check_last_dims(x, dims, name):
    shape = tuple(x.shape)
    if len(shape) < len(dims) or any(
            d is not None and s is not None and s != d for s, d in zip(shape[-len(dims):], dims)):
        want = "[..., " + ", ".join(str(d) for d in dims) + "]"
        raise ValueError(f"{name} must have shape {want}; received shape {shape}.")


# --------------------------------------------------------------------------------------------
# Normalization (the paper's M)
# --------------------------------------------------------------------------------------------
def normalization_matrix(width: int = PATCH_SIZE, height: int = PATCH_SIZE) -> np.ndarray:
    """The paper's ``M`` (float64 ``[3, 3]``): pixel ``(x, y)`` -> ``(2x/W - 1, 2y/H - 1)``."""
    return np.array([[2.0 / width, 0.0, -1.0],
                     [0.0, 2.0 / height, -1.0],
                     [0.0, 0.0, 1.0]], dtype=np.float64)


def scale_to_unit(h):
    """Divide ``[..., 3, 3]`` homographies by their ``[2, 2]`` element."""
    h = _as_float_array(h)
    _check_last_dims(h, (3, 3), "homography")
    return h / h[..., 2:3, 2:3]


def normalize_homography(a_from_b, width: int = PATCH_SIZE, height: int = PATCH_SIZE):
    """Pixel homography ``[..., 3, 3]`` -> normalized ``H_bar = M @ H @ inv(M)``, ``[2,2] = 1``.

    Direction is preserved: a pixel ``H_ba`` (patch_b -> patch_a) gives ``H_bar_ba`` mapping
    normalized patch_b coordinates to normalized patch_a coordinates.
    """
    a_from_b = _as_float_array(a_from_b)
    _check_last_dims(a_from_b, (3, 3), "homography")
    o = _ops(a_from_b)
    m = normalization_matrix(width, height)
    m, m_inv = o.convert(m, a_from_b), o.convert(np.linalg.inv(m), a_from_b)
    return scale_to_unit(o.matmul(o.matmul(m, a_from_b), m_inv))


def denormalize_homography(a_from_b_norm, width: int = PATCH_SIZE, height: int = PATCH_SIZE):
    """Normalized ``H_bar`` ``[..., 3, 3]`` -> pixel ``H = inv(M) @ H_bar @ M``, ``[2,2] = 1``."""
    a_from_b_norm = _as_float_array(a_from_b_norm)
    _check_last_dims(a_from_b_norm, (3, 3), "homography")
    o = _ops(a_from_b_norm)
    m = normalization_matrix(width, height)
    m, m_inv = o.convert(m, a_from_b_norm), o.convert(np.linalg.inv(m), a_from_b_norm)
    return scale_to_unit(o.matmul(o.matmul(m_inv, a_from_b_norm), m))


# --------------------------------------------------------------------------------------------
# 8-vector <-> 3x3
# --------------------------------------------------------------------------------------------
def vector_to_matrix(h8):
    """``[..., 8]`` (first eight entries of the row-major ``H``) -> ``[..., 3, 3]`` with
    ``[2,2] = 1``."""
    h8 = _as_float_array(h8)
    _check_last_dims(h8, (8,), "homography vector")
    o = _ops(h8)
    ones = o.ones_like(h8[..., :1])
    flat = o.concatenate([h8, ones], axis=-1)
    lead = tuple(o.shape(h8)[:-1])
    # A batch of one unknown size (a symbolic Keras tensor) reshapes as -1.
    return o.reshape(flat, (-1, 3, 3) if len(lead) == 1 else lead + (3, 3))


def matrix_to_vector(h):
    """``[..., 3, 3]`` -> ``[..., 8]``: scaled so ``H[2,2] = 1``, then the first eight entries."""
    h = scale_to_unit(h)
    o = _ops(h)
    lead = tuple(o.shape(h)[:-2])
    flat = o.reshape(h, (-1, 9) if len(lead) == 1 else lead + (9,))
    return flat[..., :8]


def h_bar_to_pixel(h_bar, size: int = PATCH_SIZE) -> np.ndarray:
    """A network's ``[..., 8]`` normalized ``H_bar`` -> pixel ``H_ba`` ``[..., 3, 3]`` (float64,
    ``[2,2] = 1``) in the ``size x size`` patch frame (NumPy)."""
    return denormalize_homography(vector_to_matrix(np.asarray(h_bar, np.float64)), size, size)


def as_matrix(h):
    """Accept ``[..., 8]`` or ``[..., 3, 3]`` homographies and return ``[..., 3, 3]``."""
    h = _as_float_array(h)
    shape = tuple(h.shape)
    if len(shape) >= 1 and shape[-1] == 8:
        return vector_to_matrix(h)
    if len(shape) >= 2 and shape[-2:] == (3, 3):
        return h
    raise ValueError(f"homography must have shape [..., 8] or [..., 3, 3]; received shape {shape}.")


# --------------------------------------------------------------------------------------------
# Points, corners, four-point parameterization
# --------------------------------------------------------------------------------------------
def patch_corners(size: int = PATCH_SIZE) -> np.ndarray:
    """The four corners ``(0,0), (S,0), (S,S), (0,S)`` as float64 ``[4, 2]`` (x, y)."""
    return np.array([[0, 0], [size, 0], [size, size], [0, size]], dtype=np.float64)


def warp_points(a_from_b, points_b):
    """Map points of frame b into frame a: ``dehom(a_from_b @ p)`` (``a_from_b`` is ``H_ba``).

    Args:
      a_from_b: ``[..., 3, 3]`` homography.
      points_b: ``[..., N, 2]`` (x, y) points (broadcast against the homography's batch).
    Returns:
      ``[..., N, 2]`` points in frame a.
    """
    a_from_b, points_b = _as_float_array(a_from_b), _as_float_array(points_b)
    _check_last_dims(a_from_b, (3, 3), "homography")
    _check_last_dims(points_b, (2,), "points")
    o = _ops(a_from_b, points_b)
    points_b = o.convert(points_b, a_from_b) if o is _NP else points_b
    ones = o.ones_like(points_b[..., :1])
    hom = o.concatenate([points_b, ones], axis=-1)  # [..., N, 3]
    mapped = o.matmul(hom, _swap_last(a_from_b, o))  # [..., N, 3] = (H @ p)^T
    return mapped[..., :2] / mapped[..., 2:3]


def _swap_last(h, o):
    if o is _NP:
        return np.swapaxes(h, -1, -2)
    return o.k.swapaxes(h, -1, -2)


def homography_from_points(points_b, points_a):
    """Direct linear solve for ``H`` with ``points_a ~ H @ points_b`` from four correspondences.

    Same result as ``cv2.getPerspectiveTransform(points_b, points_a)``, batched.

    Args:
      points_b, points_a: ``[..., 4, 2]`` (x, y).
    Returns:
      ``[..., 3, 3]`` with ``H[2,2] = 1`` (maps b -> a).
    """
    points_b, points_a = _as_float_array(points_b), _as_float_array(points_a)
    _check_last_dims(points_b, (4, 2), "points_b")
    _check_last_dims(points_a, (4, 2), "points_a")
    o = _ops(points_b, points_a)
    x, y = points_b[..., 0], points_b[..., 1]  # [..., 4]
    u, v = points_a[..., 0], points_a[..., 1]
    one, zero = o.ones_like(x), o.zeros_like(x)
    row_u = o.stack([x, y, one, zero, zero, zero, -u * x, -u * y], axis=-1)  # [..., 4, 8]
    row_v = o.stack([zero, zero, zero, x, y, one, -v * x, -v * y], axis=-1)
    a = o.concatenate([row_u, row_v], axis=-2)  # [..., 8, 8]
    b = o.concatenate([u, v], axis=-1)[..., None]  # [..., 8, 1]
    h8 = o.solve(a, b)[..., 0]
    return vector_to_matrix(h8)


def offsets_to_homography(offsets, size: int = PATCH_SIZE):
    """Four-point parameterization -> ``H_ba``.

    Args:
      offsets: ``[..., 4, 2]`` or ``[..., 8]``: for each corner ``c`` of :func:`patch_corners`,
        ``H_ba @ c - c`` (where patch_b's corner lies in patch_a's pixel frame).
    Returns:
      ``[..., 3, 3]`` pixel homography (patch_b -> patch_a), ``[2,2] = 1``.
    """
    offsets = _as_float_array(offsets)
    o = _ops(offsets)
    shape = tuple(offsets.shape)
    if shape[-1] == 8:
        offsets = o.reshape(offsets, tuple(o.shape(offsets)[:-1]) + (4, 2))
    _check_last_dims(offsets, (4, 2), "offsets")
    corners = o.convert(patch_corners(size), offsets)
    corners = o.broadcast_to(corners, o.shape(offsets)) if o is _NP else corners + 0 * offsets
    return homography_from_points(corners, corners + offsets)


def homography_to_offsets(a_from_b, size: int = PATCH_SIZE):
    """``H_ba`` ``[..., 3, 3]`` -> four-point offsets ``[..., 4, 2]`` (inverse of
    :func:`offsets_to_homography`)."""
    a_from_b = _as_float_array(a_from_b)
    o = _ops(a_from_b)
    corners = o.convert(patch_corners(size), a_from_b)
    return warp_points(a_from_b, corners) - corners


# --------------------------------------------------------------------------------------------
# Frames, composition, errors
# --------------------------------------------------------------------------------------------
def translation(tx, ty) -> np.ndarray:
    """``[3, 3]`` float64 translation by ``(tx, ty)``."""
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]], dtype=np.float64)


def image_to_patch(h_image, x0, y0):
    """Image-frame ``H_ba`` -> the same map in the frame of the patch at top-left ``(x0, y0)``:
    ``inv(T) @ H @ T`` (NumPy, ``[3, 3]``)."""
    return scale_to_unit(translation(-x0, -y0) @ np.asarray(h_image, np.float64)
                         @ translation(x0, y0))


def patch_to_image(h_patch, x0, y0):
    """Inverse of :func:`image_to_patch`: ``T @ H @ inv(T)`` (NumPy, ``[3, 3]``)."""
    return scale_to_unit(translation(x0, y0) @ np.asarray(h_patch, np.float64)
                         @ translation(-x0, -y0))


DIHEDRAL = {"identity": "", "flip_x": "h", "flip_y": "v", "rotate_180": "hv",
            "transpose": "t", "rotate_90_cw": "th", "rotate_90_ccw": "tv", "anti_transpose": "thv"}
"""The eight symmetries of a rectangle's pixel grid (:func:`dihedral_image`), by name: the steps
applied in order, ``t`` transpose (swap rows and columns), ``h`` mirror left-right, ``v`` mirror
top-bottom."""


def centre_scale(a_from_b, size_b) -> float:
    """The linear scale at which the image-frame ``a_from_b`` (``[3, 3]``, image_b pixel ->
    image_a pixel) maps the centre of an image_b of ``size_b = (w, h)``: ``sqrt(|det J|)`` of
    ``p -> a_from_b(p)`` there (``det J = det(H) / w**3``, ``w`` the homogeneous coordinate);
    above 1 image_b sees image_a smaller (a zoom out); NaN where not finite or behind the camera.

    >>> round(centre_scale(np.diag([2.0, 2.0, 1.0]), (320, 240)), 6)
    2.0
    """
    h = np.asarray(a_from_b, np.float64)
    centre = np.array([(size_b[0] - 1) / 2, (size_b[1] - 1) / 2, 1.0])
    with np.errstate(all="ignore"):
        w = float(h[2] @ centre)
        det = float(np.linalg.det(h)) if np.isfinite(h).all() else math.nan
        scale = math.sqrt(abs(det / w ** 3)) if w > 0 and math.isfinite(det) else math.nan
    return scale if math.isfinite(scale) else math.nan


def in_front(a_from_b, size_b=(IMAGE_WIDTH, IMAGE_HEIGHT)) -> bool:
    """Whether every pixel of an image_b of ``size_b = (w, h)`` maps by the image-frame
    ``a_from_b`` (``[3, 3]``) to a finite point in front of camera a: a positive homogeneous
    coordinate at image_b's four corner pixels, hence everywhere between (NumPy only).

    >>> in_front(np.eye(3)), in_front([[1, 0, 0], [0, 1, 0], [-0.01, 0, 1]])
    (True, False)
    """
    w, h = size_b
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], float)
    a_from_b = np.asarray(a_from_b, np.float64)
    z = corners @ a_from_b[2]
    return bool(np.all(np.isfinite(a_from_b)) and np.all(z > 1e-6))


def _check_dihedral(name: str) -> str:
    if name not in DIHEDRAL:
        raise ValueError(f"dihedral name must be one of {tuple(DIHEDRAL)}; received {name!r}.")
    return DIHEDRAL[name]


def dihedral_image(image, name: str, axes=(0, 1)) -> np.ndarray:
    """``image`` transposed and/or mirrored as :data:`DIHEDRAL` ``[name]`` says (NumPy).

    Args:
      image: array whose rows and columns are ``axes`` (``(0, 1)`` for ``[h, w]``, ``(1, 2)`` for
        a batch ``[B, h, w, C]``).
      name: a key of :data:`DIHEDRAL`.
    Returns:
      The transformed array (a view; ``rows`` and ``columns`` swapped by a transpose); pixel ``p``
      of the input lands at ``dihedral_matrix(name, w, h) @ p``.
    Raises:
      ValueError: an unknown ``name``.

    >>> dihedral_image(np.arange(6).reshape(2, 3), "rotate_90_cw").tolist()
    [[3, 0], [4, 1], [5, 2]]
    """
    rows, cols = axes
    out = np.asarray(image)
    for step in _check_dihedral(name):
        if step == "t":
            out = np.swapaxes(out, rows, cols)
        else:
            out = np.flip(out, cols if step == "h" else rows)
    return out


def dihedral_matrix(name: str, width: int, height: int) -> np.ndarray:
    """``[3, 3]`` float64 map from pixel ``(x, y)`` of a ``height x width`` image to the same
    pixel's position in ``dihedral_image(image, name)`` (pixel centres at integers).

    A homography ``a_from_b`` between two such images becomes ``G @ a_from_b @ inv(G)`` between
    their transformed copies, with ``G = dihedral_matrix(name, width, height)``.

    Raises:
      ValueError: an unknown ``name``.

    >>> dihedral_matrix("flip_x", 128, 128) @ [0, 5, 1]
    array([127.,   5.,   1.])
    """
    out, (w, h) = np.eye(3), (float(width), float(height))
    for step in _check_dihedral(name):
        if step == "t":
            out, (w, h) = np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, 1]]) @ out, (h, w)
        elif step == "h":
            out = np.array([[-1.0, 0, w - 1], [0, 1, 0], [0, 0, 1]]) @ out
        else:
            out = np.array([[1.0, 0, 0], [0, -1, h - 1], [0, 0, 1]]) @ out
    return out


def scale_matrix(sx, sy) -> np.ndarray:
    """``[3, 3]`` float64 scaling ``(x, y) -> (sx x, sy y)``."""
    return np.diag([float(sx), float(sy), 1.0])


def compose(*homographies):
    """``H_1 @ H_2 @ ... @ H_n`` (each ``[..., 3, 3]``), scaled so ``[2,2] = 1``.

    With stage estimates in the ``H_ba`` direction, the product maps patch_b into patch_a: stage k
    refines the output of stages ``1..k-1`` on the right.
    """
    if not homographies:
        raise ValueError("compose needs at least one homography.")
    hs = [_as_float_array(h) for h in homographies]
    o = _ops(*hs)
    out = hs[0]
    for h in hs[1:]:
        out = o.matmul(out, h)
    return scale_to_unit(out)


def corner_errors(h_pred, h_true, size: int = PATCH_SIZE):
    """Per-sample mean corner error ``[...]`` in pixels between two pixel homographies
    ``[..., 3, 3]`` (both in the same direction, e.g. patch_b -> patch_a)."""
    h_pred, h_true = _as_float_array(h_pred), _as_float_array(h_true)
    o = _ops(h_pred, h_true)
    corners = o.convert(patch_corners(size), h_true if o is not _NP else np.asarray(h_pred))
    diff = warp_points(h_pred, corners) - warp_points(h_true, corners)
    return o.mean(o.sqrt(o.sum(diff * diff, axis=-1)), axis=-1)


def mean_corner_error(h_pred, h_true, size: int = PATCH_SIZE):
    """MACE: :func:`corner_errors` averaged over every sample (a scalar), in pixels."""
    errors = corner_errors(h_pred, h_true, size)
    return _ops(errors).mean(errors)
