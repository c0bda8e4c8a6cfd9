r"""`make demo`: an offline self-check of the conventions on a bundled photograph.

  python -m experiments.demo [--seed=0] [--num_pairs=8]

Generates paper-protocol homographies (corners perturbed uniformly in [-32, 32]) on patches of
scikit-image's bundled photographs and checks, printing one JSON object, that

* ``normalize_homography`` equals ``M @ H @ inv(M)`` and round-trips,
* the four-point parameterization round-trips through ``cv2.getPerspectiveTransform``,
* the :class:`~stnh_tf.layers.SpatialTransformer` reproduces
  ``cv2.warpPerspective(patch, H_ba, flags=WARP_INVERSE_MAP | INTER_LINEAR)``,
* the identity estimate's mean corner error (about 24.6 px on this protocol).

Exits non-zero if any check fails.
"""

from __future__ import annotations

import json
import sys

from absl import app, flags

flags.DEFINE_integer("seed", 0, "Seed of the homographies.")
flags.DEFINE_integer("num_pairs", 8, "Number of random homographies.")
FLAGS = flags.FLAGS


def self_check(seed: int = 0, num_pairs: int = 8) -> dict:
    import cv2
    import keras
    import numpy as np
    import skimage.data

    from stnh_tf import geometry
    from stnh_tf.layers import SpatialTransformer

    rng = np.random.default_rng(seed)
    gray = cv2.resize(cv2.cvtColor(skimage.data.astronaut(), cv2.COLOR_RGB2GRAY), (320, 240))
    patch = gray[50:178, 120:248].astype(np.float32)
    corners = geometry.patch_corners().astype(np.float32)
    h_pix = np.stack([cv2.getPerspectiveTransform(
        corners, corners + rng.uniform(-32, 32, (4, 2)).astype(np.float32)) for _ in range(num_pairs)])
    m = geometry.normalization_matrix()
    h_bar = geometry.normalize_homography(h_pix)
    ref_bar = m @ h_pix @ np.linalg.inv(m)
    ref_bar /= ref_bar[:, 2:3, 2:3]
    offsets = geometry.homography_to_offsets(h_pix)
    out = keras.ops.convert_to_numpy(SpatialTransformer()(
        [np.repeat(patch[None, ..., None], num_pairs, 0), geometry.matrix_to_vector(h_bar).astype(np.float32)]))
    stn_diff = []
    for i in range(num_pairs):
        ref = cv2.warpPerspective(patch, h_pix[i], (128, 128), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
        stn_diff.append(float(np.abs(out[i, ..., 0] - ref).mean()))
    result = {
        "normalize_max_abs_error": float(np.abs(h_bar - ref_bar).max()),
        "denormalize_round_trip_max_abs_error": float(np.abs(geometry.denormalize_homography(h_bar) - h_pix).max()),
        "four_point_round_trip_max_abs_error": float(np.abs(geometry.offsets_to_homography(offsets) - h_pix).max()),
        "stn_vs_opencv_mean_abs_gray_levels": max(stn_diff),
        "identity_mace_px": float(geometry.mean_corner_error(np.broadcast_to(np.eye(3), h_pix.shape), h_pix)),
    }
    result["ok"] = bool(result["normalize_max_abs_error"] < 1e-9
                        and result["denormalize_round_trip_max_abs_error"] < 1e-6
                        and result["four_point_round_trip_max_abs_error"] < 1e-4
                        and result["stn_vs_opencv_mean_abs_gray_levels"] < 0.5)
    return result


def main(argv):
    del argv
    result = self_check(FLAGS.seed, FLAGS.num_pairs)
    print(json.dumps(result, indent=2))
    if not result["ok"]:
        sys.exit("demo: a convention check failed (see above).")


if __name__ == "__main__":
    app.run(main)
