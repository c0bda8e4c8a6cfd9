"""experiments.render_fig4 (stnh_tf.paper.fig4_render) and Fig. 4's bars (stnh_tf.paper.figures):
the marks of the degenerate-prediction rule taken from a card only where its evaluation is the
figure's hierarchy on the figure's pairs, the seeds as dots, the paper's-schedule bars, and what
the drawn figure holds (its artists), all against values written here."""

import json
import os

import numpy as np
import pytest

from stnh_tf.paper import figures, fig4_render

FIG4 = {"Identity": 24.0, "STN-Homography 1 stage": 18.0, "STN-Homography 2 stages": 9.0,
        "STN-Homography 3 stages": 6.0}
PER_STAGE = [{"non_finite": 0, "outside_context": 6, "singular": 0},
             {"non_finite": 1, "outside_context": 22, "singular": 0},
             {"non_finite": 0, "outside_context": 16, "singular": 2}]


def _write(path, doc):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        json.dump(doc, f)


def _setup(tmp_path, card_mace_2=9.0, rejected_in_results=None):
    results = {"fig4_mace": FIG4, "assembled": True, "budget": {"name": "cpu"},
               "test_pairs": 300, "paper": {"fig4_mace": {"STN-Homography 1 stage": 5.83}},
               "table1_mace_per_seed": {"1,1": [18.3, 17.7, 18.1]}}
    if rejected_in_results is not None:
        results["fig4_rejected"] = rejected_in_results
    _write(str(tmp_path / "repro" / "results.json"), results)
    stages = {f"after_{k}_stages": {"mace": v} for k, v in ((1, 18.0), (2, card_mace_2), (3, 6.0))}
    _write(str(tmp_path / "weights" / "paper_recipe" / "model_card.json"),
           {"evaluation": {"identity": {"mace": 24.0},
                           "model": {"count": 300, "rejected": PER_STAGE, "stages": stages}}})
    return str(tmp_path / "repro"), str(tmp_path / "weights")


def test_marks_from_the_card_that_measured_the_same_hierarchy(tmp_path):
    repro, weights = _setup(tmp_path)
    inputs = fig4_render.fig4_inputs(repro, weights)
    # stages 1..k summed: 6 + 23 = 29 of 600, 29 + 18 = 47 of 900
    assert inputs["rejected"] == {"STN-Homography 2 stages": 29, "STN-Homography 3 stages": 47}
    assert inputs["predictions"] == {"STN-Homography 2 stages": 600,
                                     "STN-Homography 3 stages": 900}
    assert inputs["marks_from"].endswith(os.path.join("paper_recipe", "model_card.json"))
    assert inputs["seeds"] == {"STN-Homography 1 stage": [18.3, 17.7, 18.1]}
    assert inputs["label"] == "ours, budget 'cpu', assembled from several runs"
    assert inputs["schedule"] == {}  # no paper_schedule card in this weights folder


def test_the_committed_figure_has_its_marks():
    """docs/reproduce_cpu's Fig. 4 takes its marks from the paper recipe's card (README says so)."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    inputs = fig4_render.fig4_inputs(os.path.join(root, "docs", "reproduce_cpu"),
                                     os.path.join(root, "stnh_tf", "weights"))
    assert inputs["marks_from"] is not None
    assert inputs["rejected"] == {"STN-Homography 2 stages": 28, "STN-Homography 3 stages": 44}


def test_no_marks_from_a_card_of_other_numbers_and_results_marks_first(tmp_path):
    repro, weights = _setup(tmp_path, card_mace_2=9.02)  # 0.02 px: another hierarchy
    inputs = fig4_render.fig4_inputs(repro, weights)
    assert inputs["rejected"] == {} and inputs["marks_from"] is None
    repro, weights = _setup(tmp_path / "b", rejected_in_results={"STN-Homography 3 stages": 5})
    inputs = fig4_render.fig4_inputs(repro, weights)
    assert inputs["rejected"] == {"STN-Homography 3 stages": 5}
    assert inputs["marks_from"] == "results.json"


def test_drawn_figure_holds_the_bars_dots_and_hatches():
    bars = figures.fig4_bars(FIG4, paper={"STN-Homography 1 stage": 5.83},
                             rejected={"STN-Homography 2 stages": 29},
                             predictions={"STN-Homography 2 stages": 600},
                             seeds={"STN-Homography 1 stage": [18.3, 17.7]},
                             schedule={"STN-Homography 1 stage": 6.84})
    fig = figures.mace_bars_figure(bars, label="ours")
    try:
        ax = fig.axes[0]
        heights = [(c.get_label(), [round(p.get_height(), 2) for p in c])
                   for c in ax.containers]
        assert heights[0] == ("ours", [24.0, 18.0, 9.0, 6.0])
        assert heights[1][0] == "ours, the paper's schedule"
        assert heights[1][1][1] == 6.84 and np.isnan(heights[1][1][0])
        assert heights[2][0] == "paper" and heights[2][1][1] == 5.83
        assert [p.get_hatch() or "" for p in ax.containers[0]] == ["", "", "//", ""]
        (dots,) = ax.collections
        offsets = dots.get_offsets()
        assert sorted(offsets[:, 1].tolist()) == [17.7, 18.3]
        # on the 1-stage method's own bar: its x is that bar's centre
        ours_1 = ax.containers[0][1]
        assert offsets[:, 0].tolist() == pytest.approx([ours_1.get_x() + ours_1.get_width() / 2] * 2)
    finally:
        figures._pyplot().close(fig)


def test_render_writes_the_png(tmp_path):
    repro, weights = _setup(tmp_path)
    out = fig4_render.render(repro, weights_dir=weights)
    assert out["output"] == os.path.join(repro, "figures", "fig4_mace_bars.png")
    with open(out["output"], "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
