r"""The "current results" tables of BENCHMARKS.md and README.md, generated from the project's JSON
(library core of ``experiments.current_results``: :func:`run` prints, rewrites or checks them).

Each of the two files holds one block between ``<!-- current-results:start -->`` and
``<!-- current-results:end -->``; only the text between the markers is generated, the rest of the
file is left as it is. The numbers come from the JSON the project already writes (``SOURCES``,
paths from the repository root):

- ``stnh_tf/weights/model_card.json``: the shipped default (``experiments.ship_weights``: its
  ``evaluation`` from ``experiments.evaluate`` and ``experiments.check_implausible``, its
  ``bundled_check`` and each stage's training configuration);
- ``stnh_tf/weights/paper_recipe/model_card.json``: the paper recipe's CPU-budget hierarchy;
- ``docs/reproduce_cpu/results.json`` and ``docs/reproduce_cpu/table1.json``:
  ``experiments.reproduce --budget=cpu`` (Fig. 4, Table 1, Table 2);
- ``docs/camera_pairs/seed0_photographs_a99ebf6.json`` and ``wide_seed0_a99ebf6.json``:
  ``experiments.benchmark_camera_pairs`` (``estimate_images``' default beside SIFT, ORB and the
  identity on every group of the camera-pair benchmark,
  :data:`stnh_tf.paper.result_cells.CAMERA_SETS`).

The commands are those BENCHMARKS.md records for each measurement; a commit or machine is shown
where the JSON records one, "not recorded" where it does not; the reproduction's rows show where
its models were trained (``model_provenance``:
:func:`stnh_tf.paper.result_cells.provenance_cells`). Numbers typed in prose elsewhere
are checked against the same JSON by ``tests/test_docs_numbers.py``, which calls
:func:`differing` and :func:`value`. The standard library only: no TensorFlow.

    >>> run("check")  # doctest: +SKIP
    0
"""

from __future__ import annotations

import difflib
import json
import math
import os
import sys

from stnh_tf.paths import atomic_write_text, document_text, read_document
from stnh_tf.paper.result_cells import (FIG4_MODELS, TABLE1_ROWS, camera_rows, joined,
                                        latency_cells, latency_command, latency_machine,
                                        provenance_cells, recorded, stage_paths, table1_cells)
from stnh_tf.paper.results_json import (NOT_RECORDED, PAPER_STEPS, SOURCES,  # noqa: F401
                                        card_steps, default_root, fixed, load_sources, percent,
                                        value)

START = "<!-- current-results:start -->"
END = "<!-- current-results:end -->"
# The identity's expected MACE under the paper's protocol (docs/conventions.md): the mean length
# of a uniform offset in [-32, 32]^2.
IDENTITY_EXPECTED = 32 * (math.sqrt(2) + math.asinh(1)) / 3
_DEFAULT_EVAL = "evaluation/plain_coco_mini_test/model"


def benchmarks_rows(sources: dict[str, dict]) -> list[tuple[str, str, str, str, str, str]]:
    """The rows of BENCHMARKS.md's "Current results" table.

    Args:
        sources: as returned by :func:`load_sources`.

    Returns:
        One ``(what, result, command, source, commit, machine)`` tuple of markdown cells per row.

    Raises:
        KeyError: a JSON lacks a field the table shows.
    """
    card, paper_card, schedule_card = (f"`{SOURCES[k]}`"
                                       for k in ("card", "paper_card", "schedule_card"))
    shipped = len(value(sources, "schedule_card", "stages"))  # the paper schedule's stages shipped
    ks = range(1, shipped + 1)

    def card_num(path, digits=2):
        return fixed(value(sources, "card", path), digits)

    def check(prefix, stages="3"):
        return [f"bundled_check/{prefix}estimate_mace_{k}_stages" for k in stages]

    plain, photo = _DEFAULT_EVAL, "evaluation/photometric_coco_mini_test/model"
    flag = "evaluation/implausibility_coco_mini_test"
    flag_photo = "evaluation/implausibility_coco_mini_test_photometric"
    beyond = [value(sources, "card", f"{flag}/{kind}/flagged")
              for kind in ("other_photograph", "rotated_180", "moved_80px")]
    steps = card_steps(sources)
    training = value(sources, "card", "evaluation/training")
    machines = sorted({training[f"stage{k}"]["machine"] for k in (1, 2, 3)})
    fig4 = {label: fixed(value(sources, "results", f"fig4_mace/{label}"))
            for label in value(sources, "results", "fig4_mace")}
    table1, table1_note, _ = table1_cells(sources)
    # Re-measures every entry of a card's evaluation (stnh_tf.evaluation.card_evaluation).
    refresh = ("`python -m experiments.ship_weights --refresh_evaluation "
               "--test_image_dir=../shared/data/coco_mini/test{}`")
    evaluate = refresh.format("") + (" (each entry: `python -m experiments.evaluate "
                                     "--model_dir=M1,M2,M3 --data_dir=D --split=test "
                                     "--compute_dtype=float32 [--no_clip]`)")
    reproduce = "`python -m experiments.reproduce --budget=cpu ...` ([how](docs/reproduce.md))"
    results, table1_json = f"`{SOURCES['results']}`", f"`{SOURCES['table1']}`"
    return [
        ("[Shipped default](#shipped-weights-the-default) (fast recipe, 3-stage hierarchy): "
         "300 coco_mini test pairs, image context between stages",
         f"MACE after 1 / 2 / 3 stages {joined(sources, 'card', stage_paths(plain), bold=2)} px "
         f"({card_num('evaluation/plain_coco_mini_test_no_clip/model/mace', 3)} without the "
         "clipping rule)", evaluate, card,
         *recorded(sources, "card", os.path.dirname(plain) + "/machine")),
        ("Shipped default, the same pairs with a photometric change of patch_b",
         f"{joined(sources, 'card', stage_paths(photo), bold=2)} px "
         f"({value(sources, 'card', photo + '/worse_than_identity')} of 300 worse than the "
         "identity)", evaluate, card,
         *recorded(sources, "card", os.path.dirname(photo) + "/machine")),
        ("Shipped default, `estimate` on bare 128x128 patches (default search), the card's 60 "
         "bundled pairs",
         f"{joined(sources, 'card', check('', '123'))} px after 1 / 2 / 3 stages, "
         f"photometric {joined(sources, 'card', check('photometric_', '123'))}; after 3 stages "
         "the network alone (`search=\"none\"`) "
         f"{card_num('bundled_check/unsearched_estimate_mace_3_stages')} (photometric "
         f"{card_num('bundled_check/photometric_unsearched_estimate_mace_3_stages')}); "
         f"with `tta=\"dihedral\"` {card_num('bundled_check/tta_estimate_mace_3_stages')}",
         "`python -m experiments.ship_weights --refresh_check`", card, *recorded(sources, "card")),
        ("Shipped default, `estimate` on bare patches without the search, 300 coco_mini test "
         "pairs; the implausibility flag",
         f"MACE {card_num(flag + '/ordinary/mace')} (photometric "
         f"{card_num(flag_photo + '/ordinary/mace')}); flagged "
         f"{percent(value(sources, 'card', flag + '/ordinary/flagged'))} of ordinary pairs (their "
         f"MACE {card_num(flag + '/ordinary/mace_flagged')} against "
         f"{card_num(flag + '/ordinary/mace_kept')}), "
         f"{percent(min(beyond))[:-1]}-{percent(max(beyond))} of pairs beyond the trained range",
         refresh.format("") + " (each entry: `python -m experiments.check_implausible "
         "--model=stnh_tf/weights --data_dir=D --search=none`)", card,
         *recorded(sources, "card", flag + "/machine")),
        ("Shipped default, training (the last run of each stage; flags in the card)",
         f"{' / '.join(f'{s:,}' for s in steps)} steps for stages 1 / 2 / 3, {sum(steps):,} in "
         f"all ({sum(steps) / PAPER_STEPS:.0%} of the paper's 3 x 90,000)",
         "`python -m experiments.train_stage --recipe=fast ... --init_from=...`, then "
         "`python -m experiments.ship_weights --replace_stage=K ...`", card,
         "; ".join(f"stage {k}: {training[f'stage{k}']['code_commit']}" for k in (1, 2, 3)),
         "; ".join(machines)),
        ("Paper recipe's CPU-budget hierarchy (`stnh_tf/weights/paper_recipe/`): 300 coco_mini "
         "test pairs, image context",
         "MACE after 1 / 2 / 3 stages "
         f"{joined(sources, 'paper_card', stage_paths('evaluation/model'), bold=2)} px",
         refresh.format(" --weights_dir=stnh_tf/weights/paper_recipe"), paper_card,
         *recorded(sources, "paper_card", "evaluation/machine")),
        (f"[Paper's schedule](docs/gpu.md#the-papers-schedule-in-chunks), stages 1-{shipped} "
         "(`stnh_tf/weights/paper_schedule/`): the paper's recipe, 91,000 steps a stage, 184,800 "
         "pairs from 1,848 photographs; 300 coco_mini test pairs, image context, the networks "
         "alone (no clipping rule)",
         f"MACE after {' / '.join(map(str, ks))} stages "
         f"{joined(sources, 'schedule_card', stage_paths('evaluation/model')[:shipped], bold=shipped - 1)}"
         f" px (paper {' / '.join(['5.83', '2.6', '1.57'][:shipped])}; identity "
         f"{fixed(value(sources, 'schedule_card', 'evaluation/identity/mace'))})",
         f"`python -m experiments.paper_schedule --stage=K` (chunks, K = {', '.join(map(str, ks))}),"
         " then `python -m experiments.evaluate --model_dir="
         + ",".join(f"paper_schedule/stage{k}.keras" for k in ks)
         + " --data_dir=D --split=test --no_clip`", schedule_card,
         recorded(sources, "schedule_card", "evaluation/machine")[0],
         "; ".join(dict.fromkeys(m for stage in value(sources, "schedule_card", "stages")
                                 for m in stage["machines"]))),
        ("Paper recipe's hierarchy, `estimate` on bare patches (default search), 60 bundled pairs",
         f"{joined(sources, 'paper_card', check('', '123'))} px after 1 / 2 / 3 "
         "stages; after 3 stages the network alone "
         f"{joined(sources, 'paper_card', check('unsearched_'))}, photometric "
         f"{joined(sources, 'paper_card', check('photometric_'))} (network alone "
         f"{joined(sources, 'paper_card', check('photometric_unsearched_'))}; "
         f"{value(sources, 'paper_card', 'bundled_check/photometric_worse_than_identity_3_stages')}"
         " of 60 worse than the identity with the search)",
         "`python -m experiments.ship_weights --refresh_check "
         "--weights_dir=stnh_tf/weights/paper_recipe`", paper_card,
         *recorded(sources, "paper_card")),
        ("Reproduction at the CPU budget, Fig. 4: 300 coco_mini test pairs, every network "
         "trained 4,000 steps",
         f"identity {fig4['Identity']}, HomographyNet {fig4['HomographyNet']} "
         f"(`homographynet_gap` {fig4['HomographyNet variant (GAP)']}), STN-Homography 1 / 2 / 3 "
         f"stages {fig4['STN-Homography 1 stage']} / {fig4['STN-Homography 2 stages']} / "
         f"{fig4['STN-Homography 3 stages']}, sequence (2 stages) {fig4['Sequence 2 stages']}, "
         f"ORB + RANSAC {fig4['ORB + RANSAC']}, SIFT + RANSAC {fig4['SIFT + RANSAC']} px",
         reproduce, results, *provenance_cells(sources, "results", FIG4_MODELS)),
        ("Reproduction, Table 1: loss weights L2:L1 = "
         + " / ".join(label for _, label in TABLE1_ROWS), f"{table1} px{table1_note}", reproduce,
         table1_json, *provenance_cells(sources, "table1")),
        ("Reproduction, Table 2: batch-1 latency of 1 / 2 / 3 stages, mixed bfloat16",
         f"hierarchy {joined(sources, 'results', [f'table2_latency_ms/{k}' for k in (1, 2, 3)])}"
         f" ms, sequence model "
         f"{joined(sources, 'results', [f'sequence_latency_ms/{k}' for k in (1, 2, 3)])} ms, "
         f"on {latency_machine(sources)} "
         "([Table 2](#the-papers-table-2-hierarchy-latency-batch-1): not below the paper's GPU on "
         "other 2-core CPUs)",
         latency_command(sources, reproduce), results, *latency_cells(sources)),
        *camera_rows(sources),
    ]


def benchmarks_block(sources: dict[str, dict]) -> str:
    """BENCHMARKS.md's "Current results" table (markdown, ends with a newline)."""
    lines = ["| what | result | command | JSON | commit | machine |", "|---|---|---|---|---|---|"]
    lines += ["| " + " | ".join(row) + " |" for row in benchmarks_rows(sources)]
    return "\n".join(lines) + "\n"


def readme_block(sources: dict[str, dict]) -> str:
    """README.md's results table: ours beside the paper's (markdown, ends with a newline).

    Args:
        sources: as returned by :func:`load_sources`.

    Returns:
        The table: the reproduction's Fig. 4 methods, Table 1 and Table 2, then the shipped
        default.

    Raises:
        KeyError: a JSON lacks a field the table shows.
    """
    fig4, paper = "fig4_mace", "paper/fig4_mace"

    def ours(key):
        return fixed(value(sources, "results", f"{fig4}/{key}"))

    def theirs(key):
        return f"{value(sources, 'results', f'{paper}/{key}'):g}"

    table1, table1_note, paper_table1 = table1_cells(sources)
    stn = ["STN-Homography 1 stage", "STN-Homography 2 stages", "STN-Homography 3 stages"]
    steps = sum(card_steps(sources))
    next_ = "not yet"  # trained next, in the order of issue 60 (docs/gpu.md)
    shipped = value(sources, "schedule_card", "evaluation/model/stages")
    schedule = {k: fixed(shipped[f"after_{k}_stages"]["mace"]) if f"after_{k}_stages" in shipped
                else next_ for k in (1, 2, 3)}
    rows = [
        ("identity", ours("Identity"),
         fixed(value(sources, "schedule_card", "evaluation/identity/mace")),
         f"{IDENTITY_EXPECTED:.2f} (expected)"),
        ("HomographyNet (DeTone et al.'s network and step schedule)", ours("HomographyNet"), "-",
         theirs("HomographyNet")),
        ("HomographyNet's 4-point regression on our backbone (`homographynet_gap`, paper's "
         "recipe)", ours("HomographyNet variant (GAP)"), "-", "-"),
        ("STN-Homography, 1 stage", ours(stn[0]), schedule[1], theirs(stn[0])),
        ("hierarchy, 2 stages", ours(stn[1]), schedule[2], theirs(stn[1])),
        ("hierarchy, 3 stages", ours(stn[2]), schedule[3], theirs(stn[2])),
        ("sequence model, 2 stages", ours("Sequence 2 stages"), next_,
         theirs("Sequence 2 stages")),
        ("ORB + RANSAC (tuned on train photographs)", ours("ORB + RANSAC"), "-", "-"),
        ("SIFT + RANSAC (tuned on train photographs)", ours("SIFT + RANSAC"), "-", "-"),
        ("Table 1, loss weights L2:L1 = " + " / ".join(label for _, label in TABLE1_ROWS),
         table1 + table1_note, f"{schedule[1]} / - / - / {next_} / -", paper_table1),
        ("Table 2, batch-1 latency of 1 / 2 / 3 stages in ms (ours: mixed bfloat16 on "
         f"{latency_machine(sources)}; the paper: its GPU)",
         joined(sources, "results", [f"table2_latency_ms/{k}" for k in (1, 2, 3)]), "-",
         " / ".join(f"{value(sources, 'results', f'paper/table2_gpu_ms/{k}'):g}"
                    for k in (1, 2, 3))),
        (f"**shipped default** (not the CPU budget: the fast recipe, a deviation, {steps:,} "
         f"steps in all, {steps / PAPER_STEPS:.0%} of the paper's), after 1 / 2 / 3 stages",
         joined(sources, "card", stage_paths(_DEFAULT_EVAL), bold=2), "-",
         " / ".join(theirs(key) for key in stn)),
        ("shipped default, 3 stages, photometric change of patch_b",
         fixed(value(sources, "card", "evaluation/photometric_coco_mini_test/model/mace")), "-",
         "-"),
    ]
    lines = ["| method | MACE (px), CPU budget | paper's schedule | paper (full budget) |",
             "|---|---|---|---|"]
    lines += [f"| {a} | {b} | {c} | {d} |" for a, b, c, d in rows]
    return "\n".join(lines) + "\n"


def render(sources: dict[str, dict]) -> dict[str, str]:
    """``{file name relative to the root: its generated block}`` for BENCHMARKS.md and README.md."""
    return {"BENCHMARKS.md": benchmarks_block(sources), "README.md": readme_block(sources)}


def replace_block(text: str, block: str, name: str = "") -> str:
    """``text`` with what lies between the markers replaced by ``block``.

    Args:
        text: a markdown file's content holding ``START`` and ``END`` once each, in that order.
        block: the new content (ends with a newline).
        name: the file's name, for the error message.

    Returns:
        The new content; equal to ``text`` where the block is already ``block``.

    Raises:
        ValueError: the markers are missing, repeated or out of order.
    """
    if text.count(START) != 1 or text.count(END) != 1 or text.index(START) > text.index(END):
        raise ValueError(f"{name or 'text'}: needs {START} and {END} once each, in that order")
    head, rest = text.split(START)
    _, tail = rest.split(END)
    return f"{head}{START}\n{block}{END}{tail}"


def differing(root: str) -> dict[str, str]:
    """The files whose generated block differs from what the JSON gives, with the difference.

    Args:
        root: the repository root.

    Returns:
        ``{file name relative to root: unified diff of its block, current -> generated}``; empty
        where every block is current.

    Raises:
        ValueError: a file's markers are missing (see :func:`replace_block`).
        KeyError, OSError, json.JSONDecodeError: as :func:`load_sources` and :func:`value`.
    """
    out = {}
    for name, block in render(load_sources(root)).items():
        text, _ = read_document(os.path.join(root, name))  # (CRLF or LF, compared as LF)
        new = replace_block(text, block, name)
        if new != text:
            out[name] = "".join(difflib.unified_diff(
                text.splitlines(keepends=True), new.splitlines(keepends=True),
                f"{name} (now)", f"{name} (from the JSON)", n=0))
    return out


def write(root: str) -> list[str]:
    """Rewrite the generated blocks under ``root``; returns the names of the files changed."""
    changed = []
    for name, block in render(load_sources(root)).items():
        path = os.path.join(root, name)
        text, newline = read_document(path)  # (written back with its own line ends)
        new = replace_block(text, block, name)
        if new != text:
            atomic_write_text(path, document_text(new, newline))
            changed.append(name)
    return changed


ACTIONS = ("print", "write", "check")


def run(action: str = "print", root: str | None = None, out=None, err=None) -> int:
    """Print both generated blocks, rewrite them, or check them (``experiments.current_results``).

    Args:
        action: one of :data:`ACTIONS`: ``"print"`` each block to ``out``; ``"write"`` the blocks
            that differ into their files, printing ``{"rewritten": [file names]}``; ``"check"``,
            printing to ``err`` each file whose block differs from the JSON, with the difference.
        root: the repository root (default: :func:`default_root`).
        out, err: text streams (default: ``sys.stdout``, ``sys.stderr``).

    Returns:
        The exit status: 1 where ``"check"`` finds a block that differs or a file without its
        markers, else 0.

    Raises:
        ValueError: ``action`` is not one of :data:`ACTIONS`; a file's markers are missing
            (``"print"``, ``"write"``: see :func:`replace_block`).
        KeyError, OSError, json.JSONDecodeError: as :func:`load_sources` and :func:`value`.
    """
    if action not in ACTIONS:
        raise ValueError(f"action must be one of {ACTIONS}; received {action!r}.")
    out, err = out or sys.stdout, err or sys.stderr
    root = root or default_root()
    if action == "check":
        try:
            stale = differing(root)
        except ValueError as e:  # a file without its markers
            print(e, file=err)
            return 1
        for name, diff in stale.items():
            print(f"{name}: the block between {START} and {END} differs from the JSON "
                  f"(python -m experiments.current_results --write rewrites it):\n{diff}",
                  file=err)
        return 1 if stale else 0
    if action == "write":
        print(json.dumps({"rewritten": write(root)}), file=out)
        return 0
    for name, block in render(load_sources(root)).items():
        print(f"{name}:\n{block}", file=out)
    return 0
