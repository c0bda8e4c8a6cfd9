"""The Markdown of ``experiments.reproduce``'s outputs: ``tables.md`` (Fig. 4, Table 1, Table 2,
the models), Table 1's rows, and the banner of the smoke-test budget."""

from __future__ import annotations

import os

import numpy as np

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
             *([f"Total time of this run: {result['wall_s_this_run'] / 3600:.2f} h."]
               if "wall_s_this_run" in result else []),
             *(["", SMOKE_NOTE] if b["name"] == "tiny" else []), "",
             "## Fig. 4: mean corner error on the same test pairs", "",
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
                  "stage 1, so the row's MACE is not the network's): " + "; ".join(
                      f"{name}: {n} stage predictions for {result['test_pairs']} pairs"
                      for name, n in rejected.items()) + "."]
    steps = b["ablation_steps"] or b["train_steps"]
    lines += ["", f"## Table 1: loss weights, single stage ({steps} steps per row)", "",
              *TABLE1_HEAD]
    for key, v in result["table1_mace_per_seed"].items():
        lines.append(table1_line(*key.split(","), v, paper["table1_mace"].get(key),
                                 schedule.get("table1_mace", {}).get(key)))
    lines += ["", f"## Table 2: batch-1 latency ({latency.get('policy', '')}; paper: a GPU)", "",
              "| stages | d_e (ms), ours | formula (l_m + l_w) n | paper GPU (ms) |",
              "| ---: | ---: | ---: | ---: |"]
    for k, v in latency["hierarchy"].items():
        lines.append(f"| {k} | {v['d_e_ms']:.2f} | {v['formula_ms']:.2f} | "
                     f"{paper['table2_gpu_ms'].get(int(k), float('nan')):.2f} |")
    if latency.get("sequence"):
        lines += ["", "Sequence models, forward pass: " + ", ".join(
            f"{k} stage{'s' if k != '1' else ''} {v['forward_ms']:.2f} ms"
            for k, v in latency["sequence"].items()) + "."]
    lines += ["", "## Models", "", "| model | directory | trained on |", "| --- | --- | --- |"]
    for name, d in _model_dirs(result["models"]):
        lines.append(f"| {name} | `{d}` | {_trained_on(d)} |")
    lines += ["", "Figures: " + ", ".join(f"[{k}](figures/{os.path.basename(v)})"
                                          for k, v in result["figures"].items()), ""]
    return "\n".join(lines)


SCHEDULE_NOTE = ("the paper's recipe at its 91,000 steps per model, on the pairs of "
                 "`experiments.paper_schedule` (not this budget's), evaluated on the same test "
                 "pairs (`stnh_tf/weights/paper_schedule/model_card.json`; docs/gpu.md); empty: "
                 "not trained yet, or other test pairs.")
"""What the "paper's schedule" column of the tables is."""

TABLE1_HEAD = ["| L2 weight | L1 weight | MACE (px), ours | seeds: range | paper's schedule "
               "| paper |", "| ---: | ---: | ---: | ---: | ---: | ---: |"]


def _cell(values: dict, key) -> str:
    return f"{values[key]:.2f}" if values.get(key) is not None else ""


def table1_line(l2: str, l1: str, maces, paper, schedule=None) -> str:
    """One Table 1 row: the mean over seeds, and the range when there are several; ``schedule``:
    the row's MACE at the paper's schedule (None: not trained)."""
    spread = (f"{len(maces)} seeds: {min(maces):.2f}-{max(maces):.2f}" if len(maces) > 1
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
