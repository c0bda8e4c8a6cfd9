"""Where each model of a reproduction was trained: ``results.json``'s (and ``table1.json``'s)
``model_provenance`` and ``assembled``, read from each run folder's own records, and the one line
of ``tables.md`` that says whether the run was assembled. The standard library only.

A run folder records what produced it in the ``result.json`` that training writes when the run
finishes (:func:`stnh_tf.training.loop.train`): the final step, the wall time of the session
that finished it, and since issue 78 ``machine`` (:func:`stnh_tf.provenance.machine_info` of that
process: the code's commit, the CPU and its cores, any accelerator, the Keras backend). What a
folder lacks (a run finished before that, a folder without ``result.json``) is
:data:`~stnh_tf.paper.results_json.NOT_RECORDED`, never guessed.

    >>> machine_summary({"cpu": "Xeon", "cpu_count": 2, "gpus": [], "jax_devices": ["cpu"]})
    {'cpu': 'Xeon', 'cores': 2, 'accelerators': []}
"""

from __future__ import annotations

import json
import os

from stnh_tf.paper.results_json import NOT_RECORDED

RESULT_FILE = "result.json"  # (stnh_tf.training.run_dir.RESULT_FILE, which imports NumPy)


def machine_summary(info: dict) -> dict:
    """``{"cpu", "cores", "accelerators"}`` of a :func:`stnh_tf.provenance.machine_info` object:
    its CPU model and core count (:data:`NOT_RECORDED` where absent) and its accelerators (the
    TensorFlow GPUs and the JAX devices other than the CPU, sorted; empty on a CPU machine)."""
    accelerators = {*info.get("gpus", []),
                    *(d for d in info.get("jax_devices", []) if str(d).lower() != "cpu")}
    return {"cpu": info.get("cpu") or NOT_RECORDED, "cores": info.get("cpu_count") or NOT_RECORDED,
            "accelerators": sorted(accelerators)}


def run_provenance(run: str, reused: bool = False) -> dict:
    """What the run folder ``run`` records of its training.

    Returns:
        ``{"run", "steps", "wall_s", "commit", "machine", "backend", "reused"}``: ``steps`` the
        final step and ``wall_s`` the seconds of the session that finished the run (a run resumed
        from a checkpoint: its last session only), from its ``result.json``; ``commit`` (with
        ``+dirty`` where the checkout had changes), ``machine`` (:func:`machine_summary`) and
        ``backend`` (Keras') from that file's ``machine``; ``reused`` as given (trained elsewhere
        and used in place). Each :data:`NOT_RECORDED` where the folder does not record it (no
        readable ``result.json``, or one written before it held ``machine``).
    """
    try:
        with open(os.path.join(run, RESULT_FILE)) as f:
            result = json.load(f)
    except (OSError, ValueError):
        result = {}
    result = result if isinstance(result, dict) else {}
    machine = result.get("machine") if isinstance(result.get("machine"), dict) else {}
    wall = result.get("wall_s_this_run")
    return {"run": run, "steps": result.get("final_step", NOT_RECORDED),
            "wall_s": NOT_RECORDED if wall is None else round(float(wall), 1),
            "commit": machine.get("git_commit") or NOT_RECORDED,
            "machine": machine_summary(machine) if machine else NOT_RECORDED,
            "backend": machine.get("keras_backend") or NOT_RECORDED, "reused": bool(reused)}


def provenance_block(models: dict, reused=(), only=None) -> dict:
    """``{"model_provenance": {name: run_provenance}, "assembled": bool}`` for ``models``
    (``{name: run folder}``), ``reused`` the names trained elsewhere (a reproduction's
    ``reuse``); ``only``: the run folders to keep (all where None). ``assembled`` is true where
    any model kept was reused: its result was put together from runs this one did not train."""
    kept = {n: d for n, d in models.items() if only is None or d in only}
    entries = {n: run_provenance(d, n in reused) for n, d in kept.items()}
    return {"model_provenance": entries, "assembled": any(e["reused"] for e in entries.values())}


def assembled_line(result: dict) -> str:
    """The line of ``tables.md`` saying whether ``result`` (a ``results.json``) was assembled from
    models trained elsewhere, and where ``model_provenance`` records each model's training."""
    prov = result.get("model_provenance", {})
    reused = sorted(n for n, e in prov.items() if e.get("reused"))
    if not result.get("assembled"):
        return (f"Every model was trained by this reproduction ({len(prov)} models; commit, "
                "machine, backend, steps and wall time of each in `results.json`'s "
                "`model_provenance`).")
    return (f"**Assembled**: {len(reused)} of {len(prov)} models were trained elsewhere and "
            f"reused ({', '.join(reused)}); where each was trained (commit, machine, backend, "
            "steps, wall time) is in `results.json`'s `model_provenance`.")
