r"""Same answer on every machine: the default estimate on OpenCV's optimized and unoptimized code
paths, and its search from network estimates moved by a fraction of a pixel
(:func:`stnh_tf.search_stability.search_stability`).

  python -m experiments.benchmark_search_stability                  # the model card's 60 pairs
  python -m experiments.benchmark_search_stability --photometric
  python -m experiments.benchmark_search_stability --seed=7 --samples_per_image=30   # held out
  python -m experiments.benchmark_search_stability --model=stnh_tf/weights/paper_recipe --stages=1

Pairs: the bundled test photographs (``make_dataset --source=bundled --split=test``) with
``--seed`` and ``--samples_per_image`` (the model card's: 0 and 3). Prints one JSON object.
"""

from __future__ import annotations

import tempfile

from absl import app, flags

from experiments import common, flags_common

flags.DEFINE_string("model", None, "Model or hierarchy (default: the shipped weights).")
flags.DEFINE_integer("stages", None, "Use only the first N stages of the hierarchy.")
flags_common.define_seed("Seed of the bundled test pairs (the model card's: 0).")
flags.DEFINE_integer("samples_per_image", 3, "Pairs per bundled test photograph.")
flags.DEFINE_bool("photometric", False, "patch_b also changed in brightness, contrast and gamma.")
flags.DEFINE_list("perturbations", ["0.01", "0.1", "0.3"], "Start moves (px) of the search.")
flags_common.define_json_out()
FLAGS = flags.FLAGS
flags.adopt_module_key_flags(flags_common)  # --help lists them


def main(argv):
    del argv
    with common.user_errors("benchmark_search_stability"):
        common.check_flags_apart(("json_out",), (), models=("model",))
    import tensorflow as tf  # noqa: F401  (loaded first, so machine_info reports it)

    from stnh_tf.data import stage1
    from stnh_tf.inference import estimator as inference
    from stnh_tf.evaluation import benchmarks, search_stability
    from stnh_tf.data import tfrecords as data

    estimator = inference.HomographyEstimator.load(FLAGS.model)
    if FLAGS.stages:
        estimator = inference.HomographyEstimator(estimator.stages[:FLAGS.stages])
    with tempfile.TemporaryDirectory() as tmp:
        stage1.make_dataset("bundled", tmp, "test", seed=FLAGS.seed,
                            samples_per_image=FLAGS.samples_per_image, num_shards=1,
                            log=lambda *a, **k: None, photometric=FLAGS.photometric)
        arrays = data.load_arrays(tmp, "test")
    result = search_stability.search_stability(
        estimator, arrays["patch_a"], arrays["patch_b"], arrays["h_ba"],
        [float(p) for p in FLAGS.perturbations])
    result.update(model=FLAGS.model or "shipped default", stages=estimator.num_stages,
                  seed=FLAGS.seed, samples_per_image=FLAGS.samples_per_image,
                  photometric=FLAGS.photometric, machine=benchmarks.machine_info())
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
