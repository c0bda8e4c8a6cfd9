"""The offline demo, library core of ``experiments.demo`` (``make demo``; its docstring lists the
steps): :func:`run_demo` checks the conventions against OpenCV (:func:`self_check`), makes seeded
test pairs from the bundled photographs, and compares identity, ORB / SIFT + RANSAC and the
shipped models (:func:`shipped_models`) on them, writing ``results.json`` and a Fig. 5-style PNG.
"""

from __future__ import annotations

import os
import time



def self_check(seed: int = 0, num_pairs: int = 8) -> dict:
    """Normalization, four-point round trip and the STN against OpenCV on a bundled photograph."""
    import cv2
    import keras
    import numpy as np
    import skimage.data

    from stnh_tf import geometry
    from stnh_tf.modeling.layers import SpatialTransformer

    rng = np.random.default_rng(seed)
    gray = cv2.resize(cv2.cvtColor(skimage.data.astronaut(), cv2.COLOR_RGB2GRAY), (320, 240))
    patch = gray[50:178, 120:248].astype(np.float32)
    corners = geometry.patch_corners().astype(np.float32)
    h_pix = np.stack([cv2.getPerspectiveTransform(
        corners, corners + rng.uniform(-32, 32, (4, 2)).astype(np.float32))
        for _ in range(num_pairs)])
    m = geometry.normalization_matrix()
    h_bar = geometry.normalize_homography(h_pix)
    ref_bar = m @ h_pix @ np.linalg.inv(m)
    ref_bar /= ref_bar[:, 2:3, 2:3]
    out = keras.ops.convert_to_numpy(SpatialTransformer()(
        [np.repeat(patch[None, ..., None], num_pairs, 0),
         geometry.matrix_to_vector(h_bar).astype(np.float32)]))
    stn_diff = max(float(np.abs(out[i, ..., 0] - cv2.warpPerspective(
        patch, h_pix[i], (128, 128), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)).mean())
        for i in range(num_pairs))
    result = {
        "normalize_max_abs_error": float(np.abs(h_bar - ref_bar).max()),
        "four_point_round_trip_max_abs_error": float(np.abs(
            geometry.offsets_to_homography(geometry.homography_to_offsets(h_pix)) - h_pix).max()),
        "stn_vs_opencv_mean_abs_gray_levels": stn_diff,
    }
    result["ok"] = bool(result["normalize_max_abs_error"] < 1e-9
                        and result["four_point_round_trip_max_abs_error"] < 1e-4
                        and stn_diff < 0.5)
    return result


def shipped_models() -> dict:
    """``{name: [stage model paths]}`` of the weights shipped in ``stnh_tf/weights``: the default
    (its first stage, and all its stages if several), the paper recipe's CPU-budget weights in
    ``paper_recipe`` and the stages trained at the paper's schedule in ``paper_schedule``
    (likewise)."""
    from stnh_tf.inference import model_files

    d = model_files.default_weights_dir()
    found = {}
    for label, folder in (("shipped default", None),
                          ("paper recipe", os.path.join(d, model_files.PAPER_RECIPE_WEIGHTS)),
                          ("paper's schedule",
                           os.path.join(d, model_files.PAPER_SCHEDULE_WEIGHTS))):
        try:
            stages = model_files.resolve_model_paths(folder)
        except FileNotFoundError:
            continue
        found[f"{label}, 1 stage"] = stages[:1]
        if len(stages) > 1:
            found[f"{label}, {len(stages)} stages"] = stages
    return found


def run_demo(output_dir: str, seed: int = 0, samples_per_image: int = 3, examples: int = 4,
             printer=print) -> dict:
    """Run the demo into ``output_dir`` (its test pairs are made once and reused); prints the
    table through ``printer``; returns the result, also written to ``results.json`` (an existing
    one must be an earlier demo's: :func:`stnh_tf.evaluation.summaries.check_json_out`;
    ``OSError`` before any work otherwise). ``examples=0``: no figure."""
    import numpy as np

    from stnh_tf.data import stage1
    from stnh_tf import geometry, hierarchy
    from stnh_tf.paper import figures
    from stnh_tf.evaluation import mace as evaluation
    from stnh_tf.data import tfrecords as data
    from stnh_tf.modeling import runner
    from stnh_tf.evaluation.baselines import FIGURE_BASELINES

    from stnh_tf.evaluation import summaries

    t_start = time.time()
    results_json = os.path.join(output_dir, "results.json")
    summaries.check_json_out(results_json, "demo")  # (a reproduction's results.json, say)
    check = self_check(seed)
    printer(f"conventions vs OpenCV: {'ok' if check['ok'] else 'FAILED'} "
            f"(STN mean abs diff {check['stn_vs_opencv_mean_abs_gray_levels']:.3f} gray levels)")
    data_dir = os.path.join(output_dir, "bundled_test")
    if data.has_split(data_dir, "test"):  # made before: of this seed and count, or made anew
        made = data.split_info(data_dir, "test")
        if (made.get("seed"), made.get("protocol", {}).get("samples_per_image")) != (
                seed, samples_per_image):
            raise ValueError(f"{data_dir} holds test pairs of seed {made.get('seed')} and "
                             f"{made.get('protocol', {}).get('samples_per_image')} a "
                             f"photograph; this demo asks for seed {seed} and "
                             f"{samples_per_image}: give those, or another --output_dir.")
    else:
        stage1.make_dataset("bundled", data_dir, "test", seed=seed,
                            samples_per_image=samples_per_image,
                            num_shards=1, num_workers=1, log=lambda *a, **k: None)
    samples = data.load_arrays(data_dir, "test")
    n = len(samples["h_ba"])
    rows = {}
    base = evaluation.evaluate((), data_dir, "test", tuple(FIGURE_BASELINES))
    for name, label in FIGURE_BASELINES.items():
        r = base["baselines"][name]
        rows[label] = {
            "mace": r["mace"], "median": r["median"], "failure_rate": r["failure_rate"],
            "ms_per_pair": r["ms_per_pair"]}
    predictions = {}
    models = shipped_models()
    if not models:
        printer("no shipped weights in stnh_tf/weights: showing the baselines only")
    predictors = {}  # one per file: stage 1, shared by two rows, is loaded and traced once

    def predictor(path):
        if path not in predictors:
            predictors[path] = runner.predictor(runner.load_model(path))
        return predictors[path]

    for name, paths in models.items():
        stages = [predictor(p) for p in paths]
        hierarchy.run_hierarchy(stages, samples["context_a"][:2], samples["patch_b"][:2])  # warm-up
        t0 = time.perf_counter()
        run = hierarchy.run_hierarchy(stages, samples["context_a"], samples["patch_b"])
        ms = 1e3 * (time.perf_counter() - t0) / n
        errors = geometry.corner_errors(run["h"], samples["h_ba"])
        rows[name] = {"mace": float(errors.mean()), "median": float(np.median(errors)),
                      "failure_rate": None, "ms_per_pair": ms}
        predictions[name] = run["h"]
    printer(f"\n{n} test pairs from {len(set(samples['image_id']))} bundled photographs "
            f"(seed {seed}):")
    printer(f"{'method':<36} {'MACE px':>8} {'median':>8} {'fails':>6} {'ms/pair':>8}")
    for name, r in rows.items():
        fails = "-" if r["failure_rate"] is None else f"{100 * r['failure_rate']:.0f}%"
        printer(f"{name:<36} {r['mace']:8.2f} {r['median']:8.2f} {fails:>6} "
                f"{r['ms_per_pair']:8.2f}")
    png = None
    if predictions and examples:
        best = min(predictions, key=lambda k: rows[k]["mace"])
        idx = np.linspace(0, n - 1, min(examples, n)).astype(int)
        png = figures.prediction_examples(
            samples["context_a"][idx], samples["patch_b"][idx], samples["h_ba"][idx],
            predictions[best][idx], os.path.join(output_dir, "prediction_examples.png"),
            titles=[str(samples["image_id"][i]) for i in idx])
        printer(f"\nFig. 5-style examples ({best}): {png}")
    result = {"conventions": check, "num_pairs": n, "seed": seed, "methods": rows, "figure": png,
              "wall_s": time.time() - t_start}
    summaries.write_json_out(result, results_json, "demo", sort_keys=False)
    return result
