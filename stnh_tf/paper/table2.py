"""The paper's Table 2 in a reproduction: batch-1 latency measured at the budget's runs, warm-up
and precision (:func:`measure`, the one call of :func:`stnh_tf.evaluation.mace.latency` that
``experiments.reproduce`` makes, in a run and in a refresh), the ``results.json`` keys it fills
(:func:`results_fields`), and :func:`refresh`: Table 2 of an existing reproduction folder
measured again and written back with where and under what load it was measured
(``experiments.reproduce --refresh_latency``).

Latency does not depend on the weights: a refresh times untrained models built under the
budget's policy (a folder's stage models may be gone, as the committed CPU-budget ones are).
"""

from __future__ import annotations

import json
import os
import time

from stnh_tf.paths import atomic_write_json, atomic_write_text
from stnh_tf.paper.model_provenance import machine_summary
from stnh_tf.paper.results_json import NOT_RECORDED
from stnh_tf.paper.tables import table2_lines
from stnh_tf.provenance import load_average, machine_info
from stnh_tf.training.config import dtype_policy

REFRESHED_KEYS = ("table2_latency_ms", "sequence_latency_ms", "latency_provenance")
"""The keys of ``results.json`` that :func:`refresh` replaces; it leaves every other as it is."""
BUDGET_KEYS = ("latency_runs", "latency_warmup", "mixed_precision")


policy = dtype_policy
"""The Keras dtype policy of a budget (:func:`stnh_tf.training.config.dtype_policy` of its
``mixed_precision``)."""


def measure(stage_dirs, runs: int, warmup: int, dtype_policy: str) -> dict:
    """:func:`stnh_tf.evaluation.mace.latency` of the stage models in ``stage_dirs`` (untrained
    models built under ``dtype_policy`` where empty), medians over ``runs`` timed calls after
    ``warmup``, sequence models included; its ``policy`` is ``dtype_policy``, the budget's."""
    from stnh_tf.evaluation import mace as evaluation

    result = evaluation.latency(list(stage_dirs), runs=runs, warmup=warmup, policy=dtype_policy,
                                sequence=True)
    result["policy"] = dtype_policy
    return result


def measured(stage_dirs, runs: int, warmup: int, dtype_policy: str, models: str,
             timed=lambda f: f()) -> dict:
    """:func:`measure` (run through ``timed``) with its ``provenance``: ``commit``, ``machine``
    (``{"cpu", "cores", "accelerators"}``), ``backend`` and ``command``
    (:func:`stnh_tf.provenance.machine_info`), ``date`` (UTC, the measurement's start),
    ``loadavg_at_start`` and ``loadavg_at_end`` (``None`` where the OS has none), ``models``
    (what was timed, in words), ``policy``, ``runs``, ``warmup`` and ``versions``."""
    date, load_start = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), load_average()
    latency = timed(lambda: measure(stage_dirs, runs, warmup, dtype_policy))
    load_end, info = load_average(), machine_info()
    return {**latency, "provenance": {
        "commit": info.get("git_commit") or NOT_RECORDED, "machine": machine_summary(info),
        "backend": info.get("keras_backend") or NOT_RECORDED, "date": date,
        "loadavg_at_start": load_start, "loadavg_at_end": load_end,
        "command": info.get("command"), "models": models,
        "policy": latency["policy"], "runs": runs, "warmup": warmup,
        "versions": {k: info[k] for k in ("platform", "python", "numpy", "opencv", "tensorflow",
                                          "jax", "keras", "stnh_tf") if k in info}}}


def cached(path: str, stage_dirs, runs: int, warmup: int, dtype_policy: str,
           timed=lambda f: f()) -> dict:
    """:func:`measured` of ``stage_dirs`` (a reproduction's own stage models), kept at ``path``
    and read back only where it was measured with these runs, warm-up, policy and models (its
    ``cache_key``); one of another precision, or without the key, is measured again."""
    key = {"policy": dtype_policy, "runs": runs, "warmup": warmup,
           "models": [os.path.abspath(d) for d in stage_dirs]}
    if os.path.exists(path):
        with open(path) as f:
            doc = json.load(f)
        if isinstance(doc, dict) and doc.get("cache_key") == key:
            return doc
    doc = {**measured(stage_dirs, runs, warmup, dtype_policy, "this reproduction's stage "
                      "models", timed), "cache_key": key}
    atomic_write_json(path, doc)
    return doc


def results_fields(latency: dict) -> dict:
    """``results.json``'s Table 2 keys from :func:`measure`'s result: ``table2_latency_ms`` (each
    number of stages' end-to-end ``d_e``) and ``sequence_latency_ms`` (each sequence model's
    forward pass), in ms, keyed ``"1"``, ``"2"``, ``"3"``; and ``latency_provenance`` where the
    result is ``eval/latency.json`` of :func:`refresh` (its ``provenance``)."""
    return {"table2_latency_ms": {k: v["d_e_ms"] for k, v in latency["hierarchy"].items()},
            "sequence_latency_ms": {k: v["forward_ms"]
                                    for k, v in latency.get("sequence", {}).items()},
            # (a measurement of --refresh_latency: its own commit, machine and load)
            **({"latency_provenance": latency["provenance"]} if "provenance" in latency
               else {})}


def _read_results(path: str) -> tuple[str, dict]:
    """The text and the object of the ``results.json`` at ``path``, its budget checked.

    Raises:
      ValueError: one line naming ``path``: missing, unreadable, not a JSON object, or without
        the budget's latency fields.
    """
    try:
        with open(path) as f:
            text = f.read()
        result = json.loads(text)
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: no readable results.json of a reproduction ({e}); nothing "
                         "written.") from None
    budget = result.get("budget") if isinstance(result, dict) else None
    missing = [k for k in BUDGET_KEYS if not isinstance(budget, dict) or k not in budget]
    if missing:
        raise ValueError(f"{path}: its budget records no {', '.join(missing)}: Table 2's runs and "
                         "precision are unknown; nothing written.")
    return text, result


def _table2_section(tables_md: str, lines: list[str]) -> str | None:
    """``tables_md`` with its ``## Table 2`` section (up to the next ``## `` heading) replaced by
    ``lines``; ``None`` where it has no such section."""
    start = tables_md.find("## Table 2")
    if start < 0 or (start and tables_md[start - 1] != "\n"):
        return None
    end = tables_md.find("\n## ", start)
    end = len(tables_md) if end < 0 else end + 1
    return tables_md[:start] + "\n".join(lines) + "\n\n" + tables_md[end:]


def refresh(output_dir: str, printer=print) -> dict:
    """Measure Table 2 of the reproduction in ``output_dir`` again and write it back.

    Reads ``output_dir/results.json``; measures (:func:`measure`) untrained models built under
    its budget's policy (``budget.mixed_precision``) with its ``budget.latency_runs`` and
    ``latency_warmup``; then writes, each file atomically and ``results.json`` last:

    - ``eval/latency.json``: the measurement (with ``l_m``, ``l_w``) and its provenance;
    - ``tables.md``: its Table 2 section alone, where it has one;
    - ``results.json``: :data:`REFRESHED_KEYS` replaced, every other key and the file's layout
      (key order, indentation, final newline or none) as they were.

    ``latency_provenance`` is :func:`measured`'s ``provenance`` (the load averages: 1-, 5- and
    15-minute, just before and just after the measurement).

    Returns:
      The ``results.json`` written.

    Raises:
      ValueError: ``results.json`` is missing, unreadable, or its budget lacks
        :data:`BUDGET_KEYS` (one line; nothing measured, nothing written).
    """
    path = os.path.join(output_dir, "results.json")
    text, result = _read_results(path)
    budget = result["budget"]
    dtype_policy = policy(bool(budget["mixed_precision"]))
    runs, warmup = int(budget["latency_runs"]), int(budget["latency_warmup"])
    printer(f"[latency] {path}: Table 2 again, {runs} runs after {warmup} warm-up, "
            f"{dtype_policy}, untrained models")
    latency = measured((), runs, warmup, dtype_policy, f"untrained, built under {dtype_policy} "
                       "(latency does not depend on the weights)")
    provenance = latency.pop("provenance")
    load_start, load_end = provenance["loadavg_at_start"], provenance["loadavg_at_end"]
    written = dict(result)  # (the replaced keys keep their place; new ones go last)
    written.update(results_fields(latency), latency_provenance=provenance)
    os.makedirs(os.path.join(output_dir, "eval"), exist_ok=True)
    atomic_write_json(os.path.join(output_dir, "eval", "latency.json"),
                      {**latency, "provenance": provenance})
    tables_path = os.path.join(output_dir, "tables.md")
    if os.path.exists(tables_path):
        with open(tables_path) as f:
            tables = _table2_section(f.read(), table2_lines(
                latency, result.get("paper", {}).get("table2_gpu_ms", {})))
        if tables is not None:
            atomic_write_text(tables_path, tables)
    atomic_write_text(path, json.dumps(written, indent=2)
                      + ("\n" if text.endswith("\n") else ""))
    ms = results_fields(latency)
    loads = " and ".join(f"{x[0]:.2f} at {when}" for x, when in ((load_start, "start"),
                                                                  (load_end, "end")) if x)
    printer(f"[latency] wrote {path}: hierarchy "
            + " / ".join(f"{v:.2f}" for v in ms["table2_latency_ms"].values())
            + " ms, sequence " + " / ".join(f"{v:.2f}" for v in ms["sequence_latency_ms"].values())
            + f" ms; load {loads or NOT_RECORDED}")
    return written
