"""The settings grid of the classical baselines, library core of ``experiments.tune_baselines``
(its docstring says how to run it): paper-protocol pairs drawn in memory from photographs
(:func:`stnh_tf.data.folder_counts.load_gray_images`,
:func:`stnh_tf.data.pairs.make_pair_arrays`), identity, the registered baselines and ORB / SIFT
settings around them (:func:`settings_grid`), each evaluated with
:func:`stnh_tf.evaluation.baselines.evaluate_baseline`. NumPy/OpenCV only.
"""

from __future__ import annotations


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


def run_tuning(image_dir=None, num_pairs=300, seed=0, grid="small", max_images=0):
    """Generate the pairs (from the first ``max_images`` photographs of ``image_dir``, 0: all;
    without it the bundled ones), evaluate every entry of :func:`settings_grid`; returns the
    result dict, with ``photographs``: the folder's
    :class:`~stnh_tf.data.folder_counts.FolderCounts` (None for the bundled ones)."""
    import cv2

    from stnh_tf.evaluation import baselines
    from stnh_tf.data import pairs
    from stnh_tf.evaluation.benchmarks import machine_info

    from stnh_tf.data import folder_counts

    if image_dir:
        images, counts = folder_counts.read_gray_folder(image_dir, max_images)
    else:
        images, counts = folder_counts.load_gray_images(None, max_images), None
    pa, pb, h = pairs.make_pair_arrays(images, num_pairs, seed)
    results = {}
    for label, name, overrides in settings_grid(grid):
        est = baselines.make_baseline(name, **overrides)
        metrics = baselines.evaluate_baseline(est, pa, pb, h)
        results[label] = {**metrics, "baseline": name, "overrides": overrides}
    return {
        "experiment": "tune_baselines",
        "image_dir": image_dir, "num_images": len(images), "num_pairs": num_pairs, "seed": seed,
        "grid": grid, "max_images": max_images,
        "photographs": counts.as_dict() if counts else None,
        "settings": {"orb_ransac": baselines.ORB_SETTINGS, "sift_ransac": baselines.SIFT_SETTINGS,
                     "orb_default": baselines.ORB_DEFAULT_SETTINGS},
        "machine": {**machine_info(), "opencv_threads": cv2.getNumThreads()},
        "results": results,
    }
