"""The Markdown of ``experiments.reproduce``'s outputs: ``tables.md`` (Fig. 4, Table 1, Table 2,
the models), Table 1's rows, and the banner of the smoke-test budget."""

from __future__ import annotations

import os

import numpy as np

from stnh_tf.paper.model_provenance import assembled_line

SMOKE_NOTE = ("**Smoke test** (`--budget=tiny`: 2 steps of every model, 1 warm-up step, batch 4, "
              "2 pairs per image from the first 4 images): it checks that every step of the "
              "reproduction runs; its numbers mean nothing (expect errors of hundreds of px).")
"""The banner of every output of ``--budget=tiny``."""


def tables_markdown(result: dict, latency: dict) -> str:
    b = result["budget"]
    paper = result["paper"]
    lines = [f"# Reproduction at budget '{b['name']}'", "",
             f"{b['train_steps']} steps per model ({b['warmup_steps']} warm-up), batch "
             f"{b['batch_size']}, {'mixed bfloat16' if b['mixed_precision'] else 'float32'}; "
             f"{result['test_pairs']} test pairs (seed 1). The paper trains 91,000 steps on all of "
             "COCO 2014 on a GPU: numbers at a smaller budget are not expected to match it.",
             *([f"The sequence model's global gradient norm clipped at "
                f"{b['sequence_clipnorm']:g} (not the paper's recipe: docs/reproduce.md, "
                "\"The hour budget\")."] if b.get("sequence_clipnorm") else []),
             *([f"Total time of this run: {result['wall_s_this_run'] / 3600:.2f} h."]
               if "wall_s_this_run" in result else []),
             *(["", SMOKE_NOTE] if b["name"] == "tiny" else []),
             *(["", f"**Planned for an hour** (`budget_plan` in results.json): "
                    f"{result['budget_plan']['reason']}"] if result.get("budget_plan") else []),
             "", "## Fig. 4: mean corner error on the same test pairs", "",
             FIG4_NOTE, "",
             f"The paper's schedule: {SCHEDULE_NOTE}", "",
             "| method | MACE (px), ours | paper's schedule | paper |",
             "| --- | ---: | ---: | ---: |"]
    rejected = result.get("fig4_rejected", {})
    schedule = result.get("paper_schedule", {})
    for name, v in result["fig4_mace"].items():
        p = paper["fig4_mace"].get(name)
        mark = " (rejected: see below)" if rejected.get(name) else ""
        lines.append(f"| {name}{mark} | {v:.2f} | {_cell(schedule.get('fig4_mace', {}), name)} | "
                     f"{'' if p is None else f'{p:.2f}'} |")
    if rejected:
        lines += ["", "Rejected predictions (the hierarchy's rule: non-finite, singular or leaving "
                  "the context; such a pair keeps the estimate before that stage, the identity at "
                  "stage 1, or is clipped onto the context, so the row's MACE is not the "
                  "networks' alone; Fig. 4 hatches these bars): " + "; ".join(
                      f"{name}: {n} stage predictions for {result['test_pairs']} pairs"
                      for name, n in rejected.items()) + "."]
    steps = b["ablation_steps"] or b["train_steps"]
    lines += ["", f"## Table 1: loss weights, single stage ({steps} steps per row)", "",
              *table1_lines(result["table1_mace_per_seed"], result["fig4_mace"].get("Identity"),
                            paper["table1_mace"], schedule.get("table1_mace", {}),
                            result.get("table1_claim", {}).get("text", ""))]
    lines += ["", *table2_lines(latency, paper["table2_gpu_ms"])]
    lines += ["", "## Models", "",
              *([assembled_line(result), ""] if "model_provenance" in result else []),
              "| model | directory | trained on |", "| --- | --- | --- |"]
    dropped = b.get("drop_after_eval", ())
    for name, d in _model_dirs(result["models"]):
        gone = (" (model file removed after its evaluation at this budget)"
                if os.path.basename(d) in dropped and not os.path.exists(
                    os.path.join(d, "model.keras")) else "")
        lines.append(f"| {name}{gone} | `{d}` | {_trained_on(d)} |")
    lines += ["", "Figures: " + ", ".join(f"[{k}](figures/{os.path.basename(v)})"
                                          for k, v in result["figures"].items()), ""]
    return "\n".join(lines)


SCHEDULE_NOTE = ("the paper's recipe at its 91,000 steps per model, on the pairs of "
                 "`experiments.paper_schedule` (not this budget's), evaluated on the same test "
                 "pairs, the hierarchy without the clipping of corners onto the context "
                 "(`experiments.evaluate --no_clip`: the networks alone; "
                 "`stnh_tf/weights/paper_schedule/model_card.json`; docs/gpu.md); empty: "
                 "not trained yet, or other test pairs.")
"""What the "paper's schedule" column of the tables is."""

FIG4_NOTE = ("MACE (px) of each method on the same test pairs. STN-Homography 1 stage is the "
             "stage-1 network's own estimate, the quantity of Table 1 (its 1:1 row's seed 0 is "
             "this model); 2 and 3 stages are the hierarchy, whose degenerate-prediction rule "
             "acts on each stage's prediction (rows where it acted are marked).")
"""The caption of Fig. 4's table: which quantity each row is."""

TABLE1_NOTE = ("MACE (px) on the same test pairs of each model's own estimate (no "
               "degenerate-prediction rule: the quantity of Fig. 4's STN-Homography 1 stage, which "
               "is the 1:1 row's seed 0); the mean over the row's seeds, and each seed's MACE in "
               "seed order.")
"""The caption of Table 1."""

TABLE1_HEAD = ["| L2 weight | L1 weight | MACE (px), ours | per seed | paper's schedule "
               "| paper |", "| ---: | ---: | ---: | ---: | ---: | ---: |"]

CLAIM_ROWS = ("10,1", "1,1")
"""The Table 1 rows the paper's claim compares: L2:L1 = 10:1 gives a lower MACE than 1:1."""


def table1_lines(per_seed: dict, identity, paper: dict, schedule: dict, claim: str = "") -> list:
    """Table 1 as Markdown lines: :data:`TABLE1_NOTE`, the header, the identity's row (the MACE
    of no estimate on the same pairs; ``None``: left out), one :func:`table1_line` per row of
    ``per_seed`` (``{"l2,l1": [MACE per seed]}``, the paper's and the paper's schedule's values
    from ``paper`` and ``schedule`` under the same keys) and the ``claim`` line
    (:func:`table1_claim`'s text; empty: none)."""
    lines = [TABLE1_NOTE, "", *TABLE1_HEAD]
    if identity is not None:
        lines.append(f"| identity (no model) |  | {identity:.2f} |  |  |  |")
    lines += [table1_line(*key.split(","), v, paper.get(key), schedule.get(key))
              for key, v in per_seed.items()]
    return lines + (["", claim] if claim else [])


def earlier_table1_rows(path: str, rows: dict, steps: int) -> dict:
    """The rows of an earlier ``table1.json`` at ``path`` that ``rows`` (``{(l2, l1): [model
    dir per seed]}``) lacks and whose models are all still finished there, trained ``steps``
    steps: ``{(l2, l1): [model dir per seed]}`` (``{}`` where there is no such file). A run of
    some rows (``loss_weight_ablation --weights=10:1``) keeps the table's other rows this way.

    Raises:
      ValueError: ``path`` is not a JSON object.
    """
    import json

    from stnh_tf.training import run_dir

    if not os.path.exists(path):
        return {}
    try:
        with open(path) as f:
            earlier = json.load(f)
        if not isinstance(earlier, dict):
            raise ValueError
    except ValueError:
        raise ValueError(f"{path} is not a Table 1 written by this project (not a JSON "
                         "object); move it aside to write a new one") from None
    kept = {}
    for key, row in earlier.items():
        dirs = row.get("model_dirs") if isinstance(row, dict) else None
        try:
            weights = tuple(float(v) for v in key.split(","))
        except ValueError:
            continue  # (the provenance entries)
        if weights in rows or not dirs or len(weights) != 2:
            continue
        if all(os.path.exists(os.path.join(d, run_dir.FINAL_MODEL))
               and _trained_steps(os.path.join(d, run_dir.CONFIG_FILE)) == steps for d in dirs):
            kept[weights] = list(dirs)
    return kept


def _trained_steps(config_path: str):
    """``train_steps`` of a run's ``config.json`` (None where it is missing or unreadable)."""
    import json

    try:
        with open(config_path) as f:
            return json.load(f).get("train_steps")
    except (OSError, ValueError, AttributeError):
        return None


def table1_claim(per_seed: dict, identity, verdicts: bool = True) -> dict:
    """The paper's Table 1 claim (L2:L1 = 10:1 below 1:1, :data:`CLAIM_ROWS`) judged on
    ``per_seed`` (``{"l2,l1": [MACE per seed]}``): ``{"verdict", "text"}`` with ``verdict`` one
    of ``"holds"`` (every seed of 10:1 below every seed of 1:1), ``"does not hold"`` (every seed
    above), ``"unresolved"`` (the seeds overlap) or ``"none"``: no verdict where the budget
    cannot support one (``verdicts=False``: the smoke test) or where a compared row's mean is not
    below the ``identity``'s MACE. ``{}`` where a compared row is missing.

    >>> table1_claim({"10,1": [4.8, 4.9], "1,1": [5.8, 5.9]}, 24.0)["verdict"]
    'holds'
    >>> table1_claim({"10,1": [4.8, 4.9], "1,1": [5.8, 5.9]}, 24.0, verdicts=False)["verdict"]
    'none'
    """
    better, base = CLAIM_ROWS
    if better not in per_seed or base not in per_seed:
        return {}
    a, b = per_seed[better], per_seed[base]

    def span(v):
        return (f"{min(v):.2f}-{max(v):.2f}" if len(v) > 1 else f"{v[0]:.2f}") + " px"

    above = [k for k in CLAIM_ROWS if identity is not None and np.mean(per_seed[k]) >= identity]
    if not verdicts:
        verdict, text = "none", ("no verdict at this budget: its models are not trained enough "
                                 "for one.")
    elif above:
        verdict, text = "none", ("no verdict: " + ", ".join(
            f"the {k.replace(',', ':')} row (mean {np.mean(per_seed[k]):.2f} px)" for k in above)
            + f" not below the identity's {identity:.2f} px.")
    elif max(a) < min(b):
        verdict, text = "holds", (f"holds at this budget: every seed of 10:1 ({span(a)}) is "
                                  f"below every seed of 1:1 ({span(b)}).")
    elif min(a) > max(b):
        verdict, text = "does not hold", (f"does not hold at this budget: every seed of 10:1 "
                                          f"({span(a)}) is above every seed of 1:1 ({span(b)}).")
    else:
        verdict, text = "unresolved", (f"unresolved at this budget: the seeds overlap (10:1 "
                                       f"{span(a)}, 1:1 {span(b)}).")
    return {"verdict": verdict,
            "text": "The paper's claim (L2:L1 = 10:1 gives a lower MACE than 1:1): " + text}


def table2_lines(latency: dict, paper_gpu_ms: dict) -> list[str]:
    """``tables.md``'s Table 2 section, from its heading to the sequence models' line:
    ``latency`` (:func:`stnh_tf.evaluation.mace.latency`'s result with the budget's ``policy``)
    beside ``paper_gpu_ms`` (the paper's ms per number of stages, keyed by int, or by str as a
    ``results.json`` read back holds them)."""
    lines = [f"## Table 2: batch-1 latency ({latency.get('policy', '')}; paper: a GPU)", "",
             latency_note(latency), "",
             "| stages | d_e (ms), ours | formula (l_m + l_w) n | paper GPU (ms) |",
             "| ---: | ---: | ---: | ---: |"]
    for k, v in latency["hierarchy"].items():
        gpu = paper_gpu_ms.get(int(k), paper_gpu_ms.get(str(k), float("nan")))
        lines.append(f"| {k} | {v['d_e_ms']:.2f} | {v['formula_ms']:.2f} | {gpu:.2f} |")
    if latency.get("sequence"):
        lines += ["", "Sequence models, forward pass: " + ", ".join(
            f"{k} stage{'s' if k != '1' else ''} {v['forward_ms']:.2f} ms"
            for k, v in latency["sequence"].items()) + "."]
    return lines


def latency_note(latency: dict) -> str:
    """The caption of Table 2: what ``d_e`` and the formula column are, with this run's ``l_m``
    and ``l_w`` (:func:`stnh_tf.evaluation.mace.latency`'s result)."""
    terms = (f" (here l_m = {latency['l_m_ms']:.2f} ms, l_w = {latency['l_w_ms']:.2f} ms)"
             if "l_m_ms" in latency and "l_w_ms" in latency else "")
    return ("d_e: the measured end-to-end time of n stages on one pair (median of repeated runs). "
            "Formula: the paper's model of it, d_e = (l_m + l_w) n, from l_m, one stage's "
            "network forward pass, and l_w, the warp of the context and crop of the next "
            "patch_a between stages with the degenerate-prediction rule, each timed alone"
            f"{terms}. Paper GPU: the paper's Table 2.")


def _cell(values: dict, key) -> str:
    return f"{values[key]:.2f}" if values.get(key) is not None else ""


def table1_line(l2: str, l1: str, maces, paper, schedule=None) -> str:
    """One Table 1 row: the mean over seeds, and each seed's MACE (in seed order) when there are
    several; ``schedule``: the row's MACE at the paper's schedule (None: not trained)."""
    spread = (f"{len(maces)} seeds: " + ", ".join(f"{m:.2f}" for m in maces) if len(maces) > 1
              else "1 seed")
    return (f"| {l2} | {l1} | {float(np.mean(maces)):.2f} | {spread} | "
            f"{_cell({0: schedule}, 0)} | {'' if paper is None else f'{paper:.2f}'} |")


def schedule_results(identity_mace: float, weights_dir=None) -> dict:
    """The MACEs of the models trained at the paper's schedule, under the names of the tables:
    ``{"fig4_mace": {"STN-Homography k stage(s)": MACE}, "table1_mace": {"1,1": MACE}}``, from
    the model card in ``weights_dir`` (default: the package's ``weights/paper_schedule``; its
    ``evaluation`` is ``experiments.evaluate``'s JSON of the shipped stages). Empty dicts where
    nothing is shipped there, or where the card's test pairs are not the tables' (their
    identity MACE differs from ``identity_mace``).

    Raises:
      ValueError: the card's evaluation names another number of stages than it ships.
    """
    import json

    from stnh_tf.inference import model_files

    folder = weights_dir or os.path.join(model_files.default_weights_dir(),
                                         model_files.PAPER_SCHEDULE_WEIGHTS)
    out = {"fig4_mace": {}, "table1_mace": {}}
    path = os.path.join(folder, "model_card.json")
    if not os.path.exists(path):
        return out
    with open(path) as f:
        card = json.load(f)
    if abs(card["evaluation"]["identity"]["mace"] - identity_mace) > 1e-6:
        return out
    model, n = card["evaluation"]["model"], len(card["stages"])
    try:
        per_stage = ({1: model["mace"]} if n == 1 and "stages" not in model else
                     {k: model["stages"][f"after_{k}_stages"]["mace"] for k in range(1, n + 1)})
    except KeyError:
        raise ValueError(f"{path}: the evaluation does not cover the {n} stages the card "
                         "ships.") from None
    for k, mace in per_stage.items():
        out["fig4_mace"][f"STN-Homography {k} stage{'s' if k > 1 else ''}"] = mace
    out["table1_mace"]["1,1"] = per_stage[1]
    return out


def _model_dirs(models: dict):
    for k, d in enumerate(models["stages"], start=1):
        yield f"stage {k}", d
    yield "HomographyNet", models["homographynet"]
    yield "sequence, 2 stages", models["sequence2"]
    for key, dirs in models["ablation_seeds"].items():
        for seed, d in enumerate(dirs):
            if d not in models["stages"]:
                yield (f"ablation L2:L1 = {key.replace(',', ':')}"
                       f"{f', seed {seed}' if seed else ''}", d)


def _trained_on(model_dir: str) -> str:
    """The data source a model's recorded configuration names."""
    from stnh_tf.training import run_dir

    try:
        cfg = run_dir.read_run_config(os.path.join(model_dir, run_dir.CONFIG_FILE))
    except (OSError, ValueError):
        return "?"
    if cfg.get("image_dir"):
        how = "in memory" if cfg.get("in_memory") else "generated on the fly"
        return (f"pairs from `{cfg['image_dir']}` ({cfg.get('samples_per_image')} per image, "
                f"seed {cfg.get('seed')}, {how})")
    return f"TFRecords `{cfg.get('data_dir')}`"
