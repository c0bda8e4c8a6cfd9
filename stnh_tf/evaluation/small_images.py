"""How small an image ``estimate_images`` can use: the error of its estimate on image pairs shrunk
to a few pixels on one side (``experiments.benchmark_small_images``; the rule it backs:
:func:`stnh_tf.inference.image_input.check_image_size`).

Each pair is a bundled photograph at 320 x 240 and the same photograph warped by a known
``H_ba`` (the central square's corners moved by up to ``max_shift`` px, within the trained
range), both then shrunk to ``w x h`` with ``cv2.INTER_AREA``. ``estimate_images`` would resize
the shrunk pair back to 320 x 240 (:func:`stnh_tf.data.sources.resize_to_protocol`) and estimate
there; that resize is made here and the 320 x 240 images given to it (the same pixels, and its
homography is then the one in the 320 x 240 frame), so sizes the rule refuses are measured too.
The estimate is scored by the largest distance of the central square's four corners from the
true ones (px at 320 x 240). A side the image has lost is a motion the estimate cannot see.
"""

from __future__ import annotations

import cv2
import numpy as np

from stnh_tf import geometry
from stnh_tf.data import sources
from stnh_tf.inference import image_input


def _photographs() -> list:
    """The bundled photographs used here, gray uint8 ``[240, 320]``."""
    import skimage.data

    photos = []
    for name in ("astronaut", "camera", "chelsea", "coffee"):
        image = getattr(skimage.data, name)()
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        photos.append(cv2.resize(image, image_input.WORK_SIZE, interpolation=cv2.INTER_AREA))
    return photos


def small_image_errors(estimator, sizes, options: dict, pairs: int = 8, max_shift: float = 16.0,
                       seed: int = 0) -> dict:
    """Corner errors of ``estimator.estimate_images`` on ``pairs`` pairs shrunk to each size.

    Args:
      estimator: a :class:`~stnh_tf.inference.estimator.HomographyEstimator`.
      sizes: ``(w, h)`` sizes (one that ``check_image_size`` refuses is measured too, and
        reported with ``"refused": true``).
      options: name -> :class:`~stnh_tf.inference.options.EstimateOptions` (``None``: the
        estimator's default for images).
      pairs, max_shift, seed: the pairs (module docstring).
    Returns:
      ``{"rows": [{"size": [w, h], "patch_span_px": [sx, sy], "refused": bool,
      "<option name>": {"median_px": m, "max_px": x}}, ...], "pairs", "max_shift", "seed"}``.
    """
    rng = np.random.default_rng(seed)
    photos = _photographs()
    (x0, y0), s = image_input.PATCH_ORIGIN, image_input.PATCH_SIZE
    square = geometry.patch_corners(s) + [x0, y0]
    cases = []
    for k in range(pairs):
        image_a = photos[k % len(photos)]
        h_ba = geometry.homography_from_points(square, square + rng.uniform(-max_shift, max_shift,
                                                                            (4, 2)))
        image_b = cv2.warpPerspective(image_a, h_ba, image_input.WORK_SIZE,
                                      flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
        cases.append((image_a, image_b, h_ba))
    rows = []
    for w, h in sizes:
        span = [w * s / image_input.WORK_SIZE[0], h * s / image_input.WORK_SIZE[1]]
        row = {"size": [int(w), int(h)], "patch_span_px": span}
        try:
            image_input.check_image_size((w, h))
            row["refused"] = False
        except ValueError:
            row["refused"] = True
        for name, opts in options.items():
            errors = []
            for image_a, image_b, h_ba in cases:
                work_a, work_b = (sources.resize_to_protocol(cv2.resize(
                    x, (w, h), interpolation=cv2.INTER_AREA)) for x in (image_a, image_b))
                got = estimator.estimate_images(work_a, work_b, opts)  # the 320 x 240 frame
                errors.append(float(np.max(np.linalg.norm(
                    geometry.warp_points(got, square) - geometry.warp_points(h_ba, square),
                    axis=1))))
            row[name] = {"median_px": float(np.median(errors)), "max_px": float(np.max(errors))}
        rows.append(row)
    return {"rows": rows, "pairs": pairs, "max_shift": max_shift, "seed": seed}
