"""The paper's pair-generation protocol (DeTone et al. 2016; Zhou & Li 2019, "Dataset").

No TensorFlow or Keras import: data-generation workers and ``PairSequence`` use this module.
Conventions are :mod:`stnh_tf.geometry`'s (see ``docs/conventions.md``).

For one gray ``image_a`` (``uint8 [240, 320]``) and sample parameters drawn by :func:`draw_params`:

1. the 128x128 square has top-left corner ``(x0, y0)``, integers drawn uniformly with the square
   inside the image less a 32-px border: ``x0 in [32, 160]``, ``y0 in [32, 80]``;
2. each of its four corners is perturbed by independent uniform offsets in ``[-32, 32]`` (float64);
3. ``H_ba`` (image frame, patch_b -> patch_a, i.e. ``p_a ~ H_ba @ p_b``) maps the square's corners
   onto the perturbed corners (:func:`geometry.homography_from_points`, = getPerspectiveTransform);
4. ``image_b = cv2.warpPerspective(image_a, H_ba, (320, 240), WARP_INVERSE_MAP | INTER_LINEAR)``,
   so ``image_b(p) = image_a(H_ba @ p)``, zero outside;
5. ``patch_a``, ``patch_b`` are the crops of image_a and image_b at the square (patch_b is computed
   directly as the square's window of image_b, the same pixels);
6. ``h_ba`` is the same map in the patch frame (``inv(T) @ H_ba @ T``);
   ``h_bar = normalize(h_ba)[:8]`` with the paper's ``M`` (W = H = 128), ``[2, 2] = 1``;
7. ``patch_a_t(p) = patch_a(h_ba @ p)`` (``warpPerspective`` of patch_a, bilinear, zero outside);
8. ``context_a = image_a[y0-32 : y0+160, x0-32 : x0+160]`` (``uint8 [192, 192]``): the square
   plus a 32-px margin, enough to re-crop patch_a after a later stage's warp.

Randomness: the parameters of image ``i`` come from ``np.random.default_rng([seed, i])`` only, so
a sample depends on (seed, image index, image) and not on worker count or processing order. The
global sample index is ``i * samples_per_image + k``.

Optional, not the paper's: with ``Protocol(photometric=PhotometricChange())`` patch_b also gets an
independent photometric change (gamma, contrast, brightness, Gaussian noise;
:func:`apply_photometric`), drawn from the same generator after every geometric draw, so the
squares, perturbations, ``h_ba``, patch_a and patch_a_t are those of the unchanged protocol.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from stnh_tf import geometry


@dataclasses.dataclass(frozen=True)
class PhotometricChange:
    """Ranges of the photometric change of patch_b (a training augmentation; not the paper's).

    For ``x = patch_b / 255``: ``x' = clip((x ** gamma - 0.5) * contrast + 0.5 + brightness + n)``
    with ``gamma`` log-uniform in ``[1/gamma_max, gamma_max]``, ``contrast`` uniform in
    ``[1 - contrast_range, 1 + contrast_range]``, ``brightness`` uniform in
    ``[-brightness_range, brightness_range]`` and ``n`` Gaussian noise of a standard deviation
    uniform in ``[0, noise_max]``; rounded back to uint8."""

    gamma_max: float = 1.5
    contrast_range: float = 0.3
    brightness_range: float = 0.15
    noise_max: float = 0.02

    def __post_init__(self):
        if not (self.gamma_max >= 1 and 0 <= self.contrast_range < 1
                and 0 <= self.brightness_range <= 1 and 0 <= self.noise_max <= 1):
            raise ValueError(f"photometric ranges out of bounds: {self}.")


@dataclasses.dataclass(frozen=True)
class Protocol:
    """Every parameter of the generation protocol (recorded in ``metadata.json``)."""

    image_width: int = geometry.IMAGE_WIDTH        # every image is resized to this width
    image_height: int = geometry.IMAGE_HEIGHT      # ... and this height
    patch_size: int = geometry.PATCH_SIZE          # side of the square patches
    border: int = geometry.MAX_PERTURBATION        # excluded image border around the square
    max_perturbation: float = float(geometry.MAX_PERTURBATION)  # corner offsets in [-rho, rho]
    samples_per_image: int = 3                     # squares drawn per image
    context_margin: int = geometry.MAX_PERTURBATION  # margin of context_a around the square
    photometric: PhotometricChange | None = None   # change of patch_b (None: the paper's pairs)

    def __post_init__(self):
        if self.samples_per_image < 1:
            raise ValueError(f"samples_per_image must be >= 1; received {self.samples_per_image}.")
        if self.context_margin > self.border:
            raise ValueError(f"context_margin ({self.context_margin}) must not exceed the excluded "
                             f"border ({self.border}), or context_a would leave the image.")
        if self.patch_size + 2 * self.border > min(self.image_width, self.image_height):
            raise ValueError(f"a {self.patch_size}-px square with a {self.border}-px border does "
                             f"not fit a {self.image_width}x{self.image_height} image.")

    @property
    def context_size(self) -> int:
        return self.patch_size + 2 * self.context_margin

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d.update(
            context_size=self.context_size,
            x0_range=[self.border, self.image_width - self.border - self.patch_size],
            y0_range=[self.border, self.image_height - self.border - self.patch_size],
            perturbation="independent uniform float64 in [-rho, rho] for each corner coordinate",
            square_position="uniform integers in x0_range, y0_range (inclusive)",
            rng="np.random.default_rng([seed, image_index]); per image: x0, y0, offsets[4,2] "
                "for each of the samples_per_image squares, in that order",
            warp="image_b = cv2.warpPerspective(image_a, H_ba, (W, H), WARP_INVERSE_MAP | "
                 "INTER_LINEAR), zero border; patch_b computed directly as the square's window "
                 "of image_b (warp of image_a by H_ba @ T(x0, y0), same pixels)",
            patch_a_t="cv2.warpPerspective(patch_a, h_ba_patch, (S, S), WARP_INVERSE_MAP | "
                      "INTER_LINEAR), zero outside patch_a",
            normalization="H_bar = M H M^-1 / [2,2], M = [[2/W,0,-1],[0,2/H,-1],[0,0,1]], W=H=S",
            index="image_index * samples_per_image + k",
        )
        if self.photometric is not None:
            d["photometric_rule"] = (
                "patch_b only: x = patch_b/255; x = clip((x**gamma - 0.5)*contrast + 0.5 + "
                "brightness + sigma * N(0, 1) (float32 standard_normal)); per sample "
                "gamma = gamma_max**u(-1,1), contrast = "
                "1 + contrast_range*u(-1,1), brightness = brightness_range*u(-1,1), sigma = "
                "noise_max*u(0,1), noise seed = integers(2**63), drawn after all geometric draws")
        return d


@dataclasses.dataclass(frozen=True)
class PairParams:
    """Random parameters of one sample: square top-left ``(x0, y0)`` and ``offsets [4, 2]``
    (float64, for the corners ``(0,0), (S,0), (S,S), (0,S)`` of :func:`geometry.patch_corners`)."""

    x0: int
    y0: int
    offsets: np.ndarray
    photometric: tuple | None = None  # (gamma, contrast, brightness, sigma, noise_seed) or None


def image_rng(seed: int, image_index: int) -> np.random.Generator:
    """The generator of image ``image_index``: ``np.random.default_rng([seed, image_index])``."""
    return np.random.default_rng([int(seed), int(image_index)])


def draw_params(rng: np.random.Generator, protocol: Protocol = Protocol()) -> list:
    """Draw ``protocol.samples_per_image`` :class:`PairParams` (x0, y0, offsets; in that order)."""
    p = protocol
    out = []
    for _ in range(p.samples_per_image):
        x0 = int(rng.integers(p.border, p.image_width - p.border - p.patch_size, endpoint=True))
        y0 = int(rng.integers(p.border, p.image_height - p.border - p.patch_size, endpoint=True))
        offsets = rng.uniform(-p.max_perturbation, p.max_perturbation, size=(4, 2))
        out.append(PairParams(x0, y0, offsets))
    if p.photometric is not None:  # after every geometric draw: the geometry stays the same
        c = p.photometric
        for k, prm in enumerate(out):
            u = rng.uniform(-1.0, 1.0, size=3)
            change = (float(c.gamma_max ** u[0]), float(1.0 + c.contrast_range * u[1]),
                      float(c.brightness_range * u[2]), float(c.noise_max * rng.uniform()),
                      int(rng.integers(2 ** 63)))
            out[k] = dataclasses.replace(prm, photometric=change)
    return out


def apply_photometric(patch: np.ndarray, change: tuple) -> np.ndarray:
    """``patch`` (uint8) after the photometric change ``(gamma, contrast, brightness, sigma,
    noise_seed)`` of :class:`PhotometricChange`; uint8, same shape. The pixel-wise part is a
    256-entry table; the noise is ``sigma * default_rng(noise_seed).standard_normal(shape,
    float32)``, added before rounding."""
    gamma, contrast, brightness, sigma, noise_seed = change
    levels = np.arange(256, dtype=np.float32) / np.float32(255.0)
    table = ((np.power(levels, np.float32(gamma)) - 0.5) * np.float32(contrast)
             + np.float32(0.5 + brightness)) * np.float32(255.0)
    x = table[patch]
    if sigma > 0:
        noise = np.random.default_rng(noise_seed).standard_normal(patch.shape, np.float32)
        x += noise * np.float32(sigma * 255.0)
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def make_pair(image_a: np.ndarray, params: PairParams, protocol: Protocol = Protocol()) -> dict:
    """One training sample from ``image_a`` (``uint8 [H, W]``, the protocol's size).

    Returns a dict of NumPy arrays:
      ``patch_a``, ``patch_b``, ``patch_a_t``: uint8 ``[S, S]``;
      ``context_a``: uint8 ``[S + 2m, S + 2m]`` (m = context_margin);
      ``h_ba``: float64 ``[3, 3]``, pixel patch frame, patch_b -> patch_a, ``[2,2] = 1``;
      ``h_bar``: float32 ``[8]``, first eight entries of ``normalize(h_ba)``;
      ``square_xy``: int64 ``[2]`` = ``(x0, y0)`` in image_a.
    """
    p = protocol
    if image_a.shape != (p.image_height, p.image_width) or image_a.dtype != np.uint8:
        raise ValueError(f"image_a must be uint8 [{p.image_height}, {p.image_width}]; received "
                         f"{image_a.dtype} {image_a.shape}.")
    s, x0, y0, m = p.patch_size, params.x0, params.y0, p.context_margin
    square = geometry.patch_corners(s) + np.array([x0, y0], np.float64)
    a_from_b_image = geometry.homography_from_points(square, square + params.offsets)
    # patch_b = image_b[y0:y0+S, x0:x0+S] with image_b(p) = image_a(H_ba @ p): only the square's
    # window of image_b is computed (sampling image_a at H_ba @ T @ p), 4.7x less work than
    # warping all of image_b and the same pixels (tests compare with the full-image warp).
    patch_b = cv2.warpPerspective(image_a, a_from_b_image @ geometry.translation(x0, y0), (s, s),
                                  flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if params.photometric is not None:
        patch_b = apply_photometric(patch_b, params.photometric)
    patch_a = np.ascontiguousarray(image_a[y0:y0 + s, x0:x0 + s])
    a_from_b = geometry.image_to_patch(a_from_b_image, x0, y0)
    patch_a_t = cv2.warpPerspective(patch_a, a_from_b, (s, s),
                                    flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    h_bar = geometry.matrix_to_vector(geometry.normalize_homography(a_from_b, s, s))
    return {
        "patch_a": patch_a,
        "patch_b": patch_b,
        "patch_a_t": patch_a_t,
        "context_a": np.ascontiguousarray(image_a[y0 - m:y0 + s + m, x0 - m:x0 + s + m]),
        "h_ba": a_from_b,
        "h_bar": h_bar.astype(np.float32),
        "square_xy": np.array([x0, y0], np.int64),
    }



def make_pair_arrays(images, num_pairs: int, seed: int):
    """``num_pairs`` pairs made in memory: uint8 ``patches_a``, ``patches_b`` ``[N, 128, 128]`` and
    pixel ``H_ba`` ``[N, 3, 3]`` (patch_b -> patch_a). Image ``i % len(images)`` is used for pair
    ``i``; one seeded generator draws them all (one square per draw)."""
    rng = np.random.default_rng(seed)
    one = Protocol(samples_per_image=1)
    samples = [make_pair(images[i % len(images)], draw_params(rng, one)[0], one)
               for i in range(num_pairs)]
    return (np.stack([s["patch_a"] for s in samples]), np.stack([s["patch_b"] for s in samples]),
            np.stack([s["h_ba"] for s in samples]))

def make_image_samples(image_a: np.ndarray, seed: int, image_index: int, image_id: str,
                       protocol: Protocol = Protocol()) -> list:
    """Every stage-1 sample of one image, as dicts ready for ``features.serialize_example``.

    Adds to :func:`make_pair`'s fields: ``h_prev`` (identity: no earlier stage), ``h_mask`` 1.0
    (ground truth present), ``image_id`` and the global ``index``.
    """
    params = draw_params(image_rng(seed, image_index), protocol)
    samples = []
    for k, prm in enumerate(params):
        sample = make_pair(image_a, prm, protocol)
        sample.update(h_prev=np.eye(3), h_mask=np.float32(1.0), image_id=image_id,
                      index=np.int64(image_index * protocol.samples_per_image + k))
        samples.append(sample)
    return samples


def generate_item_samples(item, seed: int, protocol: Protocol = Protocol()) -> list:
    """Worker function of the stage-1 writer: a work item -> its samples.

    ``item`` has ``index`` (image index, seeds the RNG), ``item_id`` and ``payload`` (a path,
    encoded image bytes, or a decoded array); see ``stnh_tf.data.writer.WorkItem``.

    Raises:
      sources.ImageDecodeError: the image cannot be read (the writer records the reason).
    """
    from stnh_tf.data import sources

    image_a = sources.as_gray_320x240(item.payload)
    return make_image_samples(image_a, seed, item.index, item.item_id, protocol)
