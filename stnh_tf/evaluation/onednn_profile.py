"""Where a training step's time goes, primitive by primitive: oneDNN's own timing of each
convolution, pooling, matmul and reorder it runs (``ONEDNN_VERBOSE=1``), summed per step
(``experiments.benchmark_training --onednn_layers``; issue 77, item 5).

TensorFlow prints no per-layer time of its oneDNN kernels; oneDNN's verbose mode prints one line
per primitive executed, with its implementation (``brg_conv_fwd:avx512_core_amx``,
``jit_bf16:avx512_core_bf16``, ...), its propagation (``forward_training``,
``backward_data``, ``backward_weights``), the problem (shapes) and its wall time in ms. Those
lines are what this module reads; nothing is timed here by hand.
"""

from __future__ import annotations

import collections
import os
import subprocess
import sys

_CHILD = """
import sys
from stnh_tf.evaluation import benchmarks
policy, batch_size, steps, warmup, seed = sys.argv[1], *map(int, sys.argv[2:])
print("STEP_S", benchmarks.time_training("stn", policy, False, batch_size, steps, warmup, seed))
"""


def parse_verbose(text: str, runs: int, timed: int) -> list:
    """oneDNN verbose ``text`` (``v1`` lines without timestamps) of ``runs`` identical training
    steps, the last ``timed`` of them kept: one dict per primitive (kind, implementation,
    propagation, memory formats, problem), with ``calls_per_step`` and ``ms_per_step`` (over the
    kept steps), ``ms_per_call``; sorted by ``ms_per_step``, largest first. The lines carry no
    step, so the steps are told apart by counting: a primitive seen ``n`` times runs
    ``n // runs`` times a step (the layers of one shape) and its last ``n // runs * timed`` calls
    count; one seen fewer than ``runs`` times (set-up, first-call reorders) is left out, and
    calls beyond whole steps are taken for set-up.

    Raises:
      ValueError: ``timed`` not in ``1..runs``.

    >>> line = ("onednn_verbose,v1,primitive,exec,cpu,convolution,brg_conv_fwd:avx512_core_amx,"
    ...         "forward_training,src:bf16::blocked:acdb::f0,,alg:convolution_direct,mb64_ic2oc64,{}")
    >>> rows = parse_verbose("\\n".join(line.format(ms) for ms in (9.0, 2.0, 4.0)), 3, 2)
    >>> rows[0]["ms_per_step"], rows[0]["calls_per_step"], rows[0]["implementation"]
    (3.0, 1, 'brg_conv_fwd:avx512_core_amx')
    """
    if not 1 <= timed <= runs:
        raise ValueError(f"timed must be in 1..runs ({runs}); received {timed}.")
    calls = collections.defaultdict(list)
    for line in text.splitlines():
        fields = line.strip().split(",")
        if fields[:4] != ["onednn_verbose", "v1", "primitive", "exec"] or len(fields) < 10:
            continue
        try:
            ms = float(fields[-1])
        except ValueError:
            continue
        calls[(fields[5], fields[6], fields[7], fields[8], fields[-2])].append(ms)
    rows = []
    for (kind, implementation, propagation, formats, problem), times in calls.items():
        per_step = len(times) // runs
        if per_step == 0:
            continue
        kept = times[-per_step * timed:]
        rows.append({"kind": kind, "implementation": implementation,
                     "propagation": propagation, "formats": formats, "problem": problem,
                     "calls_per_step": per_step, "ms_per_step": sum(kept) / timed,
                     "ms_per_call": sum(kept) / len(kept)})
    return sorted(rows, key=lambda r: -r["ms_per_step"])


def profile_training_step(policy: str, batch_size: int = 64, steps: int = 4, warmup: int = 2,
                          seed: int = 0) -> dict:
    """oneDNN's time per primitive of a stage's training step (``benchmarks.time_training``'s
    ``"stn"`` model, ``policy`` a Keras dtype policy), in a child process with
    ``ONEDNN_VERBOSE=1`` (the variable must be set before oneDNN's first primitive): ``step_s``
    (the child's median step, verbose on), ``primitives`` (:func:`parse_verbose` of its last
    ``steps`` steps), ``ms_per_step`` (their sum: above ``step_s`` where TensorFlow runs two
    primitives at once, each then timed over the shared cores) and the sums per propagation.

    Raises:
      RuntimeError: the child failed (its last output lines in the message), or oneDNN timed
        no primitive in it (TensorFlow without oneDNN: ``TF_ENABLE_ONEDNN_OPTS=0``, or a build
        or CPU without it).
    """
    import stnh_tf

    env = dict(os.environ, ONEDNN_VERBOSE="1", ONEDNN_VERBOSE_TIMESTAMP="0")
    importable = os.path.dirname(os.path.dirname(os.path.abspath(stnh_tf.__file__)))
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [importable, env.get("PYTHONPATH", "")]))
    child = subprocess.run(
        [sys.executable, "-c", _CHILD, policy, str(batch_size), str(steps), str(warmup),
         str(seed)], capture_output=True, text=True, env=env)
    step = [line.split()[1] for line in child.stdout.splitlines() if line.startswith("STEP_S ")]
    if child.returncode != 0 or not step:
        tail = "\n".join((child.stdout + child.stderr).splitlines()[-5:])
        raise RuntimeError(f"the profiled training step failed (exit {child.returncode}): {tail}")
    rows = parse_verbose(child.stdout, warmup + steps, steps)
    if not rows:
        raise RuntimeError("oneDNN timed no primitive of the training step: TensorFlow ran "
                           "without oneDNN (TF_ENABLE_ONEDNN_OPTS=0, or a build or CPU "
                           "without it).")
    by_propagation = collections.defaultdict(float)
    for r in rows:
        by_propagation[r["propagation"]] += r["ms_per_step"]
    return {"policy": policy, "batch_size": batch_size, "steps": steps, "warmup": warmup,
            "step_s": float(step[0]), "ms_per_step": sum(r["ms_per_step"] for r in rows),
            "ms_per_step_by_propagation": dict(by_propagation), "primitives": rows}
