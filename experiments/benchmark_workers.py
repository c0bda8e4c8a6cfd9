r"""Data-parallel training on 1 and on 2 local worker processes, same global batch: the step time
of each and the all-reduce of the gradients (``--strategy=data_parallel``, JAX backend, CPU).

  python -m experiments.benchmark_workers --batch_size=64 --steps=10 --json_out=/tmp/workers.json

Times, on fixed in-memory batches of bundled pairs (input reading is not timed), with this
project's model and recipe (the paper's network, losses, SGD), in float32:

* ``one``: one process, ``--strategy=default``, the global batch of ``--batch_size``;
* ``two``: two processes on 127.0.0.1 under ``keras.distribution.DataParallel`` (what
  ``stnh_tf.training.distribute`` runs), ``--batch_size / 2`` rows each;

``step_s`` is the median wall time between consecutive batch ends (each waits for its loss) over
``--steps`` steps after ``--warmup``. ``allreduce_s``: on the two processes, the median time of an
all-reduce (a jitted sum over the process axis, gloo) of as many float32 values as the model has
trainable weights: what one step exchanges, the same size every step; ``allreduce_share`` is its
part of the two-process step. ``speedup`` = one's step / two's step; ``extra_s_per_step`` = two's
step - one's (the all-reduce, the processes' lock-step and, where they share cores, their
contention). On a machine with fewer
cores than the processes need, the two processes share the cores: no speed-up can show; the
all-reduce is then the measured cost of the second worker per step. Prints one JSON object.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
import time

from absl import app, flags

from experiments import common, flags_common

flags.DEFINE_integer("batch_size", 64, "Global batch (split over the processes).")
flags.DEFINE_integer("steps", 10, "Timed steps per configuration (median reported).")
flags.DEFINE_integer("warmup", 2, "Untimed steps first (compilation).")
flags.DEFINE_integer("allreduce_runs", 20, "Timed all-reduces.")
flags.DEFINE_bool("narrow", False, "The 1/16-width network of the tests (a quick check).")
flags.DEFINE_enum("role", "parent", ["parent", "worker"], "Internal: parent or worker process.")
flags.DEFINE_string("spec", "", "Internal: a worker's JSON spec.")
flags_common.define_json_out()
FLAGS = flags.FLAGS
flags.adopt_module_key_flags(flags_common)  # --help lists them

NARROW_FILTERS = (4, 4, 4, 4, 8, 8, 8, 8)


def _median(values):
    values = sorted(values)
    n = len(values)
    return (values[n // 2] + values[(n - 1) // 2]) / 2 if n else None


def worker(spec: dict) -> dict:
    """One process of a measurement (``spec``: ``num_processes``, ``process_id``, ``address``,
    ``batch_size``, ``steps``, ``warmup``, ``allreduce_runs``, ``narrow``): its median step time,
    and with two processes the all-reduce time."""
    import numpy as np

    from stnh_tf.data import batches
    from stnh_tf.modeling import models
    from stnh_tf.training import config as train_config
    from stnh_tf.training import distribute, loop, model_kinds

    n, k = spec["num_processes"], spec["process_id"]
    multi = dict(strategy="data_parallel", num_processes=n, process_id=k,
                 coordinator_address=spec["address"]) if n > 1 else {}
    cfg = train_config.TrainConfig(image_dir="bundled", model_dir="unused",
                                   batch_size=spec["batch_size"], learning_rate=1e-3,
                                   warmup_steps=0, train_steps=1000, checkpoint_every=1000,
                                   **multi)
    cluster = distribute.join(cfg)  # before any JAX computation
    import jax
    import keras

    distribute.activate(cluster, cfg.batch_size)
    if spec["narrow"]:
        models.CONV_FILTERS = NARROW_FILTERS
    keras.utils.set_random_seed(0)
    model = loop.compile_model(model_kinds.build_model(cfg), cfg)
    pairs = batches.PairBatches("bundled", cfg.batch_size, samples_per_image=4, seed=0)
    pairs.set_share(*cluster.share)
    batch = batches.model_batch(pairs.stacked_batch(0))

    class Fixed(keras.utils.PyDataset):
        num_batches = None

        def __getitem__(self, index):
            return batch

    ends = []

    class Timer(keras.callbacks.Callback):
        def on_train_batch_end(self, index, logs=None):
            float((logs or {})["loss"])  # waits for the step
            ends.append(time.perf_counter())

    model.fit(Fixed(), epochs=1, steps_per_epoch=spec["warmup"] + spec["steps"],
              callbacks=[Timer()], verbose=0)
    steps = [b - a for a, b in zip(ends[spec["warmup"] - 1:], ends[spec["warmup"]:])]
    out = {"process_id": k, "step_s": _median(steps), "rows": int(batch[0]["patch_a"].shape[0]),
           "trainable_weights": int(sum(np.prod(v.shape) for v in model.trainable_variables))}
    if n > 1:
        from jax.sharding import Mesh, NamedSharding, PartitionSpec

        mesh = Mesh(np.array(jax.devices()), ("p",))
        local = np.ones((jax.local_device_count(), out["trainable_weights"]), np.float32)
        x = jax.make_array_from_process_local_data(NamedSharding(mesh, PartitionSpec("p")),
                                                   local)
        total = jax.jit(lambda a: a.sum(0), out_shardings=NamedSharding(mesh, PartitionSpec()))
        total(x).block_until_ready()
        runs = []
        for _ in range(spec["allreduce_runs"]):
            t = time.perf_counter()
            total(x).block_until_ready()
            runs.append(time.perf_counter() - t)
        out["allreduce_s"] = _median(runs)
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run(num_processes: int) -> list:
    """Start ``num_processes`` workers (JAX backend, CPU) and return their results."""
    address = f"127.0.0.1:{_free_port()}"
    env = dict(os.environ, KERAS_BACKEND="jax", JAX_PLATFORMS="cpu")
    procs, logs = [], []
    for k in range(num_processes):
        spec = dict(num_processes=num_processes, process_id=k, address=address,
                    batch_size=FLAGS.batch_size, steps=FLAGS.steps, warmup=FLAGS.warmup,
                    allreduce_runs=FLAGS.allreduce_runs, narrow=FLAGS.narrow)
        logs.append(tempfile.TemporaryFile("w+"))  # files, not pipes: no worker blocks on one
        procs.append(subprocess.Popen(
            [sys.executable, "-m", "experiments.benchmark_workers", "--role=worker",
             f"--spec={json.dumps(spec)}"], env=env, stdout=logs[-1],
            stderr=subprocess.STDOUT, text=True))
    out = []
    for p, log in zip(procs, logs):
        p.wait()
        log.seek(0)
        text = log.read()
        lines = [ln for ln in text.splitlines() if ln.startswith("WORKER ")]
        if p.returncode or not lines:
            for q in procs:
                q.kill()
            raise SystemExit(f"benchmark_workers: a worker failed (exit {p.returncode}):\n"
                             + text[-3000:])
        out.append(json.loads(lines[-1][len("WORKER "):]))
    return out


def main(argv):
    del argv
    if FLAGS.role == "worker":
        print("WORKER " + json.dumps(worker(json.loads(FLAGS.spec))), flush=True)
        return
    from stnh_tf.evaluation import benchmarks

    if FLAGS.batch_size % 2:
        raise SystemExit("benchmark_workers: --batch_size must be even (two processes).")
    info = benchmarks.machine_info()
    one = _run(1)
    two = _run(2)
    step_two = max(w["step_s"] for w in two)  # the processes step together
    allreduce = max(w["allreduce_s"] for w in two)
    result = {"batch_size": FLAGS.batch_size, "narrow": FLAGS.narrow,
              "trainable_weights": one[0]["trainable_weights"],
              "one": one, "two": two,
              "step_s_one": one[0]["step_s"], "step_s_two": step_two,
              "speedup": one[0]["step_s"] / step_two,
              "extra_s_per_step": step_two - one[0]["step_s"], "allreduce_s": allreduce,
              "allreduce_share": allreduce / step_two, "machine": info}
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
