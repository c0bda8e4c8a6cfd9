r"""Data-parallel training on 1 and on 2 local worker processes, same global batch: the step time
of each and the all-reduce of the gradients (``--strategy=data_parallel``, JAX backend, CPU); or
(``--measure=lost_worker``) how a run of two ends when one of its workers is killed.

  python -m experiments.benchmark_workers --batch_size=64 --steps=10 --json_out=/tmp/workers.json
  python -m experiments.benchmark_workers --measure=lost_worker --repeats=2 \
      --json_out=docs/scale/lost_worker.json

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
all-reduce is then the measured cost of the second worker per step. ``beat_max_gap_s``: on each of
the two processes, the longest time between two rounds of its heartbeat thread
(:class:`stnh_tf.training.watchdog.Watchdog`), compilation included: how late a beat can come.

``--measure=lost_worker``: two ``experiments.train_stage`` processes (the paper's network, the
bundled photographs, batch 4, a checkpoint every 2 steps, the same command but
``--process_id``); after a checkpoint, worker 1 is killed (SIGKILL) and the time from the kill
to the chief's lost-worker line (:func:`stnh_tf.training.watchdog.lost_line`) is recorded with
the chief's exit status; then the two commands that line gives are run as printed (``K``
replaced), which must resume from the checkpoint it names, and the next of ``--repeats`` kills
follows. Prints one JSON object.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import socket
import subprocess
import sys
import tempfile
import time

from absl import app, flags

from experiments import common, flags_common

flags.DEFINE_integer("batch_size", 64, "Global batch (split over the processes).",
                     lower_bound=1)
flags.DEFINE_integer("steps", 10, "Timed steps per configuration (median reported).",
                     lower_bound=1)
flags.DEFINE_integer("warmup", 2, "Untimed steps first (compilation; at least one: a step's "
                     "time is between two batch ends).", lower_bound=1)
flags.DEFINE_integer("allreduce_runs", 20, "Timed all-reduces.", lower_bound=1)
flags.DEFINE_bool("narrow", False, "The 1/16-width network of the tests (a quick check).")
flags.DEFINE_enum("measure", "steps", ["steps", "lost_worker"], "steps: the step times of 1 and "
                  "2 processes; lost_worker: kill worker 1 of a two-worker train_stage run, time "
                  "the chief's line and resume with its command, --repeats times.")
flags.DEFINE_integer("repeats", 2, "lost_worker: how many kills (each then resumed).",
                     lower_bound=1)
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
    from stnh_tf.training import distribute, loop, model_kinds, watchdog

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
        out["beat_max_gap_s"] = watchdog.watch(n, k).max_gap_s  # (started by join)
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


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LOST_RUN_FLAGS = ("--batch_size=4", "--train_steps=100000",
                  "--warmup_steps=1", "--checkpoint_every=2", "--log_every=1", "--val_samples=0")
"""The training flags of the ``lost_worker`` runs besides the distribution, ``--image_dir`` (the
bundled photographs, copied) and ``--model_dir``."""


def _wait_for(condition, procs, timeout_s: float, what: str):
    """``condition()``'s first true value, polled every 50 ms; SystemExit (with the logs' ends)
    if a process of ``procs`` (``(Popen, log path)``) ends first or ``timeout_s`` passes."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        if any(p.poll() is not None for p, _ in procs):
            break
        time.sleep(0.05)
    for p, _ in procs:
        if p.poll() is None:
            p.kill()
    raise SystemExit(f"benchmark_workers: no {what}:\n"
                     + "\n".join(open(log).read()[-3000:] for _, log in procs))


def _start_command(command: str, log: str):
    """Start ``command`` (``NAME=value ... program args``, shell-quoted) in the repository, its
    output to ``log``."""
    words = shlex.split(command)
    env = dict(os.environ)
    while words and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=.*", words[0]):
        name, value = words.pop(0).split("=", 1)
        env[name] = value
    return subprocess.Popen(words, cwd=ROOT, env=env, stdout=open(log, "w"),
                            stderr=subprocess.STDOUT)


def lost_worker(repeats: int) -> dict:
    """Kill worker 1 of a two-worker ``train_stage`` run ``repeats`` times (see the module's
    docstring); each kill's checkpoint step, the seconds from the kill to the chief's line and to
    its exit, its exit status, whether its log shows a traceback or JAX's abort, the line, and
    the step the next start (the line's commands) resumed from."""
    import shutil

    from stnh_tf.data import bundled_photos
    from stnh_tf.training import checkpoints, run_dir, watchdog

    address = f"127.0.0.1:{_free_port()}"
    with tempfile.TemporaryDirectory(prefix="lost_worker_") as tmp:
        images = os.path.join(tmp, "images")
        os.makedirs(images)
        for k, (_, path) in enumerate(bundled_photos.bundled_image_files()):
            shutil.copy(path, os.path.join(images, f"{k}{os.path.splitext(path)[1]}"))
        model_dir = os.path.join(tmp, "run")
        state_dir = os.path.join(model_dir, run_dir.CHECKPOINT_DIR)
        commands = [shlex.join(["KERAS_BACKEND=jax", "JAX_PLATFORMS=cpu", sys.executable, "-m",
                                "experiments.train_stage", "--strategy=data_parallel",
                                "--num_processes=2", f"--process_id={k}",
                                f"--coordinator_address={address}", f"--image_dir={images}",
                                f"--model_dir={model_dir}", *LOST_RUN_FLAGS]) for k in range(2)]

        def step():
            state = checkpoints.read_checkpoint_state(state_dir)
            return state["step"] if state else 0

        kills = []
        for r in range(repeats):
            logs = [os.path.join(tmp, f"worker{k}-{r}.log") for k in range(2)]
            procs = list(zip([_start_command(c, g) for c, g in zip(commands, logs)], logs))
            start = step()
            if r:
                said = _wait_for(lambda: re.search(rf"resuming {re.escape(model_dir)} from step "
                                                   r"(\d+)", open(logs[0]).read()),
                                 procs, 900, "resuming line")
                kills[-1]["next_start_resumed_from"] = int(said.group(1))
            at = _wait_for(lambda: step() > start and step(), procs, 900, "new checkpoint")
            killed = time.monotonic()
            procs[1][0].kill()
            line = _wait_for(lambda: re.search(r"\[worker 0/2\] (lost worker .*)",
                                               open(logs[0]).read()),
                             procs[:1], 200, "lost-worker line")
            line_s = time.monotonic() - killed
            status = procs[0][0].wait(timeout=60)
            text = open(logs[0]).read()
            kills.append({"checkpoint_step": at, "line_after_s": round(line_s, 2),
                          "chief_exit_after_s": round(time.monotonic() - killed, 2),
                          "chief_exit_status": status, "traceback": "Traceback" in text,
                          "jax_abort": "Terminating process" in text, "line": line.group(1)})
            template = line.group(1).split("on each worker K = 0..1: ", 1)[1]
            commands = [shlex.join([f"--process_id={k}" if w == "--process_id=K" else w
                                    for w in shlex.split(template)]) for k in range(2)]
        return {"heartbeat_timeout_s": watchdog.HEARTBEAT_TIMEOUT_S,
                "heartbeat_every_s": watchdog.HEARTBEAT_EVERY_S,
                "run_flags": list(LOST_RUN_FLAGS), "kills": kills}


def main(argv):
    del argv
    if FLAGS.role == "worker":
        print("WORKER " + json.dumps(worker(json.loads(FLAGS.spec))), flush=True)
        return
    from stnh_tf.evaluation import benchmarks

    if FLAGS.measure == "lost_worker":
        common.emit_json({"measure": "lost_worker", **lost_worker(FLAGS.repeats),
                          "machine": benchmarks.machine_info()}, FLAGS.json_out)
        return

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
