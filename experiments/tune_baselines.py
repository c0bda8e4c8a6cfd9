r"""Justify the settings of the classical baselines (ORB/SIFT + RANSAC) on paper-protocol pairs.

Generates ``--num_pairs`` synthetic pairs (DeTone et al. protocol, as in
``docs/conventions.md``) from the photographs in ``--image_dir`` (or, without it, from
scikit-image's bundled photographs), evaluates identity, the registered baselines and a small grid
of ORB and SIFT settings around them, and prints one JSON object (MACE, median, p90, p99, failure
rate, ms per pair for each).

  python -m experiments.tune_baselines --image_dir=../shared/data/coco_mini/train \
      --num_pairs=300 --seed=0 --json_out=/tmp/tune_baselines.json

Pairs come from the data generator's own protocol (:mod:`stnh_tf.sources` decoding and
resizing, :mod:`stnh_tf.pairs`), drawn in memory with one seeded generator.
"""

from __future__ import annotations


from absl import app, flags

from experiments import common

flags.DEFINE_string("image_dir", None, "Folder of photographs (jpg/png). Default: scikit-image's.")
flags.DEFINE_integer("num_pairs", 300, "Number of synthetic pairs.")
flags.DEFINE_integer("seed", 0, "Seed of the pair generator.")
flags.DEFINE_enum("grid", "small", ["none", "small"],
                  "Settings grid: none (registered baselines only) or small.")
flags.DEFINE_string("json_out", None, "Also write the JSON result to this file.")

FLAGS = flags.FLAGS



def load_gray_images(image_dir=None):
    """uint8 ``[240, 320]`` grayscale images (the data generator's decoding and resizing): every
    image file below ``image_dir`` (sorted; unreadable files skipped) or the bundled photographs."""
    from stnh_tf import sources

    if not image_dir:
        return [img for _, img in sources.bundled_images()]
    images = []
    for path in sources.list_image_files(image_dir):
        try:
            images.append(sources.load_gray_320x240(path))
        except (sources.ImageDecodeError, OSError):
            pass
    if not images:
        raise ValueError(f"no readable images in {image_dir}.")
    return images


def make_pairs(images, num_pairs, seed):
    """Paper-protocol pairs (:mod:`stnh_tf.pairs`, the data generator's protocol): uint8
    ``patches_a``, ``patches_b`` ``[N, 128, 128]`` and pixel ``H_ba`` ``[N, 3, 3]`` (patch_b ->
    patch_a). Image ``i % len(images)`` is used for pair i; one seeded generator draws them all."""
    import numpy as np

    from stnh_tf import pairs

    rng = np.random.default_rng(seed)
    one = pairs.Protocol(samples_per_image=1)
    samples = [pairs.make_pair(images[i % len(images)], pairs.draw_params(rng, one)[0], one)
               for i in range(num_pairs)]
    return (np.stack([s["patch_a"] for s in samples]), np.stack([s["patch_b"] for s in samples]),
            np.stack([s["h_ba"] for s in samples]))


def settings_grid(grid="small"):
    """``[(label, baseline name, settings overrides)]``: the registered baselines first."""
    runs = [("identity", "identity", {}), ("orb_default", "orb_default", {}),
            ("orb_ransac", "orb_ransac", {}), ("sift_ransac", "sift_ransac", {})]
    if grid == "none":
        return runs
    orb = [
        ("orb/defaults_ratio0.8", "orb_default", {"ratio": 0.8, "cross_check": False}),
        ("orb/edge31_patch31_fast5", "orb_ransac", {"edgeThreshold": 31, "patchSize": 31}),
        ("orb/edge19_patch19", "orb_ransac", {"edgeThreshold": 19, "patchSize": 19}),
        ("orb/edge5_patch11", "orb_ransac", {"edgeThreshold": 5, "patchSize": 11}),
        ("orb/edge10_patch15_fast20", "orb_ransac", {"fastThreshold": 20}),
        ("orb/fast10", "orb_ransac", {"fastThreshold": 10}),
        ("orb/nlevels8", "orb_ransac", {"nlevels": 8}),
        ("orb/nlevels2", "orb_ransac", {"nlevels": 2}),
        ("orb/nfeatures500", "orb_ransac", {"nfeatures": 500}),
        ("orb/nfeatures2000", "orb_ransac", {"nfeatures": 2000}),
        ("orb/ratio0.75", "orb_ransac", {"ratio": 0.75}),
        ("orb/ratio0.9", "orb_ransac", {"ratio": 0.9}),
        ("orb/ratio0.85_no_crosscheck", "orb_ransac", {"ratio": 0.85, "cross_check": False}),
        ("orb/ratio+crosscheck", "orb_ransac", {"cross_check": True}),
        ("orb/thresh2", "orb_ransac", {"ransac_thresh": 2.0}),
        ("orb/thresh5", "orb_ransac", {"ransac_thresh": 5.0}),
        ("orb/magsac", "orb_ransac", {"ransac_method": "USAC_MAGSAC"}),
        ("orb/min_inliers4", "orb_ransac", {"min_inliers": 4}),
        ("orb/min_inliers10", "orb_ransac", {"min_inliers": 10}),
    ]
    sift = [
        ("sift/defaults_ratio0.75", "sift_ransac",
         {"contrastThreshold": 0.04, "ratio": 0.75, "ransac_thresh": 5.0}),
        ("sift/contrast0.04", "sift_ransac", {"contrastThreshold": 0.04}),
        ("sift/contrast0.02", "sift_ransac", {"contrastThreshold": 0.02}),
        ("sift/ratio0.7", "sift_ransac", {"ratio": 0.7}),
        ("sift/ratio0.75", "sift_ransac", {"ratio": 0.75}),
        ("sift/ratio0.85", "sift_ransac", {"ratio": 0.85}),
        ("sift/crosscheck", "sift_ransac", {"cross_check": True}),
        ("sift/thresh2", "sift_ransac", {"ransac_thresh": 2.0}),
        ("sift/thresh5", "sift_ransac", {"ransac_thresh": 5.0}),
        ("sift/magsac", "sift_ransac", {"ransac_method": "USAC_MAGSAC"}),
        ("sift/min_inliers4", "sift_ransac", {"min_inliers": 4}),
        ("sift/min_inliers10", "sift_ransac", {"min_inliers": 10}),
        ("sift/edge20", "sift_ransac", {"edgeThreshold": 20.0}),
    ]
    return runs + orb + sift


def run_tuning(image_dir=None, num_pairs=300, seed=0, grid="small"):
    """Generate the pairs, evaluate every entry of :func:`settings_grid`; returns the result dict."""
    import cv2

    from stnh_tf import baselines

    images = load_gray_images(image_dir)
    pa, pb, h = make_pairs(images, num_pairs, seed)
    results = {}
    for label, name, overrides in settings_grid(grid):
        est = baselines.make_baseline(name, **overrides)
        metrics = baselines.evaluate_baseline(est, pa, pb, h)
        results[label] = {**metrics, "baseline": name, "overrides": overrides}
    return {
        "experiment": "tune_baselines",
        "image_dir": image_dir, "num_images": len(images), "num_pairs": num_pairs, "seed": seed,
        "grid": grid,
        "settings": {"orb_ransac": baselines.ORB_SETTINGS, "sift_ransac": baselines.SIFT_SETTINGS,
                     "orb_default": baselines.ORB_DEFAULT_SETTINGS},
        "machine": {**common.machine_info(), "opencv_threads": cv2.getNumThreads()},
        "results": results,
    }


def main(argv):
    del argv
    result = run_tuning(FLAGS.image_dir, FLAGS.num_pairs, FLAGS.seed, FLAGS.grid)
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
