"""Data-parallel training on several processes (``--strategy=data_parallel``,
``stnh_tf.training.distribute``: keras.distribution on the JAX backend).

Fast tests check the pure logic: each process's share of a global batch (generated pairs,
TFRecords by file and by data), who writes, and the flags' checks. The slow tests start two
worker processes on 127.0.0.1 (free ports, CPU only, JAX backend, conftest's narrow network):
both finish, each line they log starts with its ``[worker k/2]``, the chief's run equals one
process's with the same global batch and data order, the second worker writes nothing, and when
worker 1 is killed mid-way the chief logs the line that says how to resume within the heartbeat
timeout, after which the restarted run ends with the uninterrupted run's weights. The watchdog's
rounds, the lost-worker line and the log prefix are checked fast, without processes.
"""

import json
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from conftest import NARROW_FILTERS
from stnh_tf.data import batches, bundled_photos, pair_datasets, stage1
from stnh_tf.data import tfrecords as data
from stnh_tf.modeling import runner
from stnh_tf.training import config as train_config
from stnh_tf.training import distribute, watchdog, worker_log
from stnh_tf.training import loop as training

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    """Four bundled photographs in a folder: 8 pairs at 2 a photograph, 2 batches of 4."""
    d = tmp_path_factory.mktemp("images")
    for k, (_, path) in enumerate(bundled_photos.bundled_image_files()[:4]):
        shutil.copy(path, d / f"{k}{os.path.splitext(path)[1]}")
    return str(d)


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    """Stage-1 TFRecords of 4 bundled photographs: ``two`` (2 train shards) and ``three``
    (3 train shards), 12 pairs each, and a test split."""
    out = {}
    for name, shards in (("two", 2), ("three", 3)):
        d = str(tmp_path_factory.mktemp(name))
        log = lambda *a, **k: None
        stage1.make_dataset("bundled", d, "train", seed=0, num_shards=shards, max_images=4,
                            log=log)
        stage1.make_dataset("bundled", d, "test", seed=1, num_shards=1, max_images=4, log=log)
        out[name] = d
    return out


# ------------------------------------------------------------------------------------------------
# Fast: the pure logic
# ------------------------------------------------------------------------------------------------
def test_share_rows_split_a_batch_into_equal_blocks():
    assert [distribute.share_rows(8, k, 2) for k in range(2)] == [slice(0, 4), slice(4, 8)]
    assert [distribute.share_rows(6, k, 3) for k in range(3)] == [slice(0, 2), slice(2, 4),
                                                                 slice(4, 6)]
    # A partial validation batch of 7 rows over 4 devices of 2 processes: 4 rows, 2 each.
    assert [distribute.share_rows(7, k, 2, multiple=4) for k in range(2)] == [slice(0, 2),
                                                                              slice(2, 4)]
    assert distribute.share_rows(3, 0, 2, multiple=4) == slice(0, 0)
    for bad in ((8, 2, 2), (8, -1, 2), (8, 0, 2, 3)):
        with pytest.raises(ValueError):
            distribute.share_rows(*bad)


def test_cluster_names_the_chief_the_only_writer():
    cfg = train_config.TrainConfig(image_dir="i", model_dir="m", strategy="data_parallel",
                                   num_processes=3, process_id=2,
                                   coordinator_address="10.0.0.1:1234", batch_size=6)
    cfg.validate()
    cluster = distribute.cluster_of(cfg)
    assert (cluster.share, cluster.multi, cluster.is_chief, cluster.data_parallel) == (
        (2, 3), True, False, True)
    assert distribute.cluster_of(train_config.TrainConfig(image_dir="i", model_dir="m")) == \
        distribute.Cluster(1, 0, False)
    assert [distribute.Cluster(3, k, True).is_chief for k in range(3)] == [True, False, False]
    assert distribute.callbacks(distribute.Cluster()) == []  # a single process adds nothing


def test_tfrecord_share_policy_is_by_file_when_the_shards_divide_else_by_data():
    assert [data.share_policy(n, 2) for n in (1, 2, 3, 4, 64)] == [
        "data", "file", "data", "file", "file"]
    assert data.share_policy(5, 1) == "none"


@pytest.mark.parametrize("option", [
    dict(num_processes=2),
    dict(num_processes=2, strategy="data_parallel"),
    dict(num_processes=2, strategy="data_parallel", coordinator_address="h:1", batch_size=5),
    dict(process_id=1),
    dict(coordinator_address="h:1"),
])
def test_distribution_flags_are_checked_together(option):
    cfg = train_config.TrainConfig(image_dir="i", model_dir="m", **option)
    with pytest.raises(ValueError) as e:
        cfg.validate()
    assert any(name in str(e.value) for name in ("strategy", "coordinator_address", "batch_size",
                                                 "process_id"))


def test_data_parallel_needs_the_jax_backend(tmp_path):
    cfg = train_config.TrainConfig(image_dir="i", model_dir=str(tmp_path / "run"),
                                   strategy="data_parallel")
    with pytest.raises(ValueError, match="KERAS_BACKEND=jax"):
        training.train(cfg)
    assert not (tmp_path / "run").exists()  # refused before model_dir is touched


@pytest.mark.parametrize("in_memory", [False, True])
def test_generated_shares_are_the_rows_of_the_single_stream(images, in_memory):
    """Each share generates its rows of every global batch alone; the two shares of step s are
    the single stream's batch s (fixed pairs and a fresh epoch; in memory as ArrayStream)."""
    def stream(share):
        kw = dict(samples_per_image=2, seed=3)
        if in_memory:
            pb = batches.PairBatches(images, 4, **kw)
            arrays = batches.materialize(pb)
            pb.set_share(*share)
            return pair_datasets.ArrayStream(arrays, pb)
        s = pair_datasets.PairStream(images, 4, fresh_pairs=True, **kw)
        s.batches.set_share(*share)
        return s

    whole, parts = stream((0, 1)), [stream((k, 2)) for k in range(2)]
    for step in (0, 1, 2, 5):  # 2 batches a data epoch: epochs 0, 1 and 2
        x, y, w = whole[step]
        got = [p[step] for p in parts]
        assert [g[0]["patch_a"].shape[0] for g in got] == [2, 2]
        for key in ("patch_a", "patch_b"):
            np.testing.assert_array_equal(np.concatenate([g[0][key] for g in got]), x[key])
        np.testing.assert_array_equal(np.concatenate([g[1]["h_bar"] for g in got]), y["h_bar"])
    with pytest.raises(ValueError):
        batches.PairBatches(images, 4, samples_per_image=2).set_share(0, 3)


def test_generated_share_reaches_the_generator_processes(images):
    whole = pair_datasets.PairStream(images, 4, samples_per_image=2)
    part = pair_datasets.PairStream(images, 4, samples_per_image=2, workers=1)
    part.batches.set_share(1, 2)
    try:
        np.testing.assert_array_equal(part[1][1]["h_bar"], whole[1][1]["h_bar"][2:])
    finally:
        part.close()


def _h_rows(ds, n):
    return [b[1]["h_bar"].numpy() for b in ds.take(n)]


@pytest.mark.parametrize("layout", ["two", "three"])
def test_tfrecord_shares(records, layout):
    """By data (3 shards, 2 processes): share k's batch s is rows [2k, 2k + 2) of the single
    stream's batch s, positioned at a resumed step too. By file (2 shards): share k reads shard
    k alone, each of its records once a pass, the two passes together the whole split."""
    d = records[layout]
    kw = dict(shuffle=False, seed=0, repeat=False)
    if layout == "three":
        whole = _h_rows(data.load_split(d, "train", 4, skip_batches=1, **kw), 2)
        parts = [_h_rows(data.load_split(d, "train", 4, skip_batches=1, share=(k, 2), **kw), 2)
                 for k in range(2)]
        for s in range(2):
            np.testing.assert_array_equal(np.concatenate([p[s] for p in parts]), whole[s])
        return
    stored = data.load_arrays(d, "train")["h_bar"]  # shard 0's 6 pairs (2 images), shard 1's
    assert len(stored) == 12
    for k in range(2):
        rows = np.concatenate(_h_rows(data.load_split(d, "train", 4, share=(k, 2),
                                                      drop_remainder=False, **kw), 99))
        assert sorted(map(tuple, rows)) == sorted(map(tuple, stored[6 * k:6 * (k + 1)]))


class Store:
    """A stand-in for the key-value store of JAX's distributed service (a dict), that can fail
    like an unreachable coordinator."""

    def __init__(self):
        self.values, self.down = {}, False

    def key_value_set(self, key, value, allow_overwrite=False):
        if self.down:
            raise RuntimeError("UNAVAILABLE: failed to connect to the coordination service")
        assert allow_overwrite or key not in self.values
        self.values[key] = value

    def key_value_try_get(self, key):
        if self.down:
            raise RuntimeError("UNAVAILABLE: failed to connect to the coordination service")
        if key not in self.values:
            raise RuntimeError(f"NOT_FOUND: Config key {key} not found")
        return self.values[key]


def _watchdogs(n, store, clock):
    return [watchdog.Watchdog(n, k, store, on_lost=None, timeout_s=20, every_s=1, clock=clock)
            for k in range(n)]


def test_watchdog_finds_the_process_whose_beats_stop():
    """Three processes beat each second of a common fake clock; process 2 stops at t = 5: the
    others, which read its last beat at t = 6, find it lost at the first round more than 20 s
    later (t = 27), not before; a process marked done is never lost; the store unreachable means
    the chief is lost (for a non-chief; the chief, which holds the store, decides nothing)."""
    now, store = [0.0], Store()
    dogs = _watchdogs(3, store, lambda: now[0])
    found = {}
    for t in range(40):
        now[0] = float(t)
        for k, dog in enumerate(dogs):
            if k == 2 and t > 5:
                continue  # killed
            lost = dog.check()
            if lost and k not in found:
                found[k] = (t, lost)
    assert found == {0: (27, [2]), 1: (27, [2])}
    assert store.values[watchdog._BEAT_KEY.format(0)] == "40"
    assert dogs[0].beaten_since(38.0) is False and dogs[1].beaten_since(38.0) is False
    dogs = _watchdogs(2, store, lambda: now[0])  # (process 1 beats each round: seen by 0)
    for t in (40.0, 41.0, 42.0):
        now[0] = t
        dogs[1].check()
        dogs[0].check()
    assert dogs[0].beaten_since(40.5) and not dogs[0].beaten_since(41.0)
    now[0] = 43.0  # process 1 beats, then is killed; process 0 fails at 43.2 and reads it at 43.5
    dogs[1].check()
    now[0] = 43.5
    dogs[0].check()
    assert not dogs[0].beaten_since(43.2)  # one change after 43.2: the beat came before it
    for t in (44.5, 45.5, 70.0):
        now[0] = t
        assert dogs[0].check() == ([1] if t == 70.0 else None)
    assert not dogs[0].beaten_since(43.2)

    now[0], store = 0.0, Store()  # a process done with its work (at exit) is no longer watched
    dogs = _watchdogs(2, store, lambda: now[0])
    dogs[1].check()
    dogs[1].finish()  # (its thread not started: returns at once)
    dogs[1].check()  # no beat after done
    assert store.values[watchdog._BEAT_KEY.format(1)] == "done"
    for t in range(60):
        now[0] = float(t)
        assert dogs[0].check() is None
    assert dogs[0].all_done.is_set() and not dogs[1].all_done.is_set()

    now[0], store = 0.0, Store()  # a failing process stops beating: the others find it lost
    dogs = _watchdogs(2, store, lambda: now[0])
    dogs[1].stop_beating()
    dogs[1].finish()  # (and is not marked done)
    verdicts = []
    for t in (0.0, 20.0, 21.0):
        now[0] = t
        verdicts.append(dogs[0].check())
    assert verdicts == [None, None, [1]]

    store.down = True
    assert (dogs[0].check(), _watchdogs(2, store, lambda: 0.0)[1].check()) == (None, [0])


def test_watchdog_thread_calls_on_lost_once_and_at_exit_waits_for_the_others():
    """The thread calls ``on_lost`` once, then ends; at exit (``finish``) a process waits while
    another works on, returns when it is done, or after it is found lost."""
    store, calls = Store(), []
    store.values[watchdog._BEAT_KEY.format(1)] = "7"  # never changes: lost after 0.2 s
    dog = watchdog.Watchdog(2, 0, store, on_lost=calls.append, timeout_s=0.2, every_s=0.05)
    dog.start()
    dog.finish(wait_s=5)
    assert calls == [[1]] and dog.lost == [1] and dog.verdict.is_set() and not dog.is_alive()
    assert 0 < dog.max_gap_s < 1

    store = Store()
    dogs = [watchdog.Watchdog(2, k, store, on_lost=calls.append, timeout_s=2, every_s=0.02)
            for k in range(2)]
    for d in dogs:
        d.start()
    first = threading.Thread(target=dogs[0].finish)
    first.start()
    time.sleep(0.5)
    assert first.is_alive()  # process 1 still at work
    dogs[1].finish()
    first.join(5)
    assert not first.is_alive() and not any(d.is_alive() for d in dogs)
    assert calls == [[1]] and all(d.all_done.is_set() for d in dogs)


def test_lost_line_names_the_lost_worker_and_the_command_that_resumes(tmp_path):
    """The line of the chief names the lost worker, the step of its last checkpoint and the
    command of each worker (``--process_id`` made K, the backend's variables first, shell-quoted
    so that it can be pasted); without ``--process_id`` on the command line, this worker's own
    command."""
    run = tmp_path / "run"
    (run / "checkpoint").mkdir(parents=True)
    (run / "checkpoint" / "state.json").write_text(json.dumps({"step": 4}))
    argv = ["python", "-m", "experiments.train_stage", "--image_dir=my photos",
            "--process_id=0", "--model_dir", str(run)]
    line = watchdog.lost_line(2, 0, [1], str(run), 20, argv, {"KERAS_BACKEND": "jax",
                                                              "HOME": "/root"})
    assert line == (
        f"lost worker 1 of 2: no heartbeat for 20 s (killed, crashed or cut off); this worker "
        f"stops too (exit status 75). To resume the run from its last checkpoint (step 4 in "
        f"{run}), start the 2 workers again, on each worker K = 0..1: KERAS_BACKEND=jax python -m "
        f"experiments.train_stage '--image_dir=my photos' --process_id=K --model_dir {run}")
    words = shlex.split(line.split("K = 0..1: ")[1].replace("=K", "=1"))
    assert words == ["KERAS_BACKEND=jax", *argv[:4], "--process_id=1", *argv[5:]]
    line = watchdog.lost_line(3, 2, [0, 1], "unused", 20,
                              ["python", "-m", "experiments.train_stage", "--process_id", "2"], {})
    assert line.startswith("lost worker 0 (the chief), worker 1 of 3: ")
    assert "from its last checkpoint, start the 3 workers again, on each worker K = 0..2: python "\
           "-m experiments.train_stage --process_id K" in line
    assert watchdog.resume_command(2, ["python", "w.py", "{}"], {}) == \
        "each with its own command (this worker's: python w.py '{}')"


def test_log_lines_carry_the_worker_prefix(monkeypatch):
    """After :func:`worker_log.prefix_logs`, every logger's records (absl's and any other) start
    with ``[worker k/N]``; one process gets no prefix; another prefix later is refused."""
    import logging

    factory = logging.getLogRecordFactory()
    monkeypatch.setattr(worker_log, "_PREFIX", None)
    records = []

    class Keep(logging.Handler):
        def emit(self, record):
            records.append(self.format(record))

    handler = Keep()
    logging.getLogger("stnh_test").addHandler(handler)
    try:
        worker_log.prefix_logs(1, 0)
        logging.getLogger("stnh_test").warning("one %s", "process")
        worker_log.prefix_logs(2, 1)
        worker_log.prefix_logs(2, 1)  # once: no double prefix
        logging.getLogger("stnh_test").warning("step %d", 3)
        with pytest.raises(RuntimeError, match="worker 1/2"):
            worker_log.prefix_logs(2, 0)
    finally:
        logging.setLogRecordFactory(factory)
        logging.getLogger("stnh_test").removeHandler(handler)
    assert records == ["one process", "[worker 1/2] step 3"]


# ------------------------------------------------------------------------------------------------
# Slow: two worker processes
# ------------------------------------------------------------------------------------------------
WORKER = r"""
import json, os, sys, time
spec = json.loads(sys.argv[1])
from stnh_tf.modeling import models
models.CONV_FILTERS = tuple(spec.pop("filters"))  # conftest's narrow network
import keras
from absl import logging
from stnh_tf.training import config as train_config
from stnh_tf.training import loop, streams
logging.set_verbosity(logging.INFO)  # the binaries' printer (absl, as under app.run)
sleep = spec.pop("sleep_per_step", 0.0)
shares = spec.pop("reference_shares", 0)
if spec.pop("mask_odd", False):  # pairs of odd index without H_bar: the masked L2 term
    import numpy as np
    from stnh_tf.data import batches
    sample = batches.PairBatches.sample
    def masked(self, s, epoch=0):
        out = sample(self, s, epoch)
        if int(out["index"]) % 2:
            out["h_mask"] = np.float32(0.0)
        return out
    batches.PairBatches.sample = masked

class Slow(keras.callbacks.Callback):  # keeps a run going long enough to be killed mid-way
    def on_train_batch_end(self, batch, logs=None):
        time.sleep(sleep)

stream_fn = None
if shares:  # one process reading the concatenated shares of `shares` processes
    import tensorflow as tf
    def stream_fn(cfg, split, start_step):
        parts = [streams.training_stream(cfg, split, start_step, share=(k, shares))
                 for k in range(shares)]
        cat = lambda *b: tf.nest.map_structure(lambda *t: tf.concat(t, 0), *b)
        return tf.data.Dataset.zip(tuple(parts)).map(cat)
res = loop.train(train_config.TrainConfig(**spec), printer=logging.info, stream_fn=stream_fn,
                 extra_callbacks=[Slow()] if sleep else ())
print("RESULT " + json.dumps({"final_step": res["final_step"], "history": res["history"]}),
      flush=True)
"""
ENV = dict(os.environ, KERAS_BACKEND="jax", JAX_PLATFORMS="cpu", CUDA_VISIBLE_DEVICES="",
           PYTHONPATH=ROOT)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _command(spec, log_path):
    """The command line of a worker of ``spec`` (its script written beside ``log_path``)."""
    script = os.path.join(os.path.dirname(log_path), "worker.py")
    if not os.path.exists(script):
        with open(script, "w") as f:
            f.write(WORKER)
    return [sys.executable, script, json.dumps({"filters": list(NARROW_FILTERS), **spec})]


def _start(spec, log_path, cwd):
    log = open(log_path, "w")
    return subprocess.Popen(_command(spec, log_path), cwd=cwd, env=ENV,
                            stdout=log, stderr=subprocess.STDOUT, text=True)


def _finish(procs, logs, timeout=400):
    """Wait for every process; their results (the RESULT line), or fail with their logs."""
    deadline = time.monotonic() + timeout
    try:
        for p in procs:
            p.wait(timeout=max(deadline - time.monotonic(), 1))
    except subprocess.TimeoutExpired:
        for p in procs:
            p.kill()
        pytest.fail("workers timed out: " + "\n".join(open(g).read()[-2000:] for g in logs))
    out = []
    for p, g in zip(procs, logs):
        text = open(g).read()
        assert p.returncode == 0, text[-4000:]
        out.append(json.loads([ln for ln in text.splitlines() if ln.startswith("RESULT ")][-1][7:]))
    return out


def _two_workers(tmp, name, base, **extra):
    """Start process 0 (model_dir ``tmp/name``) and process 1 (its own model_dir
    ``tmp/name-w1`` and working folder ``tmp/name-cwd1``, which it must leave untouched)."""
    address = f"127.0.0.1:{_free_port()}"
    (tmp / f"{name}-cwd1").mkdir(exist_ok=True)
    procs, logs = [], []
    for k in range(2):
        spec = dict(base, strategy="data_parallel", num_processes=2, process_id=k,
                    coordinator_address=address,
                    model_dir=str(tmp / (name if k == 0 else f"{name}-w1")), **extra)
        logs.append(str(tmp / f"{name}-{k}-{len(list(tmp.glob(f'{name}-{k}-*.log')))}.log"))
        procs.append(_start(spec, logs[-1], str(tmp / f"{name}-cwd1") if k else ROOT))
    return procs, logs


def _one(tmp, name, base, **extra):
    log = str(tmp / f"{name}.log")
    return _finish([_start(dict(base, model_dir=str(tmp / name), **extra), log, ROOT)], [log])


def _weights(model_dir):
    return [np.asarray(w) for w in runner.load_model(str(model_dir)).get_weights()]


def _distance(u, v):
    assert len(u) == len(v)
    return max(float(np.abs(a - b).max()) for a, b in zip(u, v))


@pytest.fixture(scope="module")
def generated_runs(images, tmp_path_factory):
    """The same run (pairs generated from ``images``, half of them without H_bar: ``h_mask`` 0
    for odd indices; validation every checkpoint, dropout 0.5) on one process and on two; the
    the results and folders of both."""
    tmp = tmp_path_factory.mktemp("generated")
    base = dict(image_dir=images, val_image_dir=images, samples_per_image=2, train_steps=8,
                warmup_steps=1, batch_size=4, checkpoint_every=2, val_samples=6,
                learning_rate=0.01, log_every=1, seed=5, mask_odd=True)
    procs, logs = _two_workers(tmp, "two", base)
    two = _finish(procs, logs)
    one = _one(tmp, "one", base)
    return {"tmp": tmp, "base": base, "one": one[0], "two": two, "two_logs": logs}


@pytest.mark.slow
def test_two_workers_equal_one_process_and_only_the_chief_writes(generated_runs):
    """Two processes of 2 rows each train the weights one process trains on the global batch of
    4 in the same order (with dropout, validation and the masked L2 term: every loss is reduced
    over the global batch). Measured on the 2-core AMD EPYC (weights of magnitude up to 1.14):
    the weights 3e-8 to 6e-8 apart in four runs (float32 sums in another order), the losses within
    5e-7 relative, the validation MACE within 1.6e-5 relative (1561.776 against 1561.801 px in a
    run without the mask: estimates near a degenerate homography amplify the difference); hence
    the bounds 1e-5 on the weights and the losses, 1e-4 on the MACE. Process 1 wrote nothing:
    neither in its own model_dir nor in its working folder. Every line the workers log (absl's,
    as the binaries' printer) starts with its ``[worker k/2]``, the one process's with none."""
    r = generated_runs
    tmp = r["tmp"]
    for k, log in enumerate(r["two_logs"]):
        lines = [ln for ln in open(log).read().splitlines() if ln.startswith("INFO:absl:")]
        assert len([ln for ln in lines if " step 8/8 " in ln]) == 1, lines
        assert all(ln.startswith(f"INFO:absl:[worker {k}/2] ") for ln in lines), lines
    assert "[worker" not in open(tmp / "one.log").read()
    assert [w["final_step"] for w in r["two"]] == [8, 8]
    assert r["two"][0]["history"] == r["two"][1]["history"]  # both report the global step
    for key, rtol in (("loss", 1e-5), ("h_bar_loss", 1e-5), ("patch_a_warp_loss", 1e-5),
                      ("val_loss", 1e-5), ("val_h_bar_mace", 1e-4)):
        np.testing.assert_allclose(r["two"][0]["history"][key], r["one"]["history"][key],
                                   rtol=rtol, err_msg=key)
    one, two = _weights(tmp / "one"), _weights(tmp / "two")
    assert _distance(two, one) <= 1e-5
    assert sorted(os.listdir(tmp / "two")) == ["checkpoint", "config.json", "logs", "model.keras",
                                               "result.json"]
    saved = train_config.TrainConfig.from_json(json.load(open(tmp / "two" / "config.json")))
    assert (saved.num_processes, saved.process_id) == (2, 0)
    assert not (tmp / "two-w1").exists()
    assert os.listdir(tmp / "two-cwd1") == []


@pytest.mark.slow
def test_two_workers_resume_after_a_kill(generated_runs):
    """Kill process 1 after the chief's first checkpoint: the chief logs one line (prefixed)
    naming the lost worker, the step of its last checkpoint and its own command, and ends with
    exit status 75 within the heartbeat timeout (not before it: the watchdog's verdict; not the
    JAX service's abort, 55-100 s later, nor a traceback). The same two commands restarted resume
    from that step and finish with the uninterrupted two-process run's weights."""
    r = generated_runs
    tmp = r["tmp"]
    procs, logs = _two_workers(tmp, "killed", r["base"], sleep_per_step=1.0)
    state = tmp / "killed" / "checkpoint" / "state.json"
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and all(p.poll() is None for p in procs):
        if state.exists() and json.load(open(state))["step"] >= 2:
            break
        time.sleep(0.2)
    assert all(p.poll() is None for p in procs), [open(g).read()[-2000:] for g in logs]
    killed = time.monotonic()
    procs[1].send_signal(signal.SIGKILL)
    try:
        procs[0].wait(timeout=watchdog.HEARTBEAT_TIMEOUT_S + 60)
    except subprocess.TimeoutExpired:
        procs[0].kill()
    waited = time.monotonic() - killed
    procs[1].wait()
    chief = open(logs[0]).read()
    step = json.load(open(state))["step"]
    assert procs[0].returncode == watchdog.LOST_EXIT_STATUS, chief[-3000:]
    assert 2 <= step < 8 and not (tmp / "killed" / "model.keras").exists(), step
    lost = [ln for ln in chief.splitlines() if "lost worker" in ln]
    assert len(lost) == 1 and lost[0].startswith("ERROR:absl:[worker 0/2] lost worker 1 of 2: "), \
        lost
    command = ["KERAS_BACKEND=jax", "JAX_PLATFORMS=cpu", *procs[0].args]  # as ENV, _start
    assert lost[0].endswith(f"from its last checkpoint (step {step} in {tmp / 'killed'}), start "
                            f"the 2 workers again, each with its own command (this worker's: "
                            f"{shlex.join(command)})"), lost[0]
    assert "Traceback" not in chief and "Terminating process" not in chief, chief[-3000:]
    timeout = watchdog.HEARTBEAT_TIMEOUT_S
    assert timeout - 2 * watchdog.HEARTBEAT_EVERY_S <= waited <= timeout + 10, waited
    done = _finish(*_two_workers(tmp, "killed", r["base"]))
    assert [d["final_step"] for d in done] == [8, 8]
    assert any(f"resuming {tmp / 'killed'} from step {step}" in open(g).read() for g in
               tmp.glob("killed-0-*.log"))
    np.testing.assert_array_equal(np.concatenate([w.ravel() for w in _weights(tmp / "killed")]),
                                  np.concatenate([w.ravel() for w in _weights(tmp / "two")]))
    assert not (tmp / "killed-w1").exists()


@pytest.mark.slow
def test_two_workers_on_tfrecords_read_a_shard_each(records, tmp_path):
    """TFRecords of 2 shards on 2 processes: each reads its own shard (by file), 2 rows a step;
    the run equals one process reading the two shares concatenated (the global batch)."""
    base = dict(data_dir=records["two"], train_steps=4, warmup_steps=1, batch_size=4,
                checkpoint_every=2, val_samples=6, learning_rate=0.01, dropout=0.0)
    two = _finish(*_two_workers(tmp_path, "two", base))
    one = _one(tmp_path, "one", base, reference_shares=2)
    assert [w["final_step"] for w in two] == [4, 4]
    np.testing.assert_allclose(two[0]["history"]["loss"], one[0]["history"]["loss"], rtol=1e-5)
    assert _distance(_weights(tmp_path / "two"), _weights(tmp_path / "one")) <= 1e-5
    assert not (tmp_path / "two-w1").exists()
