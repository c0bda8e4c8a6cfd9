"""Shared fixtures: real photographs (shipped with scikit-image) and paper-protocol homographies.

The normalization matrix and the OpenCV reference are written out here independently of
``stnh_tf.geometry`` so that the tests check the library against something it did not compute.
"""

import contextlib
import os

import cv2
import numpy as np
import pytest
import skimage.data

SIZE = 128


@contextlib.contextmanager
def keras_policy(name="mixed_bfloat16"):
    """Build Keras layers under the global dtype policy ``name``; float32 again afterwards."""
    import keras

    keras.mixed_precision.set_global_policy(name)
    try:
        yield
    finally:
        keras.mixed_precision.set_global_policy("float32")


@contextlib.contextmanager
def opencv_optimized(on: bool):
    """OpenCV's per-CPU SIMD kernels (``on``) or its portable code path, restored after: two
    machines' numerics on one machine."""
    import cv2

    before = cv2.useOptimized()
    cv2.setUseOptimized(on)
    try:
        yield on
    finally:
        cv2.setUseOptimized(before)


NARROW_FILTERS = (4, 4, 4, 4, 8, 8, 8, 8)
"""Convolution widths of the narrow network: 1/16 of the paper's (64, ..., 128), every layer
kept."""


@contextlib.contextmanager
def narrow_network():
    """Build the regression network with :data:`NARROW_FILTERS` (same layers, pooling, head and
    last layer; about 1/250 of a forward pass's work) for tests of wiring only: loading, saving,
    the estimator's and the card's bookkeeping, training plumbing. The paper's widths are
    tested in test_models; the full network's training in test_training's slow tests."""
    from stnh_tf.modeling import models

    with pytest.MonkeyPatch.context() as m:
        m.setattr(models, "CONV_FILTERS", NARROW_FILTERS)
        yield


@pytest.fixture
def narrow():
    """:func:`narrow_network` for one test."""
    with narrow_network():
        yield


def norm_matrix(w=SIZE, h=SIZE):
    """The paper's M, written independently of stnh_tf.geometry."""
    return np.array([[2.0 / w, 0.0, -1.0], [0.0, 2.0 / h, -1.0], [0.0, 0.0, 1.0]])


def paper_homography(rng, size=SIZE, rho=32):
    """H_ba (pixels) from corners perturbed uniformly in [-rho, rho] (DeTone et al. protocol)."""
    corners = np.array([[0, 0], [size, 0], [size, size], [0, size]], np.float32)
    offsets = rng.uniform(-rho, rho, size=(4, 2)).astype(np.float32)
    return cv2.getPerspectiveTransform(corners, corners + offsets).astype(np.float64)


def to_bar(h_pix, size=SIZE):
    """H_bar = M H inv(M), scaled so [2,2] = 1 (independent of the library)."""
    m = norm_matrix(size, size)
    hb = m @ h_pix @ np.linalg.inv(m)
    return hb / hb[2, 2]


def cv2_warp(image, h_pix, border=cv2.BORDER_CONSTANT):
    """OpenCV reference: out(p) = image(H @ p), bilinear, zero border (or ``border``, e.g.
    cv2.BORDER_REFLECT_101). image [h, w] or [h, w, C]."""
    h, w = image.shape[:2]
    return cv2.warpPerspective(image.astype(np.float32), h_pix, (w, h),
                               flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR,
                               borderMode=border, borderValue=0)


def inside_mask(h_pix, h=SIZE, w=SIZE):
    """Output pixels whose source point H @ p and its whole bilinear neighbourhood lie inside."""
    ys, xs = np.mgrid[0:h, 0:w]
    p = np.stack([xs.ravel(), ys.ravel(), np.ones(h * w)]).astype(np.float64)
    q = h_pix @ p
    x, y = q[0] / q[2], q[1] / q[2]
    ok = (q[2] > 0) & (x >= 0) & (x <= w - 1 - 1e-3) & (y >= 0) & (y <= h - 1 - 1e-3)
    return ok.reshape(h, w)


def photo_pairs(rng, n, margin=32):
    """``n`` paper-protocol pairs made here with OpenCV from scikit-image's photographs.

    Returns a dict: ``image`` (gray 320x240), ``xy`` (square corners), ``h_ba`` (patch frame),
    ``context`` (the square plus ``margin`` px), ``patch_a`` and ``patch_b`` (uint8 128x128).
    """
    photos = [skimage.data.astronaut(), skimage.data.coffee(), skimage.data.chelsea(),
              skimage.data.camera()]
    out = {"image": [], "xy": [], "h_ba": [], "context": [], "patch_a": [], "patch_b": []}
    for i in range(n):
        p = photos[i % len(photos)]
        gray = cv2.resize(p if p.ndim == 2 else cv2.cvtColor(p, cv2.COLOR_RGB2GRAY), (320, 240),
                          interpolation=cv2.INTER_AREA)
        x0, y0 = int(rng.integers(32, 161)), int(rng.integers(32, 81))
        h = paper_homography(rng)
        t = np.array([[1, 0, x0], [0, 1, y0], [0, 0, 1.0]])
        image_b = cv2.warpPerspective(gray, t @ h @ np.linalg.inv(t), (320, 240),
                                      flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
        out["image"].append(gray)
        out["xy"].append((x0, y0))
        out["h_ba"].append(h)
        out["context"].append(gray[y0 - margin:y0 + SIZE + margin, x0 - margin:x0 + SIZE + margin])
        out["patch_a"].append(gray[y0:y0 + SIZE, x0:x0 + SIZE])
        out["patch_b"].append(image_b[y0:y0 + SIZE, x0:x0 + SIZE])
    return {k: (np.stack(v) if k != "xy" else v) for k, v in out.items()}


def _crop(rgb_or_gray, x0, y0, size=SIZE, color=False):
    img = rgb_or_gray
    if img.ndim == 3 and not color:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    img = cv2.resize(img, (320, 240), interpolation=cv2.INTER_AREA)
    return img[y0:y0 + size, x0:x0 + size].astype(np.float32)


@pytest.fixture(scope="session")
def photo_patches():
    """Four 128x128 grayscale float32 patches (0..255) of real photographs."""
    return {
        "camera": _crop(skimage.data.camera(), 100, 40),
        "astronaut": _crop(skimage.data.astronaut(), 120, 50),
        "coffee": _crop(skimage.data.coffee(), 96, 64),
        "chelsea": _crop(skimage.data.chelsea(), 140, 60),
    }


@pytest.fixture(scope="session")
def color_patch():
    """A 128x128x3 float32 RGB patch of a real photograph."""
    return _crop(skimage.data.astronaut(), 120, 50, color=True)


@pytest.fixture
def pair_photos(tmp_path):
    """A folder of two photographs (``astronaut.png`` in colour, ``camera.png`` gray) to make
    camera-pair sets from."""
    folder = tmp_path / "photos"
    folder.mkdir()
    for name, photo in (("astronaut.png", skimage.data.astronaut()[..., ::-1]),
                        ("camera.png", skimage.data.camera())):
        cv2.imwrite(str(folder / name), photo)
    return folder


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


def ncc_reference(a, b, h_pix):
    """NCC of b and a warped by h_pix (OpenCV) over the pixels whose bilinear neighbourhood lies in
    a, leaving out those clipped in either (within half a grey level of 0 or 1, for images on the
    [0, 1] scale: issue 79); NaN if fewer than a quarter of them lie in a."""
    mask = inside_mask(h_pix)
    if mask.mean() < 0.25:
        return float("nan")
    warped = cv2_warp(a.astype(np.float64), h_pix)
    for image in (warped, b):
        if 0.0 <= image.min() and image.max() <= 1.0:
            mask = mask & (image > 0.5 / 255) & (image < 1.0 - 0.5 / 255)
    x = warped[mask]
    y = b.astype(np.float64)[mask]
    x, y = x - x.mean(), y - y.mean()
    return float((x * y).sum() / np.sqrt((x * x).sum() * (y * y).sum()))


def photo_folder(root, names):
    """``root`` (made if missing) holding a copy of one bundled photograph under each of
    ``names``."""
    import shutil

    from stnh_tf.data import bundled_photos

    root.mkdir(parents=True, exist_ok=True)
    photo = bundled_photos.bundled_image_files()[0][1]
    for name in names:
        shutil.copy(photo, root / name)
    return root


def constant_stage(h_pix, name="constant"):
    """A single-stage model that outputs H_bar = M @ h_pix @ inv(M) whatever its input (the narrow
    network, fc2's kernel zeroed: its width does not reach the output)."""
    from stnh_tf.modeling import models

    with narrow_network():
        model = models.build_stn_homography(name=name)
    fc2 = model.get_layer("regression").get_layer("fc2")
    kernel, _ = fc2.get_weights()
    fc2.set_weights([np.zeros_like(kernel), to_bar(h_pix).ravel()[:8].astype("float32")])
    return model


def binary_flags(modules) -> dict:
    """Each binary module's absl flags and their defaults, ``{module: {flag: default}}``, read by
    importing it in a fresh interpreter (its flags register at import), all modules at once."""
    import json
    import subprocess
    import sys

    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    code = ("import importlib, json, sys\nfrom absl import flags\n"
            "importlib.import_module(sys.argv[1])\n"
            "print(json.dumps({n: flags.FLAGS[n].default for n in flags.FLAGS}, default=str))\n")
    procs = {m: subprocess.Popen([sys.executable, "-c", code, m], cwd=repo, text=True,
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE)
             for m in modules}
    found = {}
    for module, proc in procs.items():
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, err[-2000:]
        found[module] = json.loads(out.strip().splitlines()[-1])
    return found
