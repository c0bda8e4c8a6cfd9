r"""Fig. 4 drawn again from a reproduction's JSON (issue 78): the library core of
``python -m experiments.render_fig4 --reproduce_dir=docs/reproduce_cpu``.

What :func:`fig4_inputs` gathers, each from a committed record:

- the bars: ``results.json``'s ``fig4_mace`` and the paper's values (``paper/fig4_mace``),
  labelled as assembled where ``results.json`` says so (``assembled``: models from several runs);
- the marks of the degenerate-prediction rule: ``results.json``'s ``fig4_rejected`` where it has
  them; else the counts of a model card whose ``evaluation`` is the same hierarchy on the same
  pairs (its identity's MACE equal to the figure's, and after 2 and 3 stages to 0.01 px; the CPU
  budget's hierarchy ships in ``stnh_tf/weights/paper_recipe``), :func:`hierarchy_rejections`;
- each seed of Table 1's 1:1 row as a dot on the 1-stage bar (``table1_mace_per_seed``: the
  network alone, without the clipping the bar's hierarchy applies);
- the paper's-schedule bars (:func:`stnh_tf.paper.tables.schedule_results`).

    >>> hierarchy_rejections({"count": 10, "rejected": [{"outside_context": 1},
    ...                                                 {"outside_context": 2, "singular": 1}]})
    ({'STN-Homography 2 stages': 4}, {'STN-Homography 2 stages': 20})
"""

from __future__ import annotations

import json
import os

RESULTS = "results.json"
FIGURE = os.path.join("figures", "fig4_mace_bars.png")
ONE_STAGE = "STN-Homography 1 stage"


def hierarchy_rejections(model_evaluation: dict) -> tuple[dict, dict]:
    """``(rejected, predictions)`` of Fig. 4's k-stage rows (k >= 2) from a hierarchy's
    evaluation (``experiments.evaluate``'s ``model``: ``count`` pairs, ``rejected`` per stage):
    the stage predictions the degenerate-prediction rule replaced in stages 1..k, of
    ``k * count``; rows with none left out of ``rejected``."""
    per_stage = [sum(r.values()) for r in model_evaluation.get("rejected", [])]
    rejected, predictions = {}, {}
    for k in range(2, len(per_stage) + 1):
        name = f"STN-Homography {k} stages"
        predictions[name] = k * int(model_evaluation["count"])
        if sum(per_stage[:k]):
            rejected[name] = sum(per_stage[:k])
    return rejected, {k: predictions[k] for k in rejected}


def _card_rejections(results: dict, card_path: str):
    """:func:`hierarchy_rejections` of the card at ``card_path`` where its evaluation is the
    figure's hierarchy on the figure's pairs, else ``None``."""
    if not os.path.exists(card_path):
        return None
    with open(card_path) as f:
        evaluation = json.load(f).get("evaluation", {})
    fig4, model = results["fig4_mace"], evaluation.get("model", {})
    stages = model.get("stages", {})
    # the same pairs (the identity's MACE exactly) and the same stages: their MACE to 0.01 px, as
    # a re-measurement with another CPU's bfloat16 kernels may move it (on the same machine it
    # was the same to the last digit); two different hierarchies do not agree so closely
    same = [(evaluation.get("identity", {}).get("mace"), fig4["Identity"], 1e-6)] + [
        (stages.get(f"after_{k}_stages", {}).get("mace"), fig4.get(f"STN-Homography {k} stages"),
         0.01) for k in (2, 3)]
    if any(a is None or b is None or abs(a - b) > tol for a, b, tol in same):
        return None
    return hierarchy_rejections(model)


def fig4_inputs(reproduce_dir: str, weights_dir: str | None = None) -> dict:
    """The arguments of :func:`stnh_tf.paper.figures.mace_bars` for the reproduction in
    ``reproduce_dir`` (its ``results.json``), with ``marks_from`` (where the rejected counts come
    from: ``"results.json"``, a card's path, or ``None``: no marks).

    Args:
      reproduce_dir: a folder written by ``experiments.reproduce``.
      weights_dir: the package's ``stnh_tf/weights`` (default), holding ``paper_recipe`` and
        ``paper_schedule``.

    Raises:
      OSError, json.JSONDecodeError, KeyError: no readable ``results.json`` with ``fig4_mace``.
    """
    from stnh_tf.inference import model_files
    from stnh_tf.paper import tables

    with open(os.path.join(reproduce_dir, RESULTS)) as f:
        results = json.load(f)
    weights_dir = weights_dir or model_files.default_weights_dir()
    fig4 = results["fig4_mace"]
    if "fig4_rejected" in results:
        rejected, predictions = results["fig4_rejected"], results.get("fig4_rejected_of", {})
        marks_from = RESULTS
    else:
        card = os.path.join(weights_dir, "paper_recipe", "model_card.json")
        found = _card_rejections(results, card)
        rejected, predictions = found or ({}, {})
        marks_from = os.path.relpath(card) if found else None
    seeds = results.get("table1_mace_per_seed", {}).get("1,1", [])
    budget = results.get("budget", {}).get("name", "?")
    label = f"ours, budget '{budget}'" + (", assembled from several runs"
                                          if results.get("assembled") else "")
    schedule = tables.schedule_results(
        fig4["Identity"], os.path.join(weights_dir, model_files.PAPER_SCHEDULE_WEIGHTS))
    return {"results": fig4, "paper": results.get("paper", {}).get("fig4_mace"),
            "rejected": rejected, "predictions": predictions,
            "seeds": {ONE_STAGE: seeds} if len(seeds) > 1 else {},
            "schedule": schedule["fig4_mace"], "label": label,
            "seeds_label": "Table 1's 1:1 seeds (the network alone)",
            "title": f"MACE on the same {results.get('test_pairs', '?')} test pairs",
            "marks_from": marks_from}


def render(reproduce_dir: str, output: str | None = None, weights_dir: str | None = None) -> dict:
    """Draw Fig. 4 of ``reproduce_dir`` (:func:`fig4_inputs`) into ``output`` (default: its
    ``figures/fig4_mace_bars.png``, replaced); returns ``{"output", "marks_from", "label"}``."""
    from stnh_tf.paper import figures

    inputs = fig4_inputs(reproduce_dir, weights_dir)
    output = output or os.path.join(reproduce_dir, FIGURE)
    marks_from = inputs.pop("marks_from")
    os.makedirs(os.path.dirname(os.path.abspath(output)), exist_ok=True)
    figures.mace_bars(path=output, **inputs)
    return {"output": output, "marks_from": marks_from, "label": inputs["label"]}
