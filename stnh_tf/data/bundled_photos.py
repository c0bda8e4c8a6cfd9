"""The natural photographs shipped inside installed packages (scikit-image, matplotlib, and
scikit-learn where installed): the ``bundled`` source of make_dataset and the tests' photographs,
needing no download and nothing from ``../shared``.
"""

from __future__ import annotations

import os

from stnh_tf.data.sources import load_gray_320x240

# Natural photographs shipped inside scikit-image's wheel (no download needed); synthetic
# images (checkerboards, logos, colour wheels, silhouettes) are left out on purpose.
_SKIMAGE_PHOTOS = ("astronaut.png", "brick.png", "camera.png", "cell.png", "chelsea.png",
                   "clock_motion.png", "coffee.png", "coins.png", "grass.png", "gravel.png",
                   "hubble_deep_field.jpg", "ihc.png", "moon.png", "motorcycle_left.png",
                   "motorcycle_right.png", "page.png", "retina.jpg", "rocket.jpg", "text.png")
_MATPLOTLIB_PHOTOS = ("grace_hopper.jpg",)
_SKLEARN_PHOTOS = ("china.jpg", "flower.jpg")


def bundled_image_files() -> list:
    """``(image_id, path)`` of the natural photographs shipped inside installed packages.

    scikit-image's bundled photographs (no download), matplotlib's sample photograph(s), and
    scikit-learn's two sample images when scikit-learn is installed. Sorted by id; ids look like
    ``"skimage/camera.png"``.
    """
    import importlib

    import skimage

    found = [(f"skimage/{n}", os.path.join(os.path.dirname(skimage.__file__), "data", n))
             for n in _SKIMAGE_PHOTOS]
    for package, names, folder in (  # optional: scikit-learn is not a dependency of this project
            ("matplotlib", _MATPLOTLIB_PHOTOS, lambda m: (m.get_data_path(), "sample_data")),
            ("sklearn", _SKLEARN_PHOTOS, lambda m: (os.path.dirname(m.__file__), "datasets",
                                                    "images"))):
        try:
            module = importlib.import_module(package)
        except ImportError:
            continue
        found += [(f"{package}/{n}", os.path.join(*folder(module), n)) for n in names]
    return sorted((i, p) for i, p in found if os.path.isfile(p))


def bundled_images() -> list:
    """``(image_id, uint8 [240, 320])`` for every :func:`bundled_image_files` photograph."""
    return [(i, load_gray_320x240(p)) for i, p in bundled_image_files()]
