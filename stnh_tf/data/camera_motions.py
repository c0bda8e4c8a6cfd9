"""Realistic image pairs from photographs: camera motions and camera degradations, with the true
homography and a group by motion size (issue 46). NumPy/OpenCV only.

Frames (:mod:`stnh_tf.geometry`): both images are ``uint8 [240, 320]`` gray; ``h_ba``
(``a_from_b``) maps pixels of image_b to pixels of image_a in that 320 x 240 frame, pixel centres
at integers, ``image_b(p) = image_a(h_ba @ p)``:
``cv2.warpPerspective(image_a, h_ba, (320, 240), flags=WARP_INVERSE_MAP)`` before the degradation.

Rendering (:func:`render_pair`). A photograph becomes ``source``, its gray version resized to
560 x 420 as the paper resizes to 320 x 240 (:func:`stnh_tf.data.sources.resize_to_protocol`);
image_a is its central 320 x 240 window (top-left ``(120, 90)``, :data:`MARGIN`), so image_a is
the photograph's central 57% in the paper's conversion. image_b samples ``source`` at
``T @ h_ba @ p`` (``T``: translation by :data:`MARGIN`), bilinear: where ``h_ba @ p`` falls inside
image_a it is image_a's pixel, beyond it the photograph's surroundings (a real camera's view),
beyond the photograph its mirror image (OpenCV's ``BORDER_REFLECT_101``). Then image_b is blurred,
its exposure changed, sensor noise added and the result JPEG-compressed (:func:`degrade`);
image_a stays as is.

Larger pairs (issue 79: ``scale`` ``s``, an integer, 1 by default): the same motions drawn in the
320 x 240 frame, rendered at ``320 s x 240 s`` from the photograph resized to ``560 s x 420 s``
(image_a at ``(120 s, 90 s)``), their ``h_ba`` in that frame (:func:`to_scale`:
``inv(R) @ h_ba @ R``, ``R`` the resize map from ``320 s x 240 s`` to 320 x 240 pixels,
:func:`stnh_tf.data.sources.resize_matrix`) and the blur's sigma times ``s``; noise and JPEG per
pixel as at 320 x 240. A photograph smaller than the source is enlarged: the coco_mini
photographs (~640 x 480) hold the detail of a ``366 x 274`` image_a, whatever ``s``.

Motions (:data:`KINDS`; camera a has focal length ``f``, principal point at the image centre):

* ``"camera_rotation"``: rotation about the camera centre with zoom, ``h_ba = K_a R^T K_b^-1``
  (``K_b``'s focal length ``zoom * f``; ``R`` from yaw, pitch and roll);
* ``"plane_viewpoint"``: the photograph as a tilted plane seen from a second camera that moved
  around the point camera a looks at and looks at it again (plane-induced homography);
* ``"inplane_rotation"``: roll up to +-30 degrees and zoom about the image centre, plus a shift.

Motion size (:func:`motion_offset`, :func:`group_of`): the largest corner offset of the central
128 x 128 patch (top-left ``(96, 56)``, where ``estimate_images`` looks) in the patch frame,
``max |h_patch @ c - c|`` over its corners and over x and y: the training's offsets are uniform
in ``[-32, 32]`` per coordinate, so ``"within"`` (<= 32 px) is exactly the trained range,
``"1-2x"`` is (32, 64] px and ``"2-4x"`` (64, 128] px (:data:`GROUPS`).

Seeding (:func:`stnh_tf.data.camera_pair_files.make_image_pairs`, which makes the pairs of a
photograph from this module's parts): pair ``k = i * pairs_per_image + j`` of photograph ``i`` is
drawn from ``np.random.default_rng([seed, i])`` and belongs to group ``GROUPS[k % 3]`` (groups
balanced); its motion is drawn from :class:`MotionRanges` and scaled towards the identity
(:func:`draw_motion`) so that its size is uniform in the group's interval. Sets of pairs on
disk: :mod:`stnh_tf.data.camera_pair_files`.

The wide-baseline set (issue 64; ``motion_set="wide"``, :data:`MOTION_SETS`): its motions and
low-light degradation are :mod:`stnh_tf.data.wide_motions`'; pair ``k`` belongs to
``WIDE_GROUPS[k % 2]``: ``"wide"`` (the :class:`Degradation` of the other groups) or
``"wide_low_light"`` (dim, blurred, noisy). The low-overlap set (issue 79;
``motion_set="low_overlap"``, group ``"low_overlap"``): turns of 20-40 degrees, views overlapping
by 30-60%, image_a's window placed off-centre against the turn (:func:`render_pair`'s
``origin``; :mod:`stnh_tf.data.overlap_motions`).
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from stnh_tf import geometry
from stnh_tf.data import sources

WORK_SIZE = (geometry.IMAGE_WIDTH, geometry.IMAGE_HEIGHT)
"""``(width, height)`` of image_a and image_b."""
MARGIN = (120, 90)
"""Where image_a's top-left corner lies in the 560 x 420 source (its surroundings: image_b's
view beyond image_a)."""
SOURCE_SIZE = (WORK_SIZE[0] + 2 * MARGIN[0], WORK_SIZE[1] + 2 * MARGIN[1])
PATCH_ORIGIN = tuple((side - geometry.PATCH_SIZE) // 2 for side in WORK_SIZE)
"""Top-left ``(96, 56)`` of the central 128 x 128 patch (``estimate_images``' patch)."""
TRAINED_OFFSET = float(geometry.MAX_PERTURBATION)
"""The trained range: corner offsets up to 32 px per coordinate (patch frame)."""
GROUPS = {"within": (0.0, 1.0), "1-2x": (1.0, 2.0), "2-4x": (2.0, 4.0)}
"""Group -> its interval ``(lo, hi]`` of :func:`motion_offset` / :data:`TRAINED_OFFSET`."""
KINDS = ("camera_rotation", "plane_viewpoint", "inplane_rotation")


@dataclasses.dataclass(frozen=True)
class MotionRanges:
    """The widest motions drawn (angles in degrees; a pair's motion is this draw scaled towards
    the identity to fit its group). Every field is recorded in the manifest.

    Attributes:
      fov_deg: camera a's horizontal field of view, uniform (``f = 160 / tan(fov / 2)`` px).
      zoom: focal length of camera b over camera a's, log-uniform.
      roll_deg: in-plane rotation, uniform in ``[-roll, roll]`` (every kind).
      pan_deg: yaw and pitch of ``"camera_rotation"``, each uniform in ``[-pan, pan]``.
      view_deg: ``"plane_viewpoint"``: camera b's angle about the looked-at point, uniform in
        ``[0, view]``, in a uniform direction.
      distance: ``"plane_viewpoint"``: camera b's distance to that point over camera a's,
        log-uniform.
      tilt_deg: ``"plane_viewpoint"``: angle between the plane's normal and camera a's axis,
        uniform in ``[0, tilt]``, in a uniform direction.
      shift_px: ``"inplane_rotation"``: shift of x and y, each uniform in ``[-shift, shift]``.
    """

    fov_deg: tuple = (45.0, 75.0)
    zoom: tuple = (0.7, 1.4)
    roll_deg: float = 30.0
    pan_deg: float = 15.0
    view_deg: float = 40.0
    distance: tuple = (0.8, 1.25)
    tilt_deg: float = 30.0
    shift_px: float = 96.0


@dataclasses.dataclass(frozen=True)
class Degradation:
    """Ranges of image_b's degradation (:func:`degrade`; every one uniform, every pair gets all).

    Attributes:
      blur_sigma: Gaussian blur's standard deviation (px; below 0.1 no blur).
      exposure_ev: exposure change in stops on a gamma-2.2 encoding: gain ``2 ** (ev / 2.2)``,
        clipped to [0, 255] (saturation).
      read_noise: sensor read noise, standard deviation in grey levels.
      shot_noise: photon noise: variance ``shot_noise * value`` (grey levels).
      jpeg_quality: JPEG quality (integer).
    """

    blur_sigma: tuple = (0.0, 1.5)
    exposure_ev: tuple = (-1.0, 1.0)
    read_noise: tuple = (0.5, 3.0)
    shot_noise: tuple = (0.0, 0.1)
    jpeg_quality: tuple = (40, 95)


WIDE_GROUPS = ("wide", "wide_low_light")
"""The groups of the wide-baseline set (:mod:`stnh_tf.data.wide_motions`): pair ``k`` is in
``WIDE_GROUPS[k % 2]``; the second gets ``wide_motions.LOW_LIGHT`` instead of the set's
degradation."""

PAPER_GROUPS = ("paper", "paper_exposure")
"""The groups of the paper's protocol on whole images (:mod:`stnh_tf.data.paper_motions`, issue
79): pair ``k`` is in ``PAPER_GROUPS[k % 2]``; the second with an exposure change."""

LOW_OVERLAP_GROUPS = ("low_overlap",)
"""The group of the low-overlap set (:mod:`stnh_tf.data.overlap_motions`, issue 79)."""

MOTION_SETS = {"size": tuple(GROUPS), "wide": WIDE_GROUPS, "paper": PAPER_GROUPS,
               "low_overlap": LOW_OVERLAP_GROUPS}
"""The kinds of set :func:`stnh_tf.data.camera_pair_files.make_image_pairs` makes, with their
groups: ``"size"`` (motions scaled to a group by size, :func:`draw_motion`), ``"wide"``
(:func:`stnh_tf.data.wide_motions.draw_wide_motion`), ``"paper"``
(:func:`stnh_tf.data.paper_motions.draw_paper_motion`) and ``"low_overlap"``
(:func:`stnh_tf.data.overlap_motions.draw_overlap_motion`)."""

ALL_GROUPS = tuple(GROUPS) + WIDE_GROUPS + PAPER_GROUPS + LOW_OVERLAP_GROUPS
"""Every group a pair can belong to, in the order they are reported."""


@dataclasses.dataclass(frozen=True)
class CameraPair:
    """One pair. ``image_a``, ``image_b``: ``uint8 [240, 320]`` (``[240 s, 320 s]`` at
    ``scale`` ``s``); ``h_ba``: float64 ``[3, 3]`` (image_b -> image_a pixels in the images'
    own frame, ``[2, 2] = 1``); ``offset_px``: :func:`motion_offset` (the 320 x 240 frame's);
    ``motion`` and ``photometric``: the drawn parameters (JSON-ready)."""

    index: int
    image_id: str
    group: str
    kind: str
    h_ba: np.ndarray
    offset_px: float
    motion: dict
    photometric: dict
    image_a: np.ndarray
    image_b: np.ndarray


# --------------------------------------------------------------------------------------------
# Motions
# --------------------------------------------------------------------------------------------
def intrinsics(focal: float, size=WORK_SIZE) -> np.ndarray:
    """``K`` ``[3, 3]``: focal length ``focal`` px, principal point at the centre
    ``((w - 1) / 2, (h - 1) / 2)`` of a ``size = (w, h)`` image (pixel centres at integers)."""
    return np.array([[focal, 0.0, (size[0] - 1) / 2], [0.0, focal, (size[1] - 1) / 2],
                     [0.0, 0.0, 1.0]])


def rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """``R = Rz(roll) @ Rx(pitch) @ Ry(yaw)`` ``[3, 3]`` (radians; camera axes x right, y down,
    z forward), each factor from ``cv2.Rodrigues``."""
    return np.linalg.multi_dot([cv2.Rodrigues(np.array([0.0, 0.0, roll]))[0],
                                cv2.Rodrigues(np.array([pitch, 0.0, 0.0]))[0],
                                cv2.Rodrigues(np.array([0.0, yaw, 0.0]))[0]])


def rotation_homography(focal, zoom, yaw, pitch, roll, size=WORK_SIZE) -> np.ndarray:
    """``h_ba = K_a R^T K_b^-1`` (``[2, 2] = 1``): camera b is camera a rotated by ``R``
    (:func:`rotation`, radians) about its centre, with focal length ``zoom * focal``; a ray ``d``
    (camera a's coordinates) is seen at ``K_a d`` in a and ``K_b R d`` in b."""
    k_a, k_b = intrinsics(focal, size), intrinsics(zoom * focal, size)
    return geometry.scale_to_unit(k_a @ rotation(yaw, pitch, roll).T @ np.linalg.inv(k_b))


def _unit(v):
    return v / np.linalg.norm(v)


def plane_pose(view, view_dir, distance, tilt, tilt_dir, roll) -> tuple:
    """Camera b's pose and the plane of ``"plane_viewpoint"`` (angles in radians), in camera a's
    coordinates (camera a at the origin looking along +z; x right, y down).

    The plane is ``n . X = 1``, ``n`` tilted by ``tilt`` from camera a's axis towards
    ``tilt_dir``; the axis meets it at ``X0``. Camera b sits at ``X0 - distance * Rot(view) @ X0``
    (camera a's position turned by ``view`` about ``X0``, about an axis at ``view_dir`` in the
    image plane), looks at ``X0`` and is rolled by ``roll``.

    Returns:
      ``(R, t, n)``: ``X_b = R @ X_a + t`` (``[3, 3]``, ``[3]``) and the plane's ``n`` ``[3]``.
    """
    n = np.array([math.sin(tilt) * math.cos(tilt_dir), math.sin(tilt) * math.sin(tilt_dir),
                  math.cos(tilt)])
    x0 = np.array([0.0, 0.0, 1.0 / n[2]])
    axis = view * np.array([math.cos(view_dir), math.sin(view_dir), 0.0])
    centre_b = x0 - distance * cv2.Rodrigues(axis)[0] @ x0
    z = _unit(x0 - centre_b)
    x = _unit(np.cross([0.0, 1.0, 0.0], z))
    look = np.stack([x, np.cross(z, x), z])  # rows: camera b's axes in camera a's coordinates
    r = cv2.Rodrigues(np.array([0.0, 0.0, roll]))[0] @ look
    return r, -r @ centre_b, n


def plane_homography(focal, zoom, view, view_dir, distance, tilt, tilt_dir, roll,
                     size=WORK_SIZE) -> np.ndarray:
    """Plane-induced ``h_ba`` (``[2, 2] = 1``) of :func:`plane_pose`'s cameras, camera b with
    focal length ``zoom * focal``: with ``n . X_a = 1`` on the plane,
    ``H_ab = K_b (R + t n^T) K_a^-1`` and ``h_ba = inv(H_ab)``; the identity at
    ``view = roll = 0`` and ``zoom = distance = 1``. (OpenCV decomposes such a homography,
    ``decomposeHomographyMat``, but has no function that makes one.)"""
    r, t, n = plane_pose(view, view_dir, distance, tilt, tilt_dir, roll)
    h_ab = intrinsics(zoom * focal, size) @ (r + np.outer(t, n)) @ np.linalg.inv(
        intrinsics(focal, size))
    return geometry.scale_to_unit(np.linalg.inv(h_ab))


def inplane_homography(zoom, roll, shift_x, shift_y, size=WORK_SIZE) -> np.ndarray:
    """Rotation by ``roll`` (radians) and zoom about the image centre, then a shift of
    ``(shift_x, shift_y)`` px in image_a: ``T(shift) @ rotation_homography(f, zoom, 0, 0, roll)``
    (any ``f``)."""
    return geometry.scale_to_unit(geometry.translation(shift_x, shift_y)
                                  @ rotation_homography(300.0, zoom, 0.0, 0.0, roll, size))


def motion_offset(h_ba) -> np.ndarray:
    """The largest corner offset (px) of the central 128 x 128 patch (:data:`PATCH_ORIGIN`) in the
    patch frame, over its 4 corners and over x and y, for image-frame ``h_ba`` ``[..., 3, 3]``;
    ``inf`` where a corner maps to infinity. Returns float64 ``[...]``.

    >>> float(motion_offset(geometry.translation(3.0, -40.0)))
    40.0
    """
    h = np.asarray(h_ba, np.float64)
    t = geometry.translation(*PATCH_ORIGIN)
    corners = geometry.patch_corners(geometry.PATCH_SIZE)
    with np.errstate(all="ignore"):
        offsets = geometry.warp_points(np.linalg.inv(t) @ h @ t, corners) - corners
        out = np.abs(offsets).max(axis=(-1, -2))
    return np.where(np.isfinite(out), out, np.inf)


def group_of(offset_px) -> str | None:
    """The :data:`GROUPS` key of a :func:`motion_offset` (``None`` beyond 4x the range).

    >>> group_of(32.0), group_of(32.5), group_of(128.0), group_of(129.0)
    ('within', '1-2x', '2-4x', None)
    """
    ratio = float(offset_px) / TRAINED_OFFSET
    return next((g for g, (lo, hi) in GROUPS.items() if lo < ratio <= hi
                 or (lo == 0 and ratio == 0)), None)


def _homography(kind, p):
    deg = math.radians
    if kind == "camera_rotation":
        return rotation_homography(p["focal"], p["zoom"], deg(p["yaw_deg"]), deg(p["pitch_deg"]),
                                   deg(p["roll_deg"]))
    if kind == "plane_viewpoint":
        return plane_homography(p["focal"], p["zoom"], deg(p["view_deg"]), deg(p["view_dir_deg"]),
                                p["distance"], deg(p["tilt_deg"]), deg(p["tilt_dir_deg"]),
                                deg(p["roll_deg"]))
    return inplane_homography(p["zoom"], deg(p["roll_deg"]), p["shift_x"], p["shift_y"])


# Motion parameters scaled towards the identity: linearly (angles, shifts) or in log (ratios).
_LINEAR = ("yaw_deg", "pitch_deg", "roll_deg", "view_deg", "shift_x", "shift_y")
_LOG = ("zoom", "distance")


def _scaled(params, s):
    return {k: (v * s if k in _LINEAR else v ** s if k in _LOG else v) for k, v in params.items()}


def _draw_full(rng, kind, r: MotionRanges) -> dict:
    log_uniform = lambda lo_hi: float(np.exp(rng.uniform(*np.log(lo_hi))))  # noqa: E731
    p = {"focal": WORK_SIZE[0] / 2 / math.tan(math.radians(rng.uniform(*r.fov_deg)) / 2),
         "zoom": log_uniform(r.zoom), "roll_deg": float(rng.uniform(-r.roll_deg, r.roll_deg))}
    if kind == "camera_rotation":
        p.update(yaw_deg=float(rng.uniform(-r.pan_deg, r.pan_deg)),
                 pitch_deg=float(rng.uniform(-r.pan_deg, r.pan_deg)))
    elif kind == "plane_viewpoint":
        p.update(view_deg=float(rng.uniform(0, r.view_deg)),
                 view_dir_deg=float(rng.uniform(0, 360)), distance=log_uniform(r.distance),
                 tilt_deg=float(rng.uniform(0, r.tilt_deg)),
                 tilt_dir_deg=float(rng.uniform(0, 360)))
    else:
        p.update(shift_x=float(rng.uniform(-r.shift_px, r.shift_px)),
                 shift_y=float(rng.uniform(-r.shift_px, r.shift_px)))
    return p


def draw_motion(rng: np.random.Generator, group: str, ranges: MotionRanges = MotionRanges(),
                max_draws: int = 1000):
    """A motion of ``group``: a kind (uniform over :data:`KINDS`) and its parameters from
    ``ranges``, scaled by ``s`` in [0, 1] towards the identity (angles and shifts times ``s``,
    ratios to the power ``s``) so that :func:`motion_offset` equals a target uniform in the
    group's interval; a draw that cannot reach the target, or that maps image_b's corners
    behind camera a, is drawn again. ``s`` is found by bisection (SciPy's ``brentq`` would do;
    this module stays NumPy/OpenCV only).

    Returns:
      ``(kind, params, h_ba)``: params with ``"scale"`` (``s``) and ``"target_offset_px"``.
    Raises:
      ValueError: an unknown group. RuntimeError: no draw fitted in ``max_draws`` tries.
    """
    if group not in GROUPS:
        raise ValueError(f"group must be one of {tuple(GROUPS)}; received {group!r}.")
    lo, hi = (TRAINED_OFFSET * g for g in GROUPS[group])
    kind, target = KINDS[int(rng.integers(len(KINDS)))], float(rng.uniform(lo, hi))
    for _ in range(max_draws):
        full = _draw_full(rng, kind, ranges)
        offset = lambda s: float(motion_offset(_homography(kind, _scaled(full, s))))  # noqa
        if not offset(1.0) >= target:
            continue
        a, b = 0.0, 1.0
        for _ in range(50):  # offset(a) < target <= offset(b)
            mid = 0.5 * (a + b)
            a, b = (mid, b) if offset(mid) < target else (a, mid)
        params = _scaled(full, b)
        h = _homography(kind, params)
        if geometry.in_front(h) and lo < motion_offset(h) <= hi:
            return kind, {**params, "scale": b, "target_offset_px": target}, h
    raise RuntimeError(f"no motion of group {group!r} in {max_draws} draws.")



# --------------------------------------------------------------------------------------------
# Rendering and degradation
# --------------------------------------------------------------------------------------------
def source_image(gray: np.ndarray, scale: int = 1) -> np.ndarray:
    """A photograph's gray ``uint8 [h, w]`` -> the ``uint8 [420 s, 560 s]`` source of its pairs
    at ``scale`` ``s`` (resized as the paper resizes to 320 x 240: area when shrinking, else
    bilinear)."""
    return sources.resize_to_protocol(np.asarray(gray, np.uint8), *_times(SOURCE_SIZE, scale))


def _times(size, scale):
    return tuple(int(scale) * v for v in size)


def to_scale(h_ba, scale: int = 1) -> np.ndarray:
    """A 320 x 240 frame ``h_ba`` ``[3, 3]`` in the frame of pairs rendered at ``scale`` ``s``
    (``320 s x 240 s``, pixel centres at integers): ``inv(R) @ h_ba @ R`` (``[2, 2] = 1``), ``R``
    the map of :func:`stnh_tf.data.sources.resize_matrix` from those pixels to 320 x 240's;
    ``h_ba`` itself at ``s = 1``."""
    if int(scale) == 1:
        return np.asarray(h_ba, np.float64)
    r = sources.resize_matrix(_times(WORK_SIZE, scale), WORK_SIZE)
    return geometry.scale_to_unit(np.linalg.inv(r) @ np.asarray(h_ba, np.float64) @ r)


def render_pair(source: np.ndarray, h_ba, scale: int = 1, origin=None) -> tuple:
    """``(image_a, image_b)`` float32 ``[240 s, 320 s]`` (0..255) of a ``[420 s, 560 s]`` source
    (:func:`source_image`, ``s = scale``): image_a its window at ``origin`` times ``s``
    (top-left ``(x, y)``, integers in ``[0, 240] x [0, 180]``; ``None``: :data:`MARGIN`, the
    central window), ``image_b(p) = source(T @ H @ p)`` (``H = to_scale(h_ba, s)``, ``h_ba`` in
    the 320 x 240 frame; ``T`` the translation by the window's corner: image_a's pixel ``H @ p``
    where that lies in image_a), bilinear, mirrored beyond the source.

    Raises:
      ValueError: a source of another shape, an ``origin`` that is not such a corner.
    """
    source = np.asarray(source, np.float32)
    if source.shape != _times(SOURCE_SIZE, scale)[::-1]:
        raise ValueError(f"source must have shape {list(_times(SOURCE_SIZE, scale)[::-1])}; "
                         f"received shape {source.shape}.")
    origin = MARGIN if origin is None else tuple(origin)
    if not (len(origin) == 2 and all(isinstance(v, (int, np.integer)) and 0 <= v <= 2 * m
                                     for v, m in zip(origin, MARGIN))):
        raise ValueError(f"origin must be integers (x, y) in [0, {2 * MARGIN[0]}] x "
                         f"[0, {2 * MARGIN[1]}]; received {origin!r}.")
    (mx, my), (w, h) = _times(origin, scale), _times(WORK_SIZE, scale)
    image_a = source[my:my + h, mx:mx + w].copy()
    image_b = cv2.warpPerspective(source, geometry.translation(mx, my) @ to_scale(h_ba, scale),
                                  (w, h), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_REFLECT_101)
    return image_a, image_b


def draw_degradation(rng: np.random.Generator, ranges: Degradation = Degradation()) -> dict:
    """One pair's degradation parameters (JSON-ready) from ``ranges``, with a noise seed."""
    return {"blur_sigma": float(rng.uniform(*ranges.blur_sigma)),
            "exposure_ev": float(rng.uniform(*ranges.exposure_ev)),
            "read_noise": float(rng.uniform(*ranges.read_noise)),
            "shot_noise": float(rng.uniform(*ranges.shot_noise)),
            "jpeg_quality": int(rng.integers(ranges.jpeg_quality[0], ranges.jpeg_quality[1] + 1)),
            "noise_seed": int(rng.integers(2 ** 63))}


def degrade(image: np.ndarray, p: dict, scale: int = 1) -> np.ndarray:
    """float ``[h, w]`` (0..255) -> ``uint8 [h, w]``: Gaussian blur (``p["blur_sigma"]`` times
    ``scale``: the same blur of a pair rendered at ``scale``, :func:`render_pair`), the
    exposure change (gain ``2 ** (ev / 2.2)``, clipped), Gaussian noise of variance
    ``read_noise^2 + shot_noise * value`` (from ``p["noise_seed"]``), rounding, then JPEG
    encoding and decoding at ``p["jpeg_quality"]`` (OpenCV's libjpeg)."""
    x = np.asarray(image, np.float32)
    if p["blur_sigma"] >= 0.1:
        x = cv2.GaussianBlur(x, (0, 0), p["blur_sigma"] * int(scale),
                             borderType=cv2.BORDER_REFLECT_101)
    x = np.clip(x * 2.0 ** (p["exposure_ev"] / 2.2), 0, 255)
    std = np.sqrt(p["read_noise"] ** 2 + p["shot_noise"] * x)
    x = x + std * np.random.default_rng(p["noise_seed"]).standard_normal(x.shape, np.float32)
    x = np.clip(np.rint(x), 0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", x, [cv2.IMWRITE_JPEG_QUALITY, p["jpeg_quality"]])
    return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)

