r"""Benchmark of the SpatialTransformer: forward and forward+backward vs OpenCV.

Measures the median wall time of
  * STN forward on ``[batch, size, size, 1]`` photograph patches with paper-protocol homographies
    (corners perturbed uniformly in [-32, 32] at size 128, scaled with size), in a ``tf.function``;
  * STN forward + backward (gradient of ``sum(out * w)`` w.r.t. both image and homography);
  * ``cv2.warpPerspective`` (WARP_INVERSE_MAP | INTER_LINEAR) in a Python loop over the batch
    (forward only, the reference the layer reproduces);
with ``jit_compile`` off, on, or both (``--compare_jit``). Prints one JSON object.

  python -m experiments.benchmark_layers --iterations=50 --compare_jit
"""

from __future__ import annotations


from absl import app, flags

from experiments import common

flags.DEFINE_integer("batch_size", 64, "Patches per batch.")
flags.DEFINE_integer("size", 128, "Patch side in pixels.")
flags.DEFINE_integer("iterations", 30, "Timed iterations per measurement (the median is reported).")
flags.DEFINE_integer("warmup", 3, "Untimed iterations before each measurement (tracing, XLA).")
flags.DEFINE_integer("seed", 0, "Seed for patch positions and homographies.")
flags.DEFINE_bool("jit_compile", False, "Compile the tf.functions with XLA.")
flags.DEFINE_bool("compare_jit", False, "Measure both jit_compile=False and True (overrides --jit_compile).")
flags.DEFINE_string("json_out", None, "Also write the JSON result to this file.")

FLAGS = flags.FLAGS


def make_inputs(batch_size: int, size: int, seed: int):
    """Grayscale photograph patches ``[B, S, S, 1]`` (float32, 0..255) and ``H_bar`` ``[B, 8]``."""
    import cv2
    import numpy as np
    import skimage.data

    from stnh_tf import geometry

    rng = np.random.default_rng(seed)
    photos = [skimage.data.camera(), skimage.data.astronaut(), skimage.data.coffee(),
              skimage.data.chelsea(), skimage.data.rocket()]
    photos = [cv2.resize(p if p.ndim == 2 else cv2.cvtColor(p, cv2.COLOR_RGB2GRAY), (320, 240))
              for p in photos]
    patches, h_bars, h_pix = [], [], []
    rho = 32.0 * size / 128.0
    for i in range(batch_size):
        photo = photos[i % len(photos)]
        y0 = rng.integers(0, photo.shape[0] - size + 1)
        x0 = rng.integers(0, photo.shape[1] - size + 1)
        patches.append(photo[y0:y0 + size, x0:x0 + size])
        h = geometry.offsets_to_homography(rng.uniform(-rho, rho, size=(4, 2)), size)
        h_pix.append(h)
        h_bars.append(geometry.matrix_to_vector(geometry.normalize_homography(h, size, size)))
    images = np.stack(patches).astype(np.float32)[..., None]
    return images, np.stack(h_bars).astype(np.float32), np.stack(h_pix)


def run_benchmark(batch_size=64, size=128, iterations=30, warmup=3, seed=0, jit_modes=(False,)):
    """Runs every measurement and returns the result dict (see module docstring)."""
    import cv2
    import numpy as np
    import tensorflow as tf

    from stnh_tf.layers import SpatialTransformer

    images_np, h_np, h_pix = make_inputs(batch_size, size, seed)
    images, h_bar = tf.constant(images_np), tf.constant(h_np)
    weights = tf.constant(np.random.default_rng(seed + 1).normal(
        size=images_np.shape).astype(np.float32))
    layer = SpatialTransformer()

    result = {
        "benchmark": "stn_layers",
        "batch_size": batch_size, "size": size, "channels": 1,
        "iterations": iterations, "warmup": warmup, "seed": seed,
        "machine": common.machine_info(),
        "stn": {},
    }

    for jit in jit_modes:
        @tf.function(jit_compile=jit)
        def forward(img, h):
            return layer([img, h])

        @tf.function(jit_compile=jit)
        def forward_backward(img, h):
            with tf.GradientTape() as tape:
                tape.watch([img, h])
                loss = tf.reduce_sum(layer([img, h]) * weights)
            return tape.gradient(loss, [img, h])

        key = "jit" if jit else "no_jit"
        result["stn"][key] = {
            "forward_ms": common.median_ms(lambda: forward(images, h_bar).numpy(), iterations, warmup),
            "forward_backward_ms": common.median_ms(
                lambda: [g.numpy() for g in forward_backward(images, h_bar)], iterations, warmup),
        }
        # Sanity: the timed function computes the OpenCV warp (mean |diff| on this batch).
        out = forward(images, h_bar).numpy()
        ref = np.stack([cv2.warpPerspective(images_np[i, ..., 0], h_pix[i], (size, size),
                                            flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
                        for i in range(batch_size)])
        result["stn"][key]["mean_abs_diff_vs_cv2_all_pixels"] = float(np.abs(out[..., 0] - ref).mean())

    def cv2_loop():
        for i in range(batch_size):
            cv2.warpPerspective(images_np[i, ..., 0], h_pix[i], (size, size),
                                flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)

    result["cv2_loop_forward_ms"] = common.median_ms(cv2_loop, iterations, warmup)
    if "jit" in result["stn"] and "no_jit" in result["stn"]:
        nj, j = result["stn"]["no_jit"], result["stn"]["jit"]
        result["jit_speedup"] = {
            "forward": nj["forward_ms"] / j["forward_ms"],
            "forward_backward": nj["forward_backward_ms"] / j["forward_backward_ms"],
        }
    return result


def main(argv):
    del argv
    jit_modes = (False, True) if FLAGS.compare_jit else (FLAGS.jit_compile,)
    result = run_benchmark(FLAGS.batch_size, FLAGS.size, FLAGS.iterations, FLAGS.warmup,
                           FLAGS.seed, jit_modes)
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
