"""The project's result JSON that the docs' numbers come from: where each file is (``SOURCES``,
paths from the repository root), reading them and a value in them, and the form every number
takes in the docs. Used by :mod:`stnh_tf.paper.current_results` (the generated tables) and
``tests/test_docs_numbers.py`` (the numbers typed in prose). The standard library only.

    >>> sources = load_sources(default_root())  # doctest: +SKIP
    >>> fixed(value(sources, "table1", "1,1/mace"))  # doctest: +SKIP
    '5.83'
"""

from __future__ import annotations

import json
import os

NOT_RECORDED = "not recorded"
SOURCES = {
    "card": "stnh_tf/weights/model_card.json",
    "paper_card": "stnh_tf/weights/paper_recipe/model_card.json",
    "schedule_card": "stnh_tf/weights/paper_schedule/model_card.json",
    "schedule_record": "paper_schedule/stage1.json",
    "schedule_curve": "paper_schedule/stage1_curve.json",
    "schedule_train_photos": "paper_schedule/stage1_eval_train_photographs.json",
    "schedule_probe": "paper_schedule/logs/h200_steps_per_execution_probe.json",
    "schedule_probe_h100": "paper_schedule/logs/h100_steps_per_execution_probe.json",
    "schedule_ledger": "paper_schedule/ledger.json",
    "schedule_float32_inference": "paper_schedule/stage1_eval_float32_inference.json",
    "schedule2_eval": "paper_schedule/hierarchy2_eval.json",
    "schedule2_eval_float32": "paper_schedule/hierarchy2_eval_float32_inference.json",
    "schedule3_eval": "paper_schedule/hierarchy3_eval.json",
    "stage_pairs_before": "paper_schedule/logs/stage_pairs_benchmark_before_cpu.json",
    "stage_pairs_after": "paper_schedule/logs/stage_pairs_benchmark_after_cpu.json",
    "training_step_zen4": "paper_schedule/logs/training_step_benchmark_zen4_cpu.json",
    "device_calls_plain": "paper_schedule/logs/device_calls_plain.json",
    "device_calls_set_aside": "paper_schedule/logs/device_calls_set_aside.json",
    "device_calls_set_aside_1206": "paper_schedule/logs/device_calls_set_aside_2026-12-06.json",
    "camera0_default": "docs/camera_pairs/seed0_default.json",
    "camera0_default_estimator": "docs/camera_pairs/seed0_default_estimator.json",
    "camera0_photographs": "docs/camera_pairs/seed0_photographs.json",
    "camera1_photographs": "docs/camera_pairs/seed1_photographs.json",
    "camera0_features": "docs/camera_pairs/seed0_photographs_features.json",
    "camera1_features": "docs/camera_pairs/seed1_photographs_features.json",
    "camera1_wide_features": "docs/camera_pairs/wide_seed1_features.json",
    "camera0_wide_features": "docs/camera_pairs/wide_seed0_features.json",
    "camera2_wide_features": "docs/camera_pairs/wide_seed2_features.json",
    "camera0_speed": "docs/camera_pairs/speed_seed0_photographs.json",
    # issue 64: the whole-image refinement at one resolution (Thresholds.resolution_sigma)
    **{f"camera{s}_wide_resolution": f"docs/camera_pairs/wide_seed{s}_resolution.json"
       for s in (0, 1, 2, 3)},
    "camera3_wide_resolution_off": "docs/camera_pairs/wide_seed3_resolution_off.json",
    "camera0_resolution": "docs/camera_pairs/seed0_photographs_resolution.json",
    "camera1_resolution": "docs/camera_pairs/seed1_photographs_resolution.json",
    "camera0_speed_resolution": "docs/camera_pairs/speed_seed0_resolution.json",
    "camera0_speed_resolution_off": "docs/camera_pairs/speed_seed0_resolution_off.json",
    # issue 64: the verify move in image_b's pixels beyond the trained zoom
    **{f"camera{s}_wide_move": f"docs/camera_pairs/wide_seed{s}_move.json" for s in range(7)},
    **{f"camera{s}_wide_move_off": f"docs/camera_pairs/wide_seed{s}_move_off.json"
       for s in (4, 5, 6)},
    **{f"camera{s}_move": f"docs/camera_pairs/seed{s}_photographs_move.json" for s in (0, 1)},
    "camera0_speed_move": "docs/camera_pairs/speed_seed0_move.json",
    "camera0_speed_two_stages": "docs/camera_pairs/speed_seed0_two_stages.json",
    # issue 64: a verify move that the whole images bring back (Estimate.move_confirmed)
    **{f"camera{s}_wide_confirm": f"docs/camera_pairs/wide_seed{s}_confirm.json"
       for s in range(9)},
    **{f"camera{s}_wide_confirm_off": f"docs/camera_pairs/wide_seed{s}_confirm_off.json"
       for s in (7, 8)},
    **{f"camera{s}_confirm": f"docs/camera_pairs/seed{s}_photographs_confirm.json"
       for s in (0, 1)},
    # issue 64: the corner precision over 8 x 8 squares (Thresholds.corner_std_tile)
    **{f"camera{s}_wide_tiled": f"docs/camera_pairs/wide_seed{s}_tiled.json" for s in range(9)},
    **{f"camera{s}_tiled": f"docs/camera_pairs/seed{s}_photographs_tiled.json" for s in (0, 1)},
    # issue 64: fewer stages of the shipped hierarchy (the size groups of seed 0)
    **{f"camera0_{n}": f"docs/camera_pairs/seed0_photographs_{n}.json"
       for n in ("one_stage", "two_stages", "three_stages")},
    # issue 64: the feature start's network pass without the search
    **{f"camera{s}_wide_start": f"docs/camera_pairs/wide_seed{s}_start.json" for s in range(11)},
    **{f"camera{s}_wide_start_off": f"docs/camera_pairs/wide_seed{s}_start_off.json"
       for s in (9, 10)},
    **{f"camera{s}_start": f"docs/camera_pairs/seed{s}_photographs_start.json" for s in (0, 1)},
    # issue 64: the coarse pass out of photographs() (opt-in with coarse="rotations")
    **{f"camera{s}_wide_nocoarse": f"docs/camera_pairs/wide_seed{s}_nocoarse.json"
       for s in range(13)},
    **{f"camera{s}_wide_coarse": f"docs/camera_pairs/wide_seed{s}_coarse.json" for s in range(13)},
    **{f"camera{s}_nocoarse": f"docs/camera_pairs/seed{s}_photographs_nocoarse.json"
       for s in (0, 1, 2)},
    **{f"camera{s}_coarse": f"docs/camera_pairs/seed{s}_photographs_coarse.json"
       for s in (0, 1, 2)},
    # issue 64: features="always" against the default's "fallback"
    **{f"camera{s}_wide_always": f"docs/camera_pairs/wide_seed{s}_always.json" for s in (0, 12)},
    **{f"camera{s}_always": f"docs/camera_pairs/seed{s}_photographs_always.json" for s in (0, 2)},
    # issue 64: the late feature start (after: every method; before: the estimator alone)
    # (wide seeds 11-12 and size seed 1: the held-out check, every method both ways)
    **{f"camera{s}_wide_late": f"docs/camera_pairs/wide_seed{s}_late.json" for s in (0, 11, 12)},
    **{f"camera{s}_wide_nolate": f"docs/camera_pairs/wide_seed{s}_nolate.json"
       for s in (0, 11, 12)},
    **{f"camera{s}_late": f"docs/camera_pairs/seed{s}_photographs_late.json" for s in (0, 1, 2)},
    **{f"camera{s}_nolate": f"docs/camera_pairs/seed{s}_photographs_nolate.json"
       for s in (0, 1, 2)},
    # the baselines with their plausibility check at image_b's centre (c3ba783), on the pairs of
    # camera0_late, camera0_wide_late and camera0_paper
    "camera0_paper": "docs/camera_pairs/paper_seed0.json",
    # the "Current results" tables' camera pairs: every method at a99ebf6 (the tile-by-tile
    # ambiguity flag, the baselines' check at image_b's centre)
    "camera0_current": "docs/camera_pairs/seed0_photographs_a99ebf6.json",
    "camera0_wide_current": "docs/camera_pairs/wide_seed0_a99ebf6.json",
    "camera0_baselines_fixed": "docs/camera_pairs/seed0_photographs_baselines_fixed.json",
    "camera0_wide_baselines_fixed": "docs/camera_pairs/wide_seed0_baselines_fixed.json",
    "camera0_paper_baselines_fixed": "docs/camera_pairs/paper_seed0_baselines_fixed.json",
    "readme_example": "docs/readme_example.json",
    "semi_all_seed0": "semi_supervised/eval/stage1_alone.json",
    "semi_labeled_alone_seed0": "semi_supervised/eval/semi_labels-0.1_drop.json",
    "semi_plus_unlabeled_seed0": "semi_supervised/eval/semi_labels-0.1.json",
    "semi_none_seed0": "semi_supervised/eval/semi_labels-0.json",
    "semi_labeled_alone_seed1": "semi_supervised/eval/semi_labels-0.1_drop_seed1.json",
    "semi_all_seed1": "semi_supervised/eval/ablation_l2-1_l1-1_seed1.json",
    "semi_plus_unlabeled_seed1": "semi_supervised/eval/semi_labels-0.1_seed1.json",
    "semi_none_seed1": "semi_supervised/eval/semi_labels-0_seed1.json",
    "semi_plus_unlabeled_l1b_seed0": "semi_supervised/eval/semi_labels-0.1_l1b.json",
    "semi_none_l1b_seed0": "semi_supervised/eval/semi_labels-0_l1b.json",
    "semi_table": "semi_supervised/semi_supervised.json",
    "semi_table_l1b": "semi_supervised/semi_supervised_l1b.json",
    "semi_plus_unlabeled_l1b_seed1": "semi_supervised/eval/semi_labels-0.1_l1b_seed1.json",
    "semi_none_l1b_seed1": "semi_supervised/eval/semi_labels-0_l1b_seed1.json",
    "semi_step_cost": "semi_supervised/step_cost.json",
    "semi_step_cost_l1b": "semi_supervised/step_cost_l1b.json",
    "schedule1_eval_se": "paper_schedule/stage1_eval_se.json",
    "schedule1_eval_ci": "paper_schedule/stage1_eval_ci.json",
    "results": "docs/reproduce_cpu/results.json",
    "table1": "docs/reproduce_cpu/table1.json",
    # the reproduction's own files: Table 2's terms, the hierarchy's evaluation (its clipping)
    "reproduce_latency": "docs/reproduce_cpu/eval/latency.json",
    "reproduce_hierarchy": "docs/reproduce_cpu/eval/hierarchy.json",
}
PAPER_STEPS = 3 * 90_000  # the paper's hierarchy: 90,000 steps for each of 3 stages


def default_root() -> str:
    """The repository root: the folder above ``stnh_tf/`` (the checkout of an editable install,
    where ``experiments/`` and the docs are)."""
    return os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def load_sources(root: str) -> dict[str, dict]:
    """Read every JSON file of ``SOURCES``.

    Args:
        root: the repository root.

    Returns:
        ``{name: parsed JSON}`` for each name of ``SOURCES``.

    Raises:
        OSError: a file is missing or unreadable.
        json.JSONDecodeError: a file is not JSON.
    """
    out = {}
    for name, rel in SOURCES.items():
        with open(os.path.join(root, rel)) as f:
            out[name] = json.load(f)
    return out


def value(sources: dict[str, dict], name: str, path: str):
    """The value at ``path`` of source ``name``.

    Args:
        sources: as returned by :func:`load_sources`.
        name: a key of ``SOURCES``.
        path: keys separated by ``/`` (a key may hold dots or commas, e.g. ``table1_mace/0.1,1``);
            an integer key indexes a list.

    Returns:
        The JSON value found there.

    Raises:
        KeyError: naming the source and the path, where the path leads nowhere.
    """
    node = sources[name]
    for key in path.split("/"):
        try:
            node = node[int(key)] if isinstance(node, list) else node[key]
        except (KeyError, IndexError, ValueError, TypeError):
            raise KeyError(f"{SOURCES[name]}: no {path!r}") from None
    return node


def fixed(x: float, digits: int = 2) -> str:
    """``x`` with ``digits`` decimals, the form every generated number takes (``0.795`` -> 0.79)."""
    return f"{x:.{digits}f}"


def percent(x: float) -> str:
    """A fraction as a percentage with at most one decimal (``0.0233`` -> 2.3%, ``1.0`` -> 100%)."""
    return f"{100 * x:.1f}".rstrip("0").rstrip(".") + "%"


def card_steps(sources: dict[str, dict], name: str = "card") -> list[int]:
    """Training steps of each stage of a model card, in stage order.

    A stage trained on from earlier weights records the earlier run as ``init_from_run`` (a
    chain); its steps are the sum of ``result.final_step`` over the chain.

    Raises:
        KeyError: the card has no ``stages`` or a run no ``result.final_step``.
    """
    steps = []
    for stage in value(sources, name, "stages"):
        total, run = 0, stage
        while run:
            total += run["result"]["final_step"]
            run = run.get("init_from_run")
        steps.append(total)
    return steps

