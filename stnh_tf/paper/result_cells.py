"""The cells of the "current results" tables (:mod:`stnh_tf.paper.current_results`) that take
more than one value to write: Table 1's row, the camera-pair rows, a JSON's commit and machine,
where a reproduction's models were trained (:func:`provenance_cells`), where Table 2 was
measured. The standard library only.
"""

from __future__ import annotations

from stnh_tf.paper.model_provenance import machine_summary
from stnh_tf.paper.results_json import NOT_RECORDED, SOURCES, fixed, value

# Table 1's rows in the paper's order, as (results.json key, label).
TABLE1_ROWS = (("1,1", "1:1"), ("1,10", "1:10"), ("1,0.1", "1:0.1"), ("10,1", "10:1"),
               ("0.1,1", "0.1:1"))


def joined(sources, name, paths, digits=2, bold=None):
    """``a / b / c`` of the values at ``paths``; the one at index ``bold`` in bold."""
    parts = [fixed(value(sources, name, p), digits) for p in paths]
    if bold is not None:
        parts[bold] = f"**{parts[bold]}**"
    return " / ".join(parts)


def stage_paths(prefix, field="mace"):
    return [f"{prefix}/stages/after_{k}_stages/{field}" for k in (1, 2, 3)]


def recorded(sources, name, path="machine") -> tuple[str, str]:
    """The (commit, machine) cells of what source ``name`` records at ``path``: the object of
    :func:`stnh_tf.provenance.machine_info` (the CPU, its cores, any accelerator and the Keras
    backend), each ``NOT_RECORDED`` where the JSON has none."""
    try:
        info = value(sources, name, path)
    except KeyError:
        return NOT_RECORDED, NOT_RECORDED
    accelerators = sorted({*info.get("gpus", []),
                           *(d for d in info.get("jax_devices", []) if d.lower() != "cpu")})
    machine = "; ".join([f"{info.get('cpu') or 'CPU'}, {info.get('cpu_count')} cores",
                         *accelerators])
    if info.get("keras_backend"):
        machine += f" ({info['keras_backend']})"
    return info.get("git_commit") or NOT_RECORDED, machine


# The models of Fig. 4's row (the reproduction's names; Table 1's are table1.json's own).
FIG4_MODELS = ("stage1", "stage2", "stage3", "homographynet", "homographynet_gap", "sequence2")


def machine_label(entry: dict) -> str:
    """A model's or measurement's machine as one cell part: its accelerators, else its CPU and
    cores, with the Keras backend, from a ``model_provenance`` entry
    (:func:`stnh_tf.paper.model_provenance.run_provenance`) or a :func:`recorded`-like object."""
    machine = entry.get("machine")
    if not isinstance(machine, dict):
        return NOT_RECORDED
    label = (", ".join(machine["accelerators"]) if machine.get("accelerators")
             else f"{machine.get('cpu')}, {machine.get('cores')} cores")
    backend = entry.get("backend")
    return f"{label} ({backend})" if backend and backend != NOT_RECORDED else label


def _span(entries) -> str:
    """Where ``entries`` (``model_provenance`` entries) were trained: "between A and B" (the
    earliest ``trained_after`` and the latest ``recorded_in`` of reconstructed entries, by date),
    else "at" the distinct commits they record."""
    if all("trained_after" in e and "recorded_in" in e for e in entries):
        first = min((e["trained_after"] for e in entries), key=lambda c: c["date"])
        last = max((e["recorded_in"] for e in entries), key=lambda c: c["date"])
        return f"between {first['commit']} and {last['commit']}"
    return "at " + ", ".join(dict.fromkeys(str(e.get("commit", NOT_RECORDED)) for e in entries))


def provenance_cells(sources, name, models=None, measured=None) -> tuple[str, str]:
    """The (commit, machine) cells of a reproduction's row from source ``name``'s
    ``model_provenance`` (``results.json``, ``table1.json``), for the models named ``models``
    (all where None): "assembled: trained between A and B" (or "trained at" their commits) and
    their distinct machines; ``measured``, the key of an entry of the same form for what the row
    measures beyond the models (Table 2's latency: ``latency_provenance``), adds "measured ...".
    A source without ``model_provenance``, or without any of the models named, falls back to
    :func:`recorded`; a model named that it lacks is left out (a fresh reproduction trains no
    ``homographynet_gap``).
    """
    doc = sources[name]
    if "model_provenance" not in doc:
        return recorded(sources, name)
    prov = doc["model_provenance"]
    entries = [prov[m] for m in (models or prov) if m in prov]
    if not entries:
        return recorded(sources, name)
    commit = ("assembled: " if doc.get("assembled") else "") + f"trained {_span(entries)}"
    machines = [machine_label(e) for e in entries]
    if measured and measured in doc:
        commit += f"; measured {_span([doc[measured]])}"
        machines.append(machine_label(doc[measured]))
    elif "machine" in doc:  # a reproduction that evaluated its models itself: its machine_info
        info = doc["machine"]
        commit += f"; evaluated at {info.get('git_commit') or NOT_RECORDED}"
        machines.append(machine_label({"machine": machine_summary(info),
                                       "backend": info.get("keras_backend")}))
    return commit, "; ".join(dict.fromkeys(machines))


# Where the committed CPU-budget reproduction ran: results.json, written before machine blocks,
# records none; BENCHMARKS.md ("experiments.reproduce --budget=cpu") names the machine.
REPRODUCE_MACHINE = "the CPU machine of BENCHMARKS.md (2 cores, x86_64 with AVX-512/AMX)"


def latency_refreshed(sources) -> dict | None:
    """results.json's ``latency_provenance`` where it records the load (Table 2 measured again
    by ``experiments.reproduce --refresh_latency``), else ``None`` (as reconstructed, or none)."""
    measured = sources["results"].get("latency_provenance")
    return measured if isinstance(measured, dict) and (
        measured.get("loadavg_at_start") or measured.get("loadavg_at_end")) else None


def latency_command(sources, reproduce: str) -> str:
    """The command cell of Table 2's row: ``reproduce`` (the reproduction's), or the refresh's
    where Table 2 was measured again (:func:`latency_refreshed`)."""
    if not latency_refreshed(sources):
        return reproduce
    folder = SOURCES["results"].rsplit("/", 1)[0]
    return (f"`python -m experiments.reproduce --output_dir={folder} --refresh_latency` "
            "([how](docs/reproduce.md))")


def latency_cells(sources) -> tuple[str, str]:
    """The (commit, machine) cells of Table 2's row: where Table 2 was measured again
    (:func:`latency_refreshed`), "measured at" its commit on untrained models and its machine
    alone (the trained stages took no part); else :func:`provenance_cells` of the three stages
    with ``latency_provenance``."""
    measured = latency_refreshed(sources)
    if not measured:
        return provenance_cells(sources, "results", ("stage1", "stage2", "stage3"),
                                "latency_provenance")
    return (f"measured at {measured.get('commit') or NOT_RECORDED} on untrained models",
            machine_label(measured))


def latency_machine(sources) -> str:
    """Where Table 2's latencies were measured and under what load: results.json's
    ``latency_provenance`` where it records the load (a measurement of
    ``experiments.reproduce --refresh_latency``, :func:`stnh_tf.paper.table2.refresh`: its
    machine, commit, date and 1-minute load averages at the start and end of the measurement,
    its own load included at the end), else its ``machine`` block (:func:`recorded`, its
    ``loadavg_at_start``) where it has one, else :data:`REPRODUCE_MACHINE`, the load "not
    recorded"."""
    measured = latency_refreshed(sources)
    if measured:
        loads = " and ".join(f"{load[0]:.2f} at {when}" for load, when in (
            (measured.get("loadavg_at_start"), "start"), (measured.get("loadavg_at_end"), "end"))
            if load)
        return (f"{machine_label(measured)}, code {measured.get('commit') or NOT_RECORDED}, "
                f"{str(measured.get('date') or NOT_RECORDED)[:10]}, 1-minute load {loads}")
    commit, machine = recorded(sources, "results")
    if machine == NOT_RECORDED:
        return f"{REPRODUCE_MACHINE}, its load not recorded"
    load = value(sources, "results", "machine").get("loadavg_at_start")
    return (f"{machine}, code {commit}, "
            + (f"load {load[0]:.2f} at start" if load else "its load not recorded"))


def table1_cells(sources):
    """Table 1 as cells (ours, note, paper): our means (best in bold), the ranges of the rows
    trained with several seeds, the paper's values (best in bold)."""
    ours = {key: value(sources, "table1", f"{key}/mace") for key, _ in TABLE1_ROWS}
    paper = {key: value(sources, "table1", f"{key}/paper") for key, _ in TABLE1_ROWS}
    best, paper_best = min(ours, key=ours.get), min(paper, key=paper.get)
    cells = [f"**{fixed(ours[k])}**" if k == best else fixed(ours[k]) for k, _ in TABLE1_ROWS]
    paper_cells = [f"**{paper[k]:g}**" if k == paper_best else f"{paper[k]:g}"
                   for k, _ in TABLE1_ROWS]
    ranges = []
    for key, label in TABLE1_ROWS:
        seeds = value(sources, "table1", f"{key}/mace_per_seed")
        if len(seeds) > 1:
            ranges.append((label, len(seeds), f"{fixed(min(seeds))}-{fixed(max(seeds))}"))
    note = ""
    if ranges:
        counts = {n for _, n, _ in ranges}
        seeds = f"{counts.pop()} seeds" if len(counts) == 1 else "several seeds"
        note = (f" ({' and '.join(label for label, _, _ in ranges)}: mean of {seeds}, ranges "
                f"{' and '.join(r for _, _, r in ranges)})")
    return " / ".join(cells), note, " / ".join(paper_cells)


# estimate_images' default on the camera-pair benchmark (issue 64): (source, groups, the set's
# make_camera_pairs flags), seed 0 (the development seed)
CAMERA_SETS = (("camera0_current", ("within", "1-2x", "2-4x"), "--seed=0"),
               ("camera0_wide_current", ("wide", "wide_low_light"),
                "--motion_set=wide --seed=0 --pairs_per_image=2"))
CAMERA_METHODS = (("estimator", "estimator"), ("sift_ransac", "SIFT + RANSAC"),
                  ("sift_wide", "SIFT, wide settings"), ("orb_ransac", "ORB + RANSAC"))


def camera_rows(sources) -> list[tuple[str, str, str, str, str, str]]:
    """One row of the "Current results" table per group of :data:`CAMERA_SETS`: each method's
    successes (under 3 px), mean MACE and ms per pair, the identity's MACE, the estimator's flag
    (estimates more than 5 px off flagged, good ones flagged)."""
    rows = []
    for name, groups, flags in CAMERA_SETS:
        command = (f"`python -m experiments.make_camera_pairs --output_dir=D {flags}`, then "
                   "`python -m experiments.benchmark_camera_pairs --pairs_dir=D "
                   "--methods=estimator,sift_ransac,sift_wide,orb_ransac,identity`")
        for group in groups:
            result = value(sources, name, f"groups/{group}")
            cells = []
            for key, label in CAMERA_METHODS:
                r = result[key]
                ok = f"{round(r['success_rate'] * r['count'])} of {r['count']}"
                cells.append(f"{label} {f'**{ok}**' if key == 'estimator' else ok}, "
                             f"{fixed(r['mace'])} px, {r['ms_per_pair']:.0f} ms")
            flag = result["estimator"]["flag"]
            good = result["estimator"]["count"] - flag["bad"]
            rows.append((
                f"[`estimate_images`' default](docs/estimate.md#real-photographs-estimateoptionsph"
                f"otographs-default-of-estimate_images) (`photographs()`), camera pairs, group "
                f"`{group}` (seed 0, the development seed; [held-out seeds](#wide-baselines-issue-"
                f"64-the-coarse-pass-out-of-the-default))",
                "success, mean MACE at the image corners, time per pair: " + "; ".join(cells)
                + f"; identity {fixed(result['identity']['mace'])} px; flag: {flag['flagged_bad']}"
                f" of {flag['bad']} estimates more than 5 px off, {flag['flagged_good']} of {good}"
                " good ones", command, f"`{SOURCES[name]}`", *recorded(sources, name)))
    return rows
