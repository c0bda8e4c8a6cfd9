"""The docs' headline numbers agree with the JSON that records them (standard library only, fast).

Two kinds of number: the generated tables of BENCHMARKS.md and README.md (between the markers of
``experiments.current_results``, rewritten by ``python -m experiments.current_results --write``),
and numbers typed in prose, each listed in ``PROSE`` with the JSON value it must equal. A doc
that is reworded so that a listed phrase no longer matches fails too: update ``PROSE`` with it.
"""

from __future__ import annotations

import io
import json
import os
import re
import shutil

from stnh_tf.paper import current_results as cr
from stnh_tf.paper import result_cells

ROOT = cr.default_root()
N = r"([\d.]+)"  # one number in a phrase
S = r"\s+"  # a space or a line break


def num(source, path, digits=2):
    """Expected text of the number at ``path`` of ``source`` (see ``current_results.SOURCES``)."""
    return lambda sources: cr.fixed(cr.value(sources, source, path), digits)


def difference(a, b, digits=2):
    """Expected text of the number at ``a`` minus the one at ``b`` (each ``(source, path)``)."""
    return lambda sources: cr.fixed(cr.value(sources, *a) - cr.value(sources, *b), digits)


def ratio(a, b, digits=2):
    """Expected text of the number at ``a`` over the one at ``b`` (each ``(source, path)``)."""
    return lambda sources: cr.fixed(cr.value(sources, *a) / cr.value(sources, *b), digits)


def length(source, path):
    """Expected text of the length of the list at ``path`` of ``source``."""
    return lambda sources: str(len(cr.value(sources, source, path)))


def count(source, path):
    return lambda sources: str(cr.value(sources, source, path))


def percent(source, path):
    return lambda sources: cr.percent(cr.value(sources, source, path))[:-1]


CARD_3 = "evaluation/plain_coco_mini_test/model/stages/after_3_stages/mace"
CARD_STAGES = [num("card", f"evaluation/plain_coco_mini_test/model/stages/after_{k}_stages/mace")
               for k in (1, 2, 3)]
PHOTO = "evaluation/photometric_coco_mini_test/model"
NO_CLIP = "evaluation/plain_coco_mini_test_no_clip/model/mace"
FLAG = "evaluation/implausibility_coco_mini_test/ordinary"
FLAG_PHOTO = "evaluation/implausibility_coco_mini_test_photometric/ordinary"
CHECK = "bundled_check"
PAPER_STAGES = [num("paper_card", f"evaluation/model/stages/after_{k}_stages/mace")
                for k in (1, 2, 3)]


def check(prefix, k, source="card"):
    return num(source, f"{CHECK}/{prefix}estimate_mace_{k}_stages")


def fig4(label):
    return num("results", f"fig4_mace/{label}")


def total_steps(sources):
    return f"{sum(cr.card_steps(sources)):,}"


def share_of_paper(sources):
    return f"{sum(cr.card_steps(sources)) / cr.PAPER_STEPS:.0%}"[:-1]


def curve(step):
    """The validation MACE of the paper schedule's stage 1 at ``step`` (one point per 500)."""
    return num("schedule_curve", f"curve/{step // 500 - 1}/val_h_bar_mace")


def cam(source, group, method, field, digits=2):
    """A number of a camera-pairs benchmark (docs/camera_pairs/): ``field`` of ``method`` in
    ``group``; ``ok``: the count of successes, ``count``: of pairs, ``flag:K``: key K of the
    flag detector, ``good``: the pairs not more than 5 px off."""
    def get(sources):
        e = cr.value(sources, source, f"groups/{group}/{method}")
        if field == "ok":
            return str(round(e["success_rate"] * e["count"]))
        if field == "good":
            return str(e["count"] - e["flag"]["bad"])
        if field == "count":
            return str(e["count"])
        if field.startswith("flag:"):
            return str(e["flag"][field[5:]])
        if field == "ms":
            return f"{e['ms_per_pair']:.0f}"
        return cr.fixed(e[field], digits)
    return get


def cam_row(source, method="estimator", flag=True):
    """The cells of a row of docs/estimate.md's photographs table."""
    cells = [cam(source, "within", method, "mace"), cam(source, "within", method, "median"),
             cam(source, "within", method, "ok"), cam(source, "1-2x", method, "ok"),
             cam(source, "2-4x", method, "ok")]
    if flag:
        cells += [cam(source, "all", method, "flag:flagged_bad"), cam(source, "all", method,
                                                                      "flag:bad"),
                  cam(source, "all", method, "flag:flagged_good"),
                  cam(source, "all", method, "good")]
    return cells


def wide_rows(seed, label=""):
    """The two rows (wide, wide_low_light) of a wide-baseline table of BENCHMARKS.md (first cell
    ``seed N`` and ``label``)."""
    method = rf"(\d+) of \d+, {N} px, (\d+) ms"
    first = rf"seed {seed}{re.escape(label)}"
    return (rf"\| {first} \| wide \| (\d+) of (\d+), {N} px, (\d+) ms \| {method} \| "
            rf"{method} \| {method} \| (\d+) of \d+, {N} px \| (\d+) of (\d+), (\d+) of (\d+) \|\n"
            rf"\| {first} \| wide_low_light \| (\d+) of (\d+), {N} px, (\d+) ms \| {method} \| "
            rf"{method} \| {method} \| (\d+) of \d+, {N} px \| (\d+) of (\d+), (\d+) of (\d+) \|")


def size_flags(before, after):
    """Per size set (seeds 0, 1): its good estimates flagged in ``camera{seed}_{before}`` and in
    ``camera{seed}_{after}``, and its good estimates."""
    return [f for seed in (0, 1) for f in (
        cam(f"camera{seed}_{before}", "all", "estimator", "flag:flagged_good"),
        cam(f"camera{seed}_{after}", "all", "estimator", "flag:flagged_good"),
        cam(f"camera{seed}_{after}", "all", "estimator", "good"))]


def speed_row(label, source, searched=False):
    """A row of the one-resolution speed table: per group success, count, MACE, ms, the ratio to
    SIFT + RANSAC's ms and SIFT's ms; with ``searched``, also the share of pairs the search
    looked at per group, then the flag over all pairs (bad flagged of bad, good flagged of good):
    a row of the fewer-stages and feature-start tables."""
    cell = rf"(\d+) of (\d+), {N} px, (\d+) ms \({N}x SIFT's (\d+) ms\)"
    cell += rf", searched {N}" if searched else ""
    path = "groups/{}/{}/ms_per_pair"
    flag = r" (\d+) of (\d+), (\d+) of (\d+) \|" if searched else ""
    return (rf"\| {re.escape(label)} \| {cell} \| {cell} \| {cell} \|{flag}",
            [f for g in ("within", "1-2x", "2-4x") for f in (
                cam(source, g, "estimator", "ok"), cam(source, g, "estimator", "count"),
                cam(source, g, "estimator", "mace"), cam(source, g, "estimator", "ms"),
                ratio((source, path.format(g, "estimator")),
                      (source, path.format(g, "sift_ransac"))),
                cam(source, g, "sift_ransac", "ms"),
                *([cam(source, g, "estimator", "searched")] if searched else []))]
            + ([cam(source, "all", "estimator", f)
                for f in ("flag:flagged_bad", "flag:bad", "flag:flagged_good", "good")]
               if searched else []))


def stage_row(label, source):
    """:func:`speed_row` with the search's share and the flag."""
    return speed_row(label, source, searched=True)


def wide_cells(source):
    """The numbers of :func:`wide_rows` from ``source``."""
    return [f for g in ("wide", "wide_low_light") for f in (
        cam(source, g, "estimator", "ok"), cam(source, g, "estimator", "count"),
        cam(source, g, "estimator", "mace"),
        cam(source, g, "estimator", "ms"),
        *[cam(source, g, m, f) for m in ("sift_ransac", "sift_wide", "orb_ransac")
          for f in ("ok", "mace", "ms")],
        cam(source, g, "identity", "ok"), cam(source, g, "identity", "mace"),
        *[cam(source, g, "estimator", f)
          for f in ("flag:flagged_bad", "flag:bad", "flag:flagged_good", "good")])]


def late_row(label, before, after, group):
    """A row of BENCHMARKS.md's late-feature-start table and its numbers: the estimator in
    ``before`` and ``after``, SIFT + RANSAC in ``after``, the estimator's flag in both."""
    run = rf"(\d+) of (\d+), {N} px, (\d+) ms"
    flag = r"(\d+) of (\d+), (\d+) of (\d+)"
    regex = (rf"\| {label} \| {re.escape(group)} \| {run} \| {run} \| {run} \| {flag} \| "
             rf"{flag} \|")
    cells = [cam(source, group, method, f) for source, method in (
        (before, "estimator"), (after, "estimator"), (after, "sift_ransac"))
        for f in ("ok", "count", "mace", "ms")]
    cells += [cam(source, group, "estimator", f) for source in (before, after)
              for f in ("flag:flagged_bad", "flag:bad", "flag:flagged_good", "good")]
    return ("BENCHMARKS.md", regex, cells)


def probe(key, source="schedule_probe"):
    """Steps/s of one variant of a GPU probe (its keys hold a slash: read directly)."""
    return lambda sources: f"{sources[source]['fit'][key]['steps_per_s']:.1f}"


SEMI_TITLES = ("100% labels", "10% labels alone", "10% labels + 90% unlabeled",
               "0% labels (L1 only)")
SEMI_HISTORY = "docs/history/semi_supervised_issue47.md"
"""The semi-supervised table of issue 47, withdrawn by issue 63 (its unlabeled pairs trained on
patch_a_t): its numbers stay checked against the JSON they came from, in the history."""


def semi_table_line(title):
    """A row of the semi-supervised table: mean, seeds' count, lowest, highest, difference."""
    return (rf"\| {re.escape(title)} \| [\d,]+ \| [\d,]+ \| {N} \| (\d+) seeds: {N}-{N} \| "
            rf"([+-]?[\d.]*) \|")


def semi_row(i, table="semi_table"):
    """The numbers of row ``i`` of a semi-supervised table (``table``: its JSON's source): the
    mean, the seeds' count, lowest and highest, and the difference to the first row (empty for
    it)."""
    def field(k):
        def get(sources):
            row = cr.value(sources, table, f"rows/{i}")
            maces = row["mace_per_seed"]
            first = cr.value(sources, table, "rows/0/mace")
            return {"mace": f"{row['mace']:.2f}", "n": str(len(maces)),
                    "low": f"{min(maces):.2f}", "high": f"{max(maces):.2f}",
                    "delta": "" if i == 0 else f"{row['mace'] - first:+.2f}"}[k]
        return get
    return [field(k) for k in ("mace", "n", "low", "high", "delta")]


def callback_cost(source):
    """The share of steps/s (%) the training callbacks cost a probe at 50 steps per call."""
    return lambda sources: "%.0f" % (100 * (1 - float(probe("array/spe50+callbacks", source)(
        sources)) / float(probe("array/spe50", source)(sources))))


def schedule_chunks(stage):
    """The number of ``stage``'s chunks in the paper schedule's ledger."""
    return lambda sources: str(sum(r["stage"] == stage for r in sources["schedule_ledger"]))


def schedule_hours(stage):
    """The wall time of ``stage``'s chunks in the paper schedule's ledger, in hours."""
    return lambda sources: cr.fixed(sum(r["wall_s"] for r in sources["schedule_ledger"]
                                        if r["stage"] == stage) / 3600, 1)


def stage_pairs_ms(source, threads):
    """Best ms per re-made stage-k pair of a stage-pairs benchmark at ``threads``."""
    return lambda sources: f"{sources[source]['best_ms_per_pair'][str(threads)]:.2f}"


# (file, regex with one group per number, the expected value of each group). Every match of the
# regex in the file is checked, and the regex must match at least once.
# Stage 3's CPU chunks in docs/gpu.md: (ledger row, ordinal, from step, to step).
STAGE3_CPU_CHUNKS = ((20, "First", 0, 12022), (21, "Second", 12022, 26399),
                     (22, "Third", 26399, 37132), (23, "Fourth", 37132, 46917),
                     (24, "Fifth", 46917, 56681),
                     (25, "Sixth", 56681, 58037),
                     (26, "Seventh", 58037, 67749),
                     (27, "Eighth", 67749, 80293),
                     (28, "Ninth", 80293, 91000))
SEQUENCE2_CPU_CHUNKS = ((29, "First", 0, 1399), (30, "Second", 0, 2322),
                        (31, "Third", 2322, 4763), (32, "Fourth", 4763, 7459),
                        (33, "Fifth", 7459, 9858), (34, "Sixth", 9858, 12000),
                        (35, "Seventh", 12000, 13952), (36, "Eighth", 13952, 15816),
                        (37, "Ninth", 15816, 17544), (38, "Tenth", 17544, 19441),
                        (39, "Eleventh", 19441, 19955), (40, "Twelfth", 19955, 21452),
                        (41, "Thirteenth", 21452, 22001))

PROSE = [
    ("docs/estimate.md",
     rf"\| 0, `EstimateOptions\(\)` \| {N} \({N}\) px, (\d+) of 100 \| (\d+) / (\d+) of 100 \| "
     rf"(\d+) of (\d+), (\d+) of (\d+) \|", cam_row("camera0_default")),
    ("docs/estimate.md",
     rf"\| 0, `photographs\(features=\"none\"\)` \(issue 46\) \| {N} \({N}\) px, (\d+) \| "
     rf"(\d+) / (\d+) \| (\d+) of (\d+), (\d+) of (\d+) \|", cam_row("camera0_photographs")),
    ("docs/estimate.md",
     rf"\| 0, `photographs\(\)` with the feature start, before one resolution \| {N} \({N}\) px, "
     rf"(\d+) \| (\d+) / (\d+) \| (\d+) of (\d+), (\d+) of (\d+) \|", cam_row("camera0_features")),
    ("docs/estimate.md",
     rf"\| 0, `photographs\(\)` with one resolution \| {N} \({N}\) px, "
     rf"(\d+) \| (\d+) / (\d+) \| (\d+) of (\d+), (\d+) of (\d+) \|",
     cam_row("camera0_resolution")),
    ("docs/estimate.md",
     rf"\| 0, `photographs\(\)` without the coarse pass \| {N} \({N}\) px, "
     rf"(\d+) \| (\d+) / (\d+) \| (\d+) of (\d+), (\d+) of (\d+) \|",
     cam_row("camera0_nocoarse")),
    ("docs/estimate.md",
     rf"\| 0, \*\*`photographs\(\)`\*\* today \(the late feature start\) \| \*\*{N}\*\* \({N}\) px, "
     rf"(\d+) \| \*\*(\d+)\*\* / \*\*(\d+)\*\* \| \*\*(\d+) of (\d+)\*\*, (\d+) of (\d+) \|",
     cam_row("camera0_late")),
    ("docs/estimate.md", rf"\| 0, SIFT \+ RANSAC \| {N} \({N}\) px, (\d+) \| (\d+) / (\d+) \| - \|",
     cam_row("camera0_default", "sift_ransac", flag=False)),
    ("docs/estimate.md",
     rf"\| 1, `photographs\(features=\"none\"\)` \(issue 46\) \| {N} \({N}\) px, (\d+) \| "
     rf"(\d+) / (\d+) \| (\d+) of (\d+), (\d+) of (\d+) \|", cam_row("camera1_photographs")),
    ("docs/estimate.md",
     rf"\| 1, `photographs\(\)` with the feature start, before one resolution \| {N} \({N}\) px, "
     rf"(\d+) \| (\d+) / (\d+) \| (\d+) of (\d+), (\d+) of (\d+) \|", cam_row("camera1_features")),
    ("docs/estimate.md",
     rf"\| 1, `photographs\(\)` with one resolution \| {N} \({N}\) px, "
     rf"(\d+) \| (\d+) / (\d+) \| (\d+) of (\d+), (\d+) of (\d+) \|",
     cam_row("camera1_resolution")),
    ("docs/estimate.md",
     rf"\| 1, `photographs\(\)` without the coarse pass \| {N} \({N}\) px, "
     rf"(\d+) \| (\d+) / (\d+) \| (\d+) of (\d+), (\d+) of (\d+) \|",
     cam_row("camera1_nocoarse")),
    ("docs/estimate.md",
     rf"\| 1, \*\*`photographs\(\)`\*\* today \(the late feature start; held out for that change only\) \| "
     rf"\*\*{N}\*\* \({N}\) px, (\d+) \| \*\*(\d+)\*\* / \*\*(\d+)\*\* \| "
     rf"\*\*(\d+) of (\d+)\*\*, (\d+) of (\d+) \|",
     cam_row("camera1_late")),
    ("docs/estimate.md", rf"\| 1, SIFT \+ RANSAC \| {N} \({N}\) px, (\d+) \| (\d+) / (\d+) \| - \|",
     cam_row("camera1_photographs", "sift_ransac", flag=False)),
    ("BENCHMARKS.md",
     rf"\| \*\*`photographs\(\)`\*\* \| \*\*{N}\*\* \({N}\), \*\*(\d+)\*\*, (\d+) ms \| "
     rf"\*\*{N}\*\* \({N}\), \*\*(\d+)\*\*, (\d+) ms \| \*\*{N}\*\* \({N}\), \*\*(\d+)\*\*, "
     rf"(\d+) ms \| \*\*(\d+) of (\d+), (\d+) of (\d+)\*\* \|",
     [cam("camera0_photographs", g, "estimator", f) for g in ("within", "1-2x", "2-4x")
      for f in ("mace", "median", "ok", "ms")]
     + [cam("camera0_photographs", "all", "estimator", f)
        for f in ("flag:flagged_bad", "flag:bad", "flag:flagged_good", "good")]),
    ("BENCHMARKS.md",
     rf"\| \*\*`photographs\(\)`\*\* \| \*\*{N}\*\* \({N}\), \*\*(\d+)\*\* \| {N} \({N}\), "
     rf"\*\*(\d+)\*\* \| {N} \({N}\), \*\*(\d+)\*\* \| \*\*(\d+) of (\d+), (\d+) of "
     rf"(\d+)\*\* \|",
     [cam("camera1_photographs", g, "estimator", f) for g in ("within", "1-2x", "2-4x")
      for f in ("mace", "median", "ok")]
     + [cam("camera1_photographs", "all", "estimator", f)
        for f in ("flag:flagged_bad", "flag:bad", "flag:flagged_good", "good")]),
    *[("BENCHMARKS.md", wide_rows(seed), wide_cells(f"camera{seed}_wide_features"))
      for seed in (0, 1, 2)],  # issue 64: the wide-baseline groups
    *[("BENCHMARKS.md", wide_rows(seed, ", one resolution"),
       wide_cells(f"camera{seed}_wide_resolution")) for seed in (0, 1, 2, 3)],
    ("BENCHMARKS.md", wide_rows(3, ", `resolution_sigma=0`"),
     wide_cells("camera3_wide_resolution_off")),
    *[("BENCHMARKS.md", wide_rows(seed, ", image_b's move beyond 1.5x"),
       wide_cells(f"camera{seed}_wide_move")) for seed in range(7)],
    *[("BENCHMARKS.md", wide_rows(seed, ", before"), wide_cells(f"camera{seed}_wide_move_off"))
      for seed in (4, 5, 6)],
    *[("BENCHMARKS.md", wide_rows(seed, ", a move brought back"),
       wide_cells(f"camera{seed}_wide_confirm")) for seed in range(9)],
    *[("BENCHMARKS.md", wide_rows(seed, ", before it"),
       wide_cells(f"camera{seed}_wide_confirm_off")) for seed in (7, 8)],
    ("BENCHMARKS.md",
     rf"good estimates flagged (\d+) -> (\d+) of (\d+) and{S}(\d+) -> (\d+) of (\d+); both bad "
     rf"estimates of seed 0 still flagged",
     size_flags("move", "confirm")),
    *[("BENCHMARKS.md", wide_rows(seed, ", 8 x 8 squares"),
       wide_cells(f"camera{seed}_wide_tiled")) for seed in range(9)],
    ("BENCHMARKS.md",
     rf"good estimates flagged (\d+) -> (\d+) of (\d+) \(seed 0's `2-4x` 272,{S}0.57 px off\) and "
     rf"(\d+) -> (\d+) of (\d+); both bad ones still flagged",
     size_flags("confirm", "tiled")),
    ("BENCHMARKS.md", *speed_row("one resolution (default)", "camera0_speed_resolution")),
    ("BENCHMARKS.md", *speed_row("`--thresholds=resolution_sigma=0`",
                                 "camera0_speed_resolution_off")),
    ("BENCHMARKS.md", *speed_row("3 (default)", "camera0_speed_move")),
    ("BENCHMARKS.md", *speed_row("2", "camera0_speed_two_stages")),
    *[("BENCHMARKS.md", wide_rows(seed, ", no search from the start"),
       wide_cells(f"camera{seed}_wide_start")) for seed in range(11)],
    *[("BENCHMARKS.md", wide_rows(seed, ", before"), wide_cells(f"camera{seed}_wide_start_off"))
      for seed in (9, 10)],
    *[("BENCHMARKS.md", *stage_row(label, f"camera{seed}_{name}"))
      for seed in (0, 1) for label, name in (
          (f"seed {seed}, 8 x 8 squares (before)", "tiled"),
          (f"seed {seed}, no search from the start", "start"))],
    *[("BENCHMARKS.md", wide_rows(seed, label), wide_cells(f"camera{seed}_wide_{name}"))
      for seed in range(13) for label, name in (  # issue 64: the coarse pass out of the default
          (", coarse pass (before)", "coarse"), (", no coarse pass", "nocoarse"))],
    *[("BENCHMARKS.md", *stage_row(f"seed {seed}, {label}", f"camera{seed}_{name}"))
      for seed in (0, 1, 2) for label, name in (
          ("coarse pass (before)", "coarse"), ("no coarse pass", "nocoarse"))],
    *[("BENCHMARKS.md", wide_rows(seed, ", features always"),
       wide_cells(f"camera{seed}_wide_always")) for seed in (0, 12)],  # issue 64: features="always" against "fallback"
    *[("BENCHMARKS.md", *stage_row(f"seed {seed}, features always", f"camera{seed}_always"))
      for seed in (0, 2)],
    *[("BENCHMARKS.md",  # the current results' camera rows, against cam's reading of the JSON
       rf"group `{group}` \(seed 0[^|]*\| [^|]*?: estimator \*\*(\d+) of (\d+)\*\*, {N} px, (\d+) "
       rf"ms; SIFT \+ RANSAC (\d+) of \d+, {N} px, (\d+) ms;[^|]*; ORB \+ RANSAC (\d+) of \d+, {N} "
       rf"px, (\d+) ms; identity {N} px; flag: (\d+) of (\d+) [^|]*?, (\d+) of (\d+) good ones \|",
       [cam(source, group, m, f) for m, fields in (("estimator", ("ok", "count", "mace", "ms")),
                                                   ("sift_ransac", ("ok", "mace", "ms")),
                                                   ("orb_ransac", ("ok", "mace", "ms")),
                                                   ("identity", ("mace",)))
        for f in fields]
       + [cam(source, group, "estimator", f)
          for f in ("flag:flagged_bad", "flag:bad", "flag:flagged_good", "good")])
      for source, groups, _ in result_cells.CAMERA_SETS
      for group in groups],
    *[late_row(label, f"camera{name}_nolate", f"camera{name}_late", group)  # the late start
      for label, name, groups in (("size seed 0", "0", ("within", "1-2x", "2-4x")),
                                  ("size seed 2", "2", ("within", "1-2x", "2-4x")),
                                  ("wide seed 0", "0_wide", ("wide", "wide_low_light")),
                                  # the held-out check
                                  ("size seed 1", "1", ("within", "1-2x", "2-4x")),
                                  ("wide seed 11", "11_wide", ("wide", "wide_low_light")),
                                  ("wide seed 12", "12_wide", ("wide", "wide_low_light")))
      for group in groups],
    *[("BENCHMARKS.md", *stage_row(label, f"camera0_{name}"))  # issue 64: fewer stages
      for label, name in (("3 stages (default)", "three_stages"), ("2 stages", "two_stages"),
                          ("1 stage", "one_stage"))],
    ("BENCHMARKS.md",  # issue 64, item 3: the speed table
     rf"\| within \| (\d+) of (\d+), {N} px, (\d+) ms \| (\d+) of \d+, {N} px, (\d+) ms \|\n"
     rf"\| 1-2x \| (\d+) of (\d+), {N} px, (\d+) ms \| (\d+) of \d+, {N} px, (\d+) ms \|\n"
     rf"\| 2-4x \| (\d+) of (\d+), {N} px, (\d+) ms \| (\d+) of \d+, {N} px, (\d+) ms \|",
     [f for g in ("within", "1-2x", "2-4x") for f in (
         cam("camera0_speed", g, "estimator", "ok"),
         cam("camera0_speed", g, "estimator", "count"),
         cam("camera0_speed", g, "estimator", "mace"), cam("camera0_speed", g, "estimator", "ms"),
         cam("camera0_speed", g, "sift_ransac", "ok"), cam("camera0_speed", g, "sift_ransac", "mace"),
         cam("camera0_speed", g, "sift_ransac", "ms"))]),
    ("BENCHMARKS.md", rf"load average {N} at the start\): only the ratio",
     [lambda sources: f"{cr.value(sources, 'camera0_speed', 'machine/loadavg_at_start')[0]:.2f}"]),
    ("BENCHMARKS.md", rf"the estimator took {N}x SIFT's time",
     [ratio(("camera0_speed", "groups/within/estimator/ms_per_pair"),
            ("camera0_speed", "groups/within/sift_ransac/ms_per_pair"))]),
    ("docs/estimate.md", rf"it took (\d+){S}against the then default's (\d+) ms per pair",
     [cam("camera0_photographs", "within", "estimator", "ms"),
      cam("camera0_default_estimator", "within", "estimator", "ms")]),
    ("BENCHMARKS.md",  # issue 63: the re-measure's progress
     rf"MACE {N} px on the 300 test pairs \(`semi_supervised/eval/semi_labels-0.1_l1b.json`;"
     rf"{S}the model and its record in `semi_supervised/`\), against {N} px for the 10% labels "
     rf"alone \(seed{S}0\)",
     [num("semi_plus_unlabeled_l1b_seed0", "model/mace"),
      num("semi_labeled_alone_seed0", "model/mace")]),
    ("BENCHMARKS.md",
     rf"MACE {N} px on the{S}300 test pairs \(`semi_supervised/eval/semi_labels-0_l1b.json`; the "
     rf"model and its record in{S}`semi_supervised/`\), against {N} px for the withdrawn table's "
     rf"seed 0",
     [num("semi_none_l1b_seed0", "model/mace"), num("semi_none_seed0", "model/mace")]),
    (SEMI_HISTORY,
     rf"\| 100% labels \| 21,900 \| 21,900 \| {N} \| {N} \|\n"
     rf"\| 10% labels alone \| 2,241 \| 2,241 \| {N} \| {N} \|\n"
     rf"\| 10% labels \+ 90% unlabeled \| 2,241 \| 21,900 \| {N} \| {N} \|\n"
     rf"\| 0% labels \(L1 only\) \| 0 \| 21,900 \| {N} \| {N} \|",
     [num("semi_all_seed0", "model/mace"), num("semi_all_seed0", "model/median"),
      num("semi_labeled_alone_seed0", "model/mace"),
      num("semi_labeled_alone_seed0", "model/median"),
      num("semi_plus_unlabeled_seed0", "model/mace"),
      num("semi_plus_unlabeled_seed0", "model/median"),
      num("semi_none_seed0", "model/mace"), num("semi_none_seed0", "model/median")]),
    (SEMI_HISTORY,
     rf"lowers the MACE by {N} px\n\({N} to {N}\), against {N} px between 10% and 100%",
     [difference(("semi_labeled_alone_seed0", "model/mace"),
                 ("semi_plus_unlabeled_seed0", "model/mace")),
      num("semi_labeled_alone_seed0", "model/mace"),
      num("semi_plus_unlabeled_seed0", "model/mace"),
      difference(("semi_labeled_alone_seed0", "model/mace"), ("semi_all_seed0", "model/mace"))]),
    (SEMI_HISTORY,
     rf"\| 100% labels \(Table 1's 1:1 seed 1\) \| {N} \| {N} \|\n"
     rf"\| 10% labels alone \| {N} \| {N} \|\n"
     rf"\| 10% labels \+ 90% unlabeled \| {N} \| {N} \|\n"
     rf"\| 0% labels \(L1 only\) \| {N} \| {N} \|\n\nThe second seed of 10% alone is {N} px "
     rf"worse than its first \({N}\), more than the {N} px",
     [num("semi_all_seed1", "model/mace"), num("semi_all_seed1", "model/median"),
      num("semi_labeled_alone_seed1", "model/mace"),
      num("semi_labeled_alone_seed1", "model/median"),
      num("semi_plus_unlabeled_seed1", "model/mace"),
      num("semi_plus_unlabeled_seed1", "model/median"),
      num("semi_none_seed1", "model/mace"), num("semi_none_seed1", "model/median"),
      difference(("semi_labeled_alone_seed1", "model/mace"),
                 ("semi_labeled_alone_seed0", "model/mace")),
      num("semi_labeled_alone_seed0", "model/mace"),
      difference(("semi_labeled_alone_seed0", "model/mace"),
                 ("semi_plus_unlabeled_seed0", "model/mace"))]),
    (SEMI_HISTORY,
     rf"paper/reproduce.py since fc256e0\) gives {N} px\. So each seed of 10% \+ 90% unlabeled "
     rf"\({N},{S}{N}\) is below each seed of 10% alone \({N}, {N}\), the experiment's rule for "
     rf"\"the claim{S}holds\" \(`stnh_tf/paper/semi_supervised.py`, `claim`\): the means differ "
     rf"by {N} px, but the{S}closest seeds only by {N} px\.",
     [num("semi_plus_unlabeled_seed1", "model/mace"),
      num("semi_plus_unlabeled_seed0", "model/mace"),
      num("semi_plus_unlabeled_seed1", "model/mace"),
      num("semi_labeled_alone_seed0", "model/mace"),
      num("semi_labeled_alone_seed1", "model/mace"),
      lambda s: cr.fixed((cr.value(s, "semi_labeled_alone_seed0", "model/mace")
                          + cr.value(s, "semi_labeled_alone_seed1", "model/mace")
                          - cr.value(s, "semi_plus_unlabeled_seed0", "model/mace")
                          - cr.value(s, "semi_plus_unlabeled_seed1", "model/mace")) / 2, 2),
      difference(("semi_labeled_alone_seed0", "model/mace"),
                 ("semi_plus_unlabeled_seed1", "model/mace"))]),
    ("docs/training.md", rf"\(10% \+ 90% unlabeled {N} px against 10% alone {N}; the table",
     [semi_row(2, "semi_table_l1b")[0], semi_row(1, "semi_table_l1b")[0]]),
    ("BENCHMARKS.md", "\n".join(semi_table_line(t) for t in SEMI_TITLES),
     sum((semi_row(i, "semi_table_l1b") for i in range(4)), [])),
    (SEMI_HISTORY, "\n".join(semi_table_line(t) for t in SEMI_TITLES),
     semi_row(0) + semi_row(1) + semi_row(2) + semi_row(3)),
    (SEMI_HISTORY, rf"lowers{S}the{S}MACE{S}by{S}{N}{S}px:{S}the{S}claim{S}holds{S}at{S}this"
     rf"{S}budget{S}\(2{S}and{S}2{S}seeds\)\.", [num("semi_table", "claim/difference_px")]),
    (SEMI_HISTORY, rf"The 0% row's seed 1 \(trained in the same session, code{S}b498457\) gives "
     rf"{N} px\.", [num("semi_none_seed1", "model/mace")]),
    (SEMI_HISTORY,
     rf"median step takes {N} s with every pair labeled and {N} s with{S}every pair unlabeled "
     rf"\(`h_mask` 0, the L1 term alone\), a ratio of {N}\.",
     [num("semi_step_cost", "train_step_s/mixed_bfloat16/stn_homography", 3),
      num("semi_step_cost", "train_step_s/mixed_bfloat16/stn_homography_unlabeled", 3),
      num("semi_step_cost", "train_step_s/mixed_bfloat16/unlabeled_over_labeled", 3)]),
    ("docs/gpu.md",  # issue 60, item 4: the test set's precision of stage 1's MACE
     rf"the standard error of the {N} over its 300 pairs is {N} px",
     [num("schedule1_eval_se", "model/mace"), num("schedule1_eval_se", "model/mace_se")]),
    ("BENCHMARKS.md", rf"{N} px with a{S}standard error of {N} px over the 300 pairs",
     [num("schedule1_eval_se", "model/mace"), num("schedule1_eval_se", "model/mace_se")]),
    ("docs/gpu.md",  # issue 78, item 4: the same by photograph (a bootstrap)
     rf"`paper_schedule/stage1_eval_ci.json`\), {N} px, with a 95% interval of {N}-{N} px",
     [num("schedule1_eval_ci", "model/mace_se_by_photograph"),
      num("schedule1_eval_ci", "model/mace_ci95_by_photograph/0"),
      num("schedule1_eval_ci", "model/mace_ci95_by_photograph/1")]),
    ("BENCHMARKS.md", rf"\({N} px by photograph, with a 95% interval of{S}{N}-{N} px",
     [num("schedule1_eval_ci", "model/mace_se_by_photograph"),
      num("schedule1_eval_ci", "model/mace_ci95_by_photograph/0"),
      num("schedule1_eval_ci", "model/mace_ci95_by_photograph/1")]),
    ("BENCHMARKS.md",  # issue 63: the step cost with the leak-free L1 target
     rf"the paper's model's median step takes {N} s; the model{S}of a run with unlabeled pairs "
     rf"[^:]*?unlabeled, {N} s: a ratio of {N} \(the bare regression{S}network with the L2 loss alone: "
     rf"{N} s\)",
     [num("semi_step_cost_l1b", f"train_step_s/mixed_bfloat16/{k}", 3)
      for k in ("stn_homography", "stn_homography_unlabeled", "unlabeled_over_labeled",
                "bare_regression")]),
    ("docs/training.md", rf"its step time is {N} times the{S}paper's model's",
     [num("semi_step_cost_l1b", "train_step_s/mixed_bfloat16/unlabeled_over_labeled", 3)]),
    ("docs/estimate.md",
     rf"is {N} px from `h_true` at the image corners, and {N} px with{S}`EstimateOptions\(\)` "
     rf"\(identity: {N} px;",
     [num("readme_example", "default/plain/error_px"),
      num("readme_example", "estimate_default/plain/error_px"),
      num("readme_example", "identity_error_px")]),
    ("docs/gpu.md",
     rf"\*\*MACE {N} px\*\* on the 300 coco_mini test pairs of the tables \(identity {N};",
     [num("schedule_card", "evaluation/model/stages/after_1_stages/mace"),
      num("schedule_card", "evaluation/identity/mace")]),
    ("docs/gpu.md",
     rf"validation MACE\): {N} px at step 500,{S}{N} at 10,000, {N} at 30,000, {N} at 50,000, "
     rf"{N} at 70,000 and {N} at 91,000",
     [curve(s) for s in (500, 10_000, 30_000, 50_000, 70_000, 91_000)]),
    ("docs/gpu.md", rf"computed in float32{S}the same model gives {N} px as well",
     [num("schedule_float32_inference", "model/mace")]),
    ("docs/gpu.md", rf"photographs give {N} px \(identity {N};",
     [num("schedule_train_photos", "model/mace"),
      num("schedule_train_photos", "identity/mace")]),
    ("docs/gpu.md", rf"without callbacks: {N} / {N} / {N}\.",
     [probe(k) for k in ("array", "array/spe10", "array/spe50")]),
    ("docs/gpu.md", rf"GPU: {N} / {N} / {N}\.",
     [probe(f"array/spe{k}+callbacks") for k in (1, 10, 50)]),
    ("docs/gpu.md", rf"H100 \(2026-11-28,"
     rf" `paper_schedule/logs/h100_steps_per_execution_probe.json`\){S}gives, at 1 / 10 / 50"
     rf" steps per call, {N} / {N} / {N} steps/s without callbacks and"
     rf"{S}{N} / {N} / {N} with them\.",
     [probe(k, "schedule_probe_h100") for k in ("array", "array/spe10", "array/spe50")]
     + [probe(f"array/spe{k}+callbacks", "schedule_probe_h100") for k in (1, 10, 50)]),
    ("docs/gpu.md",
     rf"at 50 steps per call \((\d+)% of the steps/s on the H200, (\d+)% on the H100\)",
     [callback_cost("schedule_probe"), callback_cost("schedule_probe_h100")]),
    ("docs/gpu.md", rf"log `paper_schedule/logs/stage2_0-38000_h100.log`\): {N} steps/s,",
     [num("schedule_ledger", "3/steps_per_s")]),
    ("BENCHMARKS.md",
     rf"\(batch 64\) takes {N} s in float32 and {N} s in mixed bfloat16: there bfloat16 is {N}x"
     rf"{S}faster",
     [num("training_step_zen4", f"train_step_s/{p}/stn_homography") for p in
      ("float32", "mixed_bfloat16")]
     + [ratio(("training_step_zen4", "train_step_s/float32/stn_homography"),
              ("training_step_zen4", "train_step_s/mixed_bfloat16/stn_homography"))]),
    ("docs/gpu.md",
     rf"tree took {N} MiB and the photographs (\d+) calls, without them {N} MiB and (\d+) calls",
     [num("device_calls_plain", "tracked_mib", 1), length("device_calls_plain", "calls"),
      num("device_calls_set_aside", "tracked_mib", 1), length("device_calls_set_aside", "calls")]),
    ("docs/gpu.md", rf"by the committed stage-3 checkpoint and estimates, then took {N} MiB and the "
     rf"photographs (\d+){S}calls, the wheels in the first",
     [num("device_calls_set_aside_1206", "tracked_mib", 1),
      length("device_calls_set_aside_1206", "calls")]),
    ("docs/gpu.md", rf"38,000 -> 40,500 at {N} steps/s in the ledger{S}\(its log went with"
     rf" that machine's disk\), 40,500 -> 44,500 at {N} steps/s{S}"
     rf"\(`paper_schedule/logs/stage2_40500-44500_cpu.log`\) and 44,500 -> 49,000 at {N} steps/s{S}"
     rf"\(`paper_schedule/logs/stage2_44500-49000_cpu.log`\), then 49,000 -> [\d,]+ at {N} steps/s{S}"
     rf"\(`paper_schedule/logs/stage2_49000-50000_cpu.log`\) and 50,000 -> 52,500 at {N} steps/s"
     rf"[^$]*?then 52,500 -> 56,331 at {N} steps/s[^$]*?then 56,331 -> 60,094 at {N} steps/s"
     rf"[^$]*?then 60,094 ->{S}64,055 at {N} steps/s[^$]*?then 64,055 -> 66,399 at {N} steps/s"
     rf"[^$]*?then 66,399 -> 68,025 at {N}{S}steps/s[^$]*?then 68,025 -> 69,410 at {N} steps/s"
     rf"[^$]*?then 69,410 -> 70,764 at {N} steps/s[^$]*?then 70,764 -> 77,056 at {N} steps/s"
     rf"[^$]*?then 77,056 -> 78,902 at{S}{N} steps/s",
     [num("schedule_ledger", f"{i}/steps_per_s")
      for i in (4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17)]),
    ("docs/gpu.md", rf"then 78,902 -> 89,276 at {N} steps/s[^$]*?then 89,276 -> 91,000 at {N}{S}"
     rf"steps/s \(`paper_schedule/logs/stage2_89276-91000_cpu.log`",
     [num("schedule_ledger", f"{i}/steps_per_s") for i in (18, 19)]),
    ("docs/gpu.md", rf"\*\*MACE {N} px after 2 stages\*\* on the 300 coco_mini test pairs of the "
     rf"tables \(paper 2.6; after{S}stage 1 {N}, identity {N};",
     [num("schedule_card", f"evaluation/model/stages/after_{k}_stages/mace") for k in (2, 1)]
     + [num("schedule_card", "evaluation/identity/mace")]),
    ("docs/gpu.md", rf"the{S}second stage does not help: {N} px after stage 1, {N} after 2 stages "
     rf"\(identity {N}\); under{S}the photometric change of patch_b {N} and {N} px",
     [num("schedule_card", f"bundled_check/{k}") for k in (
         "estimate_mace_1_stages", "estimate_mace_2_stages", "identity_mace",
         "photometric_estimate_mace_1_stages", "photometric_estimate_mace_2_stages")]),
    ("docs/gpu.md", rf"\*\*MACE {N} px after 3 stages\*\* on the 300 coco_mini test pairs of the "
     rf"tables \(paper 1.57;{S}after stage 2 {N}, after stage 1 {N}, identity {N};[^$]*?"
     rf"95% interval by photograph {N}-{N} px; with the clipping of corners onto{S}the context "
     rf"{N} px as well",
     [num("schedule_card", f"evaluation/model/stages/after_{k}_stages/mace") for k in (3, 2, 1)]
     + [num("schedule_card", "evaluation/identity/mace")]
     + [num("schedule_card", f"evaluation/model/mace_ci95_by_photograph/{i}") for i in (0, 1)]
     + [num("schedule3_eval", "model/mace")]),
    ("docs/gpu.md", rf"float32\):{S}{N} px after 3 stages \({N} after stage 1, {N} after 2; "
     rf"identity {N}\); under the{S}photometric change of patch_b {N} px, and the networks alone "
     rf"without the estimator's search{S}{N} px, worse than the identity on (\d+) of the 60 pairs",
     [num("schedule_card", f"bundled_check/{k}") for k in (
         "estimate_mace_3_stages", "estimate_mace_1_stages", "estimate_mace_2_stages",
         "identity_mace", "photometric_estimate_mace_3_stages",
         "photometric_unsearched_estimate_mace_3_stages")]
     + [lambda sources: str(cr.value(sources, "schedule_card",
                                     "bundled_check/photometric_unsearched_worse_than_identity_3_stages"))]),
    *[("docs/gpu.md", rf"{nth} chunk, steps {a:,} -> {b:,}, on [^$]*?"
       rf"`paper_schedule/logs/{part}_{a}-{b}_cpu.log`\): {N} steps/s in the ledger",
       [num("schedule_ledger", f"{row}/steps_per_s")])
      for row, nth, a, b, part in (*[(*c, "stage3") for c in STAGE3_CPU_CHUNKS],
                                   *[(*c, "sequence2") for c in SEQUENCE2_CPU_CHUNKS])],
    ("docs/gpu.md", rf"- Finished at 91,000 steps over (\d+) chunks and {N} hours of wall time in "
     rf"all, every chunk on the",
     [schedule_chunks(3), schedule_hours(3)]),
    ("docs/gpu.md", rf"\(the reproduction's hierarchy rows\) {N} px[^$]*?saved mixed{S}bfloat16, "
     rf"{N} px with the clipping",
     [num("schedule2_eval", "model/mace"), num("schedule2_eval_float32", "model/mace")]),
    ("docs/gpu.md", rf"Finished at 91,000 steps over (\d+) chunks and {N} hours of wall time in "
     rf"all \(one H100",
     [schedule_chunks(2), schedule_hours(2)]),
    ("docs/gpu.md", rf"50 steps per call, {N} steps/s over", [num("schedule_record",
                                                                  "chunks/1/steps_per_s")]),
    ("docs/weights.md",
     rf"\*\*{N} px\*\* after stage 1, \*\*{N}\*\* after stage 2, \*\*{N}\*\* after stage 3 "
     rf"\({N} without",
     CARD_STAGES + [num("card", NO_CLIP, 3)]),
    ("docs/weights.md",
     rf"`plain_bundled_test`\):{S}\*\*{N} / {N} / {N} px\*\* after 1 / 2 / 3 stages, 95% "
     rf"interval{S}by photograph {N}-{N} px after 3 stages \({N}-{N} on the coco_mini pairs\)"
     rf"\. The coco_mini{S}figure is the better by {N} px",
     [num("card", f"evaluation/plain_bundled_test/model/stages/after_{k}_stages/mace")
      for k in (1, 2, 3)]
     + [num("card", f"evaluation/{e}/model/mace_ci95_by_photograph/{i}")
        for e in ("plain_bundled_test", "plain_coco_mini_test") for i in (0, 1)]
     + [lambda s: "{:.1f}".format(cr.value(s, "card", "evaluation/plain_bundled_test/model/mace")
                                  - cr.value(s, "card", CARD_3))]),
    ("BENCHMARKS.md", rf"image context, float32: \*\*{N} / {N} / {N} px\*\* after 1 / 2 / 3"
     rf"{S}stages, against {N} / {N} / {N} on the coco_mini test pairs",
     [num("card", f"evaluation/plain_bundled_test/model/stages/after_{k}_stages/mace")
      for k in (1, 2, 3)] + CARD_STAGES),
    ("docs/weights.md", rf"tuned ORB \+ RANSAC {N},{S}SIFT \+ RANSAC {N} on the same pairs",
     [fig4("ORB + RANSAC"), fig4("SIFT + RANSAC")]),
    ("docs/weights.md",
     rf"photometric change of patch_b \*\*{N} px\*\* \(identity{S}{N}; (\d+) of 300",
     [num("card", f"{PHOTO}/mace"), num("card", f"{PHOTO}/identity/mace"),
      count("card", f"{PHOTO}/worse_than_identity")]),
    ("docs/weights.md",
     rf"estimates-default\):{S}{N} / {N} / {N} px after 1 / 2 / 3 stages, photometric "
     rf"{N} / {N} / {N}",
     [check("", k) for k in (1, 2, 3)] + [check("photometric_", k) for k in (1, 2, 3)]),
    ("docs/weights.md", rf"test-time-augmentation-opt-in\)\) {N} \(photometric {N}\)",
     [check("tta_", 3), check("photometric_tta_", 3)]),
    ("docs/weights.md", rf'`search="none"`\): {N} px{S}after 3 stages, photometric {N}',
     [check("unsearched_", 3), check("photometric_unsearched_", 3)]),
    ("docs/weights.md",
     rf"on the 300 coco_mini test pairs {N} px after 3 stages{S}\({N} with the photometric",
     [num("card", f"{FLAG}/mace"), num("card", f"{FLAG_PHOTO}/mace")]),
    ("docs/weights.md", rf"without the{S}gate {N} / {N} px after 3 stages with the search",
     [num("card", f"{CHECK}/ungated_estimate_mace_3_stages"),
      num("card", f"{CHECK}/photometric_ungated_estimate_mace_3_stages")]),
    ("docs/weights.md", rf"full benefit \({N} px\)", [num("card", CARD_3)]),
    ("docs/weights.md",
     rf"flags {N}% of ordinary bare coco_mini test pairs \(their MACE {N} px{S}against {N} for",
     [percent("card", f"{FLAG}/flagged"), num("card", f"{FLAG}/mace_flagged"),
      num("card", f"{FLAG}/mace_kept")]),
    ("docs/weights.md", r"\(([\d,]+) steps in all, (\d+)% of the paper's 3 x 90,000\)",
     [total_steps, share_of_paper]),
    ("docs/weights.md", rf"in the paper\):{S}{N} px \(1 stage\), {N} \(2\), {N} \(3\)",
     PAPER_STAGES),
    ("docs/weights.md", rf"3 stages {N} px \(with the default search: {N} and {N};",
     [check("unsearched_", 3, "paper_card"), check("", 1, "paper_card"),
      check("", 3, "paper_card")]),
    ("docs/estimate.md", rf"today's default, with both: {N} px bundled",
     [check("unsearched_", 3)]),
    ("docs/estimate.md", rf"{N} px on the coco_mini test pairs \({N} with context\)",
     [num("card", f"{FLAG}/mace"), num("card", CARD_3)]),
    ("docs/estimate.md",
     rf"estimates-default\): {N},{S}{N} and {N} px bundled",
     [check("", 3), check("", 2), check("", 1)]),
    ("docs/estimate.md", rf"takes the 300 coco_mini{S}test pairs from{S}{N}{S}to",
     [num("card", f"{FLAG}/mace")]),
    ("docs/estimate.md", rf"the 60{S}bundled{S}pairs{S}from {N} to", [check("unsearched_", 3)]),
    ("docs/estimate.md", rf"\| coco_mini test \(300\) \| {N} \[", [num("card", f"{FLAG}/mace")]),
    ("docs/estimate.md", rf"\| model card's bundled \(60\) \| {N} \[1\] \| \*\*{N}\*\*",
     [check("unsearched_", 3), check("", 3)]),
    ("docs/estimate.md",
     rf"the model card's 60 bundled pairs {N}{S}px \(photometric {N};",
     [check("", 3), check("photometric_", 3)]),
    ("docs/estimate.md", rf"with a single stage {N} on the card's", [check("", 1)]),
    ("docs/estimate.md",
     rf"bundled MACE goes from {N} to{S}{N} px \(photometric {N} to {N}\)",
     [check("unsearched_", 3, "paper_card"), check("", 3, "paper_card"),
      check("photometric_unsearched_", 3, "paper_card"),
      check("photometric_", 3, "paper_card")]),
    ("docs/estimate.md", rf"and {N}% of ordinary bare coco_mini test pairs before the search",
     [percent("card", f"{FLAG}/flagged")]),
    ("docs/estimate.md", rf"3-stage test MACE is [\d.]+ px in float32 against {N} in bfloat16",
     [PAPER_STAGES[2]]),
    ("docs/conventions.md", rf"shipped fast recipe's: {N} and {N} px",
     [num("card", CARD_3, 3), num("card", NO_CLIP, 3)]),
    ("docs/conventions.md", rf"show it \({N} px\) beside", [fig4("HomographyNet")]),
    ("docs/conventions.md", rf"schedule \({N} px\)", [fig4("HomographyNet variant (GAP)")]),
    ("docs/training.md",
     rf"DeTone's network {N} px,{S}the variant {N} px, STN-Homography's single stage {N} px",
     [fig4("HomographyNet"), fig4("HomographyNet variant (GAP)"),
      fig4("STN-Homography 1 stage")]),
    ("BENCHMARKS.md",
     rf"\| \*\*this stage 3\*\* \| {N} / {N} / \*\*{N}\*\* \[(\d+)\] \| {N} / {N} / "
     rf"\*\*{N}\*\* \[(\d+)\]",
     CARD_STAGES[:2] + [num("card", CARD_3, 3),
                        count("card", "evaluation/plain_coco_mini_test/model/worse_than_identity")]
     + [num("card", f"{PHOTO}/stages/after_{k}_stages/mace") for k in (1, 2)]
     + [num("card", f"{PHOTO}/mace", 3), count("card", f"{PHOTO}/worse_than_identity")]),
    ("BENCHMARKS.md", rf"3 stages <= 2\.0{S}met \({N}\); bare patches <= 8\.65 met \({N}\)",
     [num("card", CARD_3), check("unsearched_", 3)]),
    ("BENCHMARKS.md", rf"Without clipping {N} after 3 stages \(previous 0.829\)",
     [num("card", NO_CLIP, 3)]),
    ("BENCHMARKS.md",
     rf"6799f50, the benchmark's two files copied in; JSON{S}"
     rf"`paper_schedule/logs/stage_pairs_benchmark_before_cpu.json`\): {N} ms per pair on 1 "
     rf"thread,{S}{N} on 2\.",
     [stage_pairs_ms("stage_pairs_before", 1), stage_pairs_ms("stage_pairs_before", 2)]),
    ("BENCHMARKS.md",
     rf"`paper_schedule/logs/stage_pairs_benchmark_after_cpu.json`\): {N} ms per pair on 1 "
     rf"thread,{S}{N} on 2\.",
     [stage_pairs_ms("stage_pairs_after", 1), stage_pairs_ms("stage_pairs_after", 2)]),
    ("BENCHMARKS.md", rf"the re-making is about{S}{N} s on these 2 cores",
     [lambda sources: "%.0f" % (184.8 * sources["stage_pairs_after"]["best_ms_per_pair"]["2"])]),
    ("BENCHMARKS.md", rf"(\d,\d+) pairs from the 219 coco_mini train{S}photographs \(20 each\), "
     rf"(\d,\d+) of them clipped",
     [lambda sources: f"{sources['stage_pairs_after']['pairs']:,}",
      lambda sources: "{:,}".format(sources["stage_pairs_after"]["runs"][0][
          "degenerate_rule_cases"]["outside_context"])]),
    ("BENCHMARKS.md",
     rf"--data_dir=D \[--photometric\]`\): {N}% of ordinary bare coco_mini test pairs \(their MACE "
     rf"{N} px{S}against {N} for the rest",
     [percent("card", f"{FLAG}/flagged"), num("card", f"{FLAG}/mace_flagged"),
      num("card", f"{FLAG}/mace_kept")]),
    ("BENCHMARKS.md",
     rf"HomographyNet \(DeTone's network\) {N}, its `homographynet_gap` variant {N}, STN 1/2/3 "
     rf"stages {N} / {N} / {N}, sequence {N}, ORB {N}, SIFT {N}, identity {N} px",
     [fig4("HomographyNet"), fig4("HomographyNet variant (GAP)"), fig4("STN-Homography 1 stage"),
      fig4("STN-Homography 2 stages"), fig4("STN-Homography 3 stages"),
      fig4("Sequence 2 stages"), fig4("ORB + RANSAC"), fig4("SIFT + RANSAC"),
      fig4("Identity")]),
    # issue 62 item 4: a lost worker (docs/scale/*.json, from experiments.benchmark_workers)
    ("docs/scale.md", rf"the chief's line came {N} s and {N} s after the kill",
     [lambda sources, k=k: cr.fixed(_scale("lost_worker")["kills"][k]["line_after_s"])
      for k in (0, 1)]),
    ("docs/scale.md", rf"on the busy 2-core machine \({N} s for a beat due every second",
     [lambda sources: cr.fixed(max(w["beat_max_gap_s"]
                                   for w in _scale("workers_batch8")["two"]))]),
]


def _camera_file(name):
    """docs/camera_pairs/``name``.json (not in ``current_results.SOURCES``)."""
    with open(os.path.join(ROOT, "docs", "camera_pairs", f"{name}.json")) as f:
        return json.load(f)


def from_file(name, get):
    """``get`` (a getter of this module, reading source ``name``) on docs/camera_pairs/``name``."""
    return lambda sources: get({**sources, name: _camera_file(name)})


def native_row(label, name, group):
    """A row of BENCHMARKS.md's table of the feature start at the images' own resolution (issue
    79) and its numbers, from docs/camera_pairs/``name``.json."""
    run = rf"(\d+) of (\d+), {N} \({N}\) px, (\d+) ms"
    base = rf"(\d+), {N} px, (\d+) ms"
    regex = (rf"\| {re.escape(label)} \| `{group}` \| {run} \| {base} \| {base} \| "
             rf"(\d+) of (\d+), (\d+) of (\d+) \|")
    fields = [("estimator", f) for f in ("ok", "count", "mace", "median", "ms")]
    fields += [(m, f) for m in ("sift_ransac", "sift_wide") for f in ("ok", "mace", "ms")]
    fields += [("estimator", f) for f in ("flag:flagged_bad", "flag:bad", "flag:flagged_good",
                                          "good")]
    return ("BENCHMARKS.md", regex, [from_file(name, cam(name, group, m, f)) for m, f in fields])


def native_pair(name, index):
    """The estimator's error of pair ``index`` in docs/camera_pairs/``name``.json."""
    return lambda sources: cr.fixed(next(p["estimator_error"] for p in _camera_file(name)["pairs"]
                                         if p["index"] == index))


NATIVE = ("wide_seed13_scale2_work_start", "wide_seed13_scale2_native_start")
PROSE += [  # issue 79, item 2: the feature start at the images' own resolution
    *[native_row(label, name, group)
      for label, name in (("320 x 240, work start (= native)", "wide_seed13_scale1"),
                          ("640 x 480, work start", NATIVE[0]),
                          ("640 x 480, native start", NATIVE[1]),
                          ("640 x 480, work start first, native where unconfirmed",
                           "wide_seed13_scale2_cascade"))
      for group in ("wide", "wide_low_light")],
    ("BENCHMARKS.md",
     rf"\(pair 10, `wide`:{S}{N} px and unflagged, a silent failure; pair 23, "
     rf"`wide_low_light`: {N} px\) get no start from{S}the 640 x 480 images and end flagged, {N} "
     rf"and {N} px off; pair 75, flagged in both, went{S}from {N} to {N} px",
     [native_pair(NATIVE[0], 10), native_pair(NATIVE[0], 23), native_pair(NATIVE[1], 10),
      native_pair(NATIVE[1], 23), native_pair(NATIVE[0], 75), native_pair(NATIVE[1], 75)]),
    ("BENCHMARKS.md",
     rf"The estimator takes {N}x the time per{S}pair in `wide` [^,]*,[^,]*, {N}x SIFT \+ "
     "RANSAC's on the same images",
     [from_file(NATIVE[1], lambda sources: cr.fixed(
         cr.value(sources, NATIVE[1], "groups/wide/estimator/ms_per_pair")
         / _camera_file(NATIVE[0])["groups"]["wide"]["estimator"]["ms_per_pair"])),
      from_file(NATIVE[1], ratio((NATIVE[1], "groups/wide/estimator/ms_per_pair"),
                                 (NATIVE[1], "groups/wide/sift_ransac/ms_per_pair")))]),
]


LOW = "low_overlap_seed13"


def low_overlap_count(test):
    """The count of pairs of docs/camera_pairs/low_overlap_seed13.json for which ``test(pair)``."""
    return lambda sources: str(sum(bool(test(p)) for p in _camera_file(LOW)["pairs"]))


PROSE += [  # issue 79, item 4: the low-overlap set
    native_row("320 x 240, low overlap", LOW, "low_overlap"),
    ("BENCHMARKS.md", rf"`nice -n 19`, load {N} at the start",
     [lambda sources: f"{_camera_file(LOW)['machine']['loadavg_at_start'][0]:.2f}"]),
    ("BENCHMARKS.md",
     rf"Every estimate more than (\d+) px off is flagged \(so none 10 px or more off is left"
     rf"{S}unflagged: (\d+) of{S}(\d+)\), and (\d+) of the (\d+) good ones are \({N}%; the goal "
     rf"is at most 5%\)\. The estimator takes {N}x{S}SIFT \+ RANSAC's time per pair",
     [lambda sources: f"{_camera_file(LOW)['flag_error_px']:.0f}",
      low_overlap_count(lambda p: p["estimator_error"] >= 10 and not p["implausible"]),
      from_file(LOW, cam(LOW, "low_overlap", "estimator", "count")),
      from_file(LOW, cam(LOW, "low_overlap", "estimator", "flag:flagged_good")),
      from_file(LOW, cam(LOW, "low_overlap", "estimator", "good")),
      from_file(LOW, lambda sources: cr.fixed(100 * cr.value(
          sources, LOW, "groups/low_overlap/estimator/flag/false_alarm_rate"), 1)),
      from_file(LOW, ratio((LOW, "groups/low_overlap/estimator/ms_per_pair"),
                           (LOW, "groups/low_overlap/sift_ransac/ms_per_pair"), 1))]),
]


def _hour(name):
    """docs/reproduce_hour/``name``.json (issue 78's hour-budget runs and traces)."""
    with open(os.path.join(ROOT, "docs", "reproduce_hour", f"{name}.json")) as f:
        return json.load(f)


def _trace(name, step, key, digits=2, sub=None):
    """``key`` (``[sub]``) of 1-based ``step`` of docs/reproduce_hour/trace_``name``.json."""
    def get(sources):
        value = _hour(f"trace_{name}")["steps"][step - 1][key]
        value = value[sub] if sub else value
        return value if isinstance(value, str) else cr.fixed(value, digits)
    return get


def _thousands(name, step):
    return lambda sources: f"{_hour(f'trace_{name}')['steps'][step - 1]['grad_norm']:,.0f}"


def _trace_row(label, clipped, name, min_step):
    """A row of BENCHMARKS.md's table of the traces that ends with its step-12 MACE: the norms of
    steps 1-2, step 3's h_bar_2 MACE, the smallest merge denominator and its step, the largest
    norm (step 2's in these traces) and step 12's MACE of both stages."""
    regex = (rf"\| {re.escape(label)} \| {N}, {N}{re.escape(clipped)} \| {N} px \| {N} "
             rf"\({min_step}\) \| {N} \(2\) \| (?:h_bar_1 / h_bar_2 )?{N} / {N} px \|")
    return ("BENCHMARKS.md", regex,
            [_trace(name, 1, "grad_norm", 1), _trace(name, 2, "grad_norm", 1),
             _trace(name, 3, "mace", 0, "h_bar_2"),
             _trace(name, min_step, "merge_min_w", 2, "merge_2"),
             _trace(name, 2, "grad_norm", 1), _trace(name, 12, "mace", 1, "h_bar_1"),
             _trace(name, 12, "mace", 1, "h_bar_2")])


def _fig4_networks(sources):
    mace = _hour("run3_results")["fig4_mace"]
    nets = [v for k, v in mace.items() if k not in ("Identity", "ORB + RANSAC", "SIFT + RANSAC")]
    return cr.fixed(min(nets)), cr.fixed(max(nets)), cr.fixed(mace["Identity"])


RUN3_MIN = lambda sources: cr.fixed(_hour("run3_results")["wall_s_this_run"] / 60, 1)  # noqa
B, F, C = "bf16_noclip", "f32_noclip", "bf16_clip10"
PROSE += [  # issue 78, item 5: the hour budget's third run and the traces behind its clip
    ("docs/reproduce.md", rf"a third run finished: {N} minutes", [RUN3_MIN]),
    ("docs/reproduce.md", rf"networks within 1 px of the identity \({N}-{N} px against {N};",
     [lambda s: _fig4_networks(s)[0], lambda s: _fig4_networks(s)[1],
      lambda s: _fig4_networks(s)[2]]),
    ("docs/reproduce.md", rf"stage's MACE {N} px at step 3", [_trace(B, 3, "mace", 0, "h_bar_2")]),
    ("docs/reproduce.md", rf"the denominator reached {N} at step 6, where the gradient norm was"
                          rf"{S}([\d,]+),{S}then ([\d,]+), ([\d,]+) and infinite at step 9",
     [_trace(B, 6, "merge_min_w", 2, "merge_2"), _thousands(B, 6), _thousands(B, 7),
      _thousands(B, 8)]),
    ("docs/reproduce.md", rf"came down to {N} at{S}step 5", [_trace(F, 5, "merge_min_w", 2,
                                                                    "merge_2")]),
    ("BENCHMARKS.md", rf"\*\*finished in {N} min\*\*", [RUN3_MIN]),
    ("BENCHMARKS.md", rf"\| mixed bfloat16, no clip \(the budget before\) \| {N}, {N} \| {N} px "
                      rf"\| {N} \(6\) \|",
     [_trace(B, 1, "grad_norm", 1), _trace(B, 2, "grad_norm", 1),
      _trace(B, 3, "mace", 0, "h_bar_2"), _trace(B, 6, "merge_min_w", 3, "merge_2")]),
    _trace_row("float32, no clip", "", F, 5),
    _trace_row("mixed bfloat16, clip 10 (run 3)", " (clipped)", C, 9),
]

def _heldout_paper(group, test):
    """How many pairs of ``group`` in docs/camera_pairs/paper_seed13_heldout.json pass ``test``."""
    return lambda sources: str(sum(test(p) for p in _camera_file("paper_seed13_heldout")["pairs"]
                                   if p["group"] == group))


PROSE += [  # issue 79: the paper's protocol on the held-out seed 13
    ("BENCHMARKS.md", rf"\(`paper`\): mean {N} px \(goal <= 0.01\), (\d+) of 60 under{S}1 px; "
                      rf"with an exposure change \(`paper_exposure`\): (\d+) of 60 under 1 px "
                      rf"against SIFT \+ RANSAC's{S}(\d+) on the same pairs",
     [lambda sources: cr.fixed(
         _camera_file("paper_seed13_heldout")["groups"]["paper"]["estimator"]["mace"], 4),
      _heldout_paper("paper", lambda p: p["estimator_error"] < 1),
      _heldout_paper("paper_exposure", lambda p: p["estimator_error"] < 1),
      _heldout_paper("paper_exposure", lambda p: p["sift_ransac_error"] < 1)]),
]

def _scale(name):
    """docs/scale/``name``.json (written by ``experiments.benchmark_workers``)."""
    with open(os.path.join(ROOT, "docs", "scale", f"{name}.json")) as f:
        return json.load(f)


def _read(name, root=ROOT):
    with open(os.path.join(root, name)) as f:
        return f.read()


def test_generated_blocks_equal_what_the_json_gives():
    stale = cr.differing(ROOT)
    assert not stale, ("run python -m experiments.current_results --write:\n"
                       + "\n".join(stale.values()))


def _prose_wrong(entries, root=ROOT):
    """What differs from its JSON among ``entries`` (as ``PROSE``'s) in the docs under ``root``:
    one line per phrase that no text matches or that reads another number."""
    sources = cr.load_sources(root)
    wrong = []
    for name, pattern, expected in entries:
        matches = re.findall(pattern, _read(name, root))
        if not matches:
            wrong.append(f"{name}: no text matches {pattern!r} (reworded? update the list)")
        want = tuple(f(sources) for f in expected)
        for found in matches:
            found = found if isinstance(found, tuple) else (found,)
            if expected and found != want:
                wrong.append(f"{name}: {pattern!r} reads {found}, the JSON gives {want}")
    return wrong


def test_prose_numbers_equal_their_json():
    wrong = _prose_wrong(PROSE)
    assert not wrong, "\n".join(wrong)


def test_readme_types_no_generated_number_outside_its_table():
    text = _read("README.md")
    head, rest = text.split(cr.START)
    block, tail = rest.split(cr.END)
    generated = set(re.findall(r"\d+\.\d+", block))
    typed = generated & set(re.findall(r"\d+\.\d+", head + tail))
    assert not typed, f"README.md types {sorted(typed)} outside the generated table"


def test_check_names_the_file_whose_number_changed(tmp_path):
    for name in [*cr.SOURCES.values(), "README.md", "BENCHMARKS.md"]:
        os.makedirs(tmp_path / os.path.dirname(name), exist_ok=True)
        shutil.copy(os.path.join(ROOT, name), tmp_path / name)
    assert cr.differing(str(tmp_path)) == {}
    card_path = tmp_path / cr.SOURCES["card"]
    card = json.loads(card_path.read_text())
    card["evaluation"]["plain_coco_mini_test"]["model"]["stages"]["after_3_stages"]["mace"] = 0.5
    card_path.write_text(json.dumps(card))
    stale = cr.differing(str(tmp_path))
    assert sorted(stale) == ["BENCHMARKS.md", "README.md"]
    assert "**0.50**" in stale["README.md"]
    out, err = io.StringIO(), io.StringIO()  # what experiments.current_results prints and exits
    assert cr.run("check", str(tmp_path), out, err) == 1
    assert err.getvalue().count("differs from the JSON") == 2 and "**0.50**" in err.getvalue()
    assert cr.run("write", str(tmp_path), out) == 0
    assert json.loads(out.getvalue()) == {"rewritten": ["BENCHMARKS.md", "README.md"]}
    assert cr.differing(str(tmp_path)) == {} and cr.run("check", str(tmp_path), out, err) == 0
    (tmp_path / "README.md").write_text("no markers\n")
    assert cr.run("check", str(tmp_path), out, err) == 1 and "README.md: needs" in err.getvalue()
    try:
        cr.differing(str(tmp_path))
    except ValueError as e:
        assert "README.md" in str(e)
    else:
        raise AssertionError("a file without markers must be refused")


def test_stage_pairs_benchmarks_made_the_same_pairs():
    """BENCHMARKS says the stage-pairs benchmark made the same pairs before and after the change,
    for every thread count: the two JSONs' digests."""
    sources = cr.load_sources(ROOT)
    digests = {d for name in ("stage_pairs_before", "stage_pairs_after")
               for d in sources[name]["sha256"].values()}
    assert len(digests) == 1
    assert "carry the same SHA-256 of all pairs" in _read("BENCHMARKS.md")


# Issue 78, point 6: one number in one place. Each group below is one item of the walk;
# each failed on the docs before they were made to agree.
def latency(path, digits=2):
    """Expected text of a value of the reproduction's Table 2 (``eval/latency.json``)."""
    return num("reproduce_latency", path, digits)


def _joined_ms(key):
    return [num("results", f"{key}/{k}") for k in (1, 2, 3)]


TABLE2 = [  # the committed reproduction's Table 2, wherever a page shows it
    ("BENCHMARKS.md", rf"\| model forward `l_m` \| - \| 8\.31 ms \| {N} ms \|",
     [latency("l_m_ms")]),
    ("BENCHMARKS.md", rf"\| warp between stages `l_w` \(goal <= 3% of `l_m`\) \| - \| [^|]+ \| "
     rf"{N} ms \({N}%\) \|",
     [latency("l_w_ms", 3), lambda s: cr.fixed(100 * s["reproduce_latency"]["l_w_over_l_m"], 1)]),
    ("BENCHMARKS.md", rf"\| 1 stage \| 4\.87 ms \| [^|]+ \| \*\*{N} ms\*\* \|",
     [num("results", "table2_latency_ms/1")]),
    *[("BENCHMARKS.md", rf"\| {k} stages[^|]* \| {paper} ms \| [^|]+ \| \*\*{N} ms\*\* \({N}x\) \|",
       [num("results", f"table2_latency_ms/{k}"),
        latency(f"hierarchy/{k}/ratio_to_one_stage")]) for k, paper in ((2, r"11\.46"),
                                                                        (3, r"17\.85"))],
    ("BENCHMARKS.md", rf"\| sequence model, 1 / 2 / 3 stages[^|]*\| [^|]+ \| [^|]+ \| {N} / {N} / "
     rf"\*\*{N} ms\*\* \|", _joined_ms("sequence_latency_ms")),
    ("BENCHMARKS.md", rf"\| Table 2, latency \(bf16, CPU\) \| {N} / {N} / {N} ms \(sequence {N} / "
     rf"{N} / {N}\)", _joined_ms("table2_latency_ms") + _joined_ms("sequence_latency_ms")),
    ("BENCHMARKS.md", rf"3 sequence stages {N} ms on{S}the", [num("results",
                                                                   "sequence_latency_ms/3")]),
    ("BENCHMARKS.md", rf"in bfloat16 \({N} ms for the model alone", [latency("l_m_ms")]),
]


def test_table2_is_the_reproduction_json_on_every_page():
    """README's Table 2 row (generated) and BENCHMARKS.md's Table 2 section, its summary row and
    its mentions show the committed reproduction's latencies, not another run's."""
    wrong = _prose_wrong(TABLE2)
    assert not wrong, "\n".join(wrong)


GPU_CLAIM = re.compile(r"paper's (?:2019 )?GPU|GPU figure|the paper: its GPU")


def _gpu_claims(text):
    """The table rows and paragraphs of ``text`` that set a CPU's bfloat16 latency against the
    paper's GPU."""
    units = []
    for part in re.split(r"\n\s*\n", text):
        lines = part.splitlines()
        units += [line for line in lines if line.startswith("|")]
        units.append("\n".join(line for line in lines if not line.startswith("|")))
    return [u for u in units if GPU_CLAIM.search(u) and "bfloat16" in u and "CPU" in u]


def test_a_claim_against_the_papers_gpu_names_the_machine_and_its_load():
    """The CPU's bfloat16 latency beat the paper's GPU on one machine (the reproduction's,
    AVX-512/AMX, its load not recorded), not on others: each row or paragraph that sets them
    side by side names that machine and its load, as ``current_results`` gives them; once Table 2
    is measured again (``experiments.reproduce --refresh_latency``), the CPU it records."""
    sources = cr.load_sources(ROOT)
    measured = result_cells.latency_refreshed(sources)
    machine = measured["machine"]["cpu"] if measured else "AVX-512/AMX"
    assert machine in result_cells.latency_machine(sources) or "machine" in sources["results"]
    unnamed = [f"{name}: {unit[:120]!r}" for name in ("README.md", "BENCHMARKS.md")
               for unit in _gpu_claims(_read(name))
               if machine not in unit or "load" not in unit]
    assert _gpu_claims(_read("README.md")) and not unnamed, "\n".join(unnamed)


def _duration_sections(text):
    """The headings of the sections of ``text`` that give a duration for 4,000 steps."""
    found = []
    for section in re.split(r"\n(?=#+ )", text):
        for paragraph in re.split(r"\n\s*\n", section):
            if "4,000 steps" in paragraph and re.search(
                    r"an hour|\d h\b|\d hours?\b|\d minutes\b", paragraph):
                found.append(section.splitlines()[0])
                break
    return found


CPU_BUDGET_TIME = [
    ("docs/training.md", rf"three hierarchy stages took (\d+), (\d+){S}and (\d+) minutes on the "
     rf"CPU machine of BENCHMARKS\.md \(2 cores, x86_64 with AVX-512/AMX;",
     [lambda s, k=k: "%.0f" % (s["paper_card"]["stages"][k]["result"]["wall_s_this_run"] / 60)
      for k in range(3)]),
    ("docs/weights.md", rf"(\d+) \+ (\d+) \+ (\d+) minutes on the{S}CPU machine of BENCHMARKS\.md "
     rf"\(2 cores, x86_64 with AVX-512/AMX\)",
     [lambda s, k=k: "%.0f" % (s["paper_card"]["stages"][k]["result"]["wall_s_this_run"] / 60)
      for k in range(3)]),
    ("docs/training.md", rf"a training step took {N} s \(`semi_supervised/step_cost\.json`\),{S}"
     rf"{N} h for 4,000 steps",
     [num("semi_step_cost", "train_step_s/mixed_bfloat16/stn_homography"),
      lambda s: cr.fixed(4000 * cr.value(s, "semi_step_cost",
                                         "train_step_s/mixed_bfloat16/stn_homography") / 3600)]),
]


def test_a_cpu_budget_models_time_is_given_once_per_machine():
    """docs/training.md gave a CPU-budget model "about an hour" in one section and 1.5-1.7 h in
    another, each for "the 2-core CPU": now one section gives it per named machine, from the
    JSON that records it, and the others link there."""
    sections = _duration_sections(_read("docs/training.md"))
    assert sections == ["### The CPU budget"], sections
    wrong = _prose_wrong(CPU_BUDGET_TIME)
    assert not wrong, "\n".join(wrong)


def stage1_alone(sources):
    return cr.fixed(cr.value(sources, "table1", "1,1/mace_per_seed/0"))


TWO_EVALUATIONS = [  # Fig. 4's clipped 1-stage row and Table 1's unclipped seed 0: one model
    ("docs/reproduce.md", rf"its Fig\. 4 1-stage row, {N} px, is the hierarchy after one stage, "
     rf"with{S}the rule \(`eval/hierarchy\.json`: (\d+) of 300 estimates clipped at the "
     rf"context\), while Table 1's{S}1:1 seed 0, {N} px, is the network alone",
     [fig4("STN-Homography 1 stage"),
      count("reproduce_hierarchy", "model/rejected/0/outside_context"), stage1_alone]),
    ("README.md", rf"its 1:1 seed 0 is the 1-stage row's model without the clipping, {N} px apart",
     [lambda s: cr.fixed(cr.value(s, "table1", "1,1/mace_per_seed/0")
                         - cr.value(s, "results", "fig4_mace/STN-Homography 1 stage"))]),
]


def test_fig4_one_stage_and_table1_seed0_are_told_apart():
    """The committed Fig. 4 1-stage row (the hierarchy after one stage, clipped) and Table 1's
    1:1 seed 0 (the network alone) are two evaluations of one model; the docs call them so,
    with both numbers from their JSON."""
    wrong = _prose_wrong(TWO_EVALUATIONS)
    assert not wrong, "\n".join(wrong)


def test_an_assembled_fig4_says_so_beside_it():
    """README shows the committed Fig. 4: where results.json's models come from more than one
    run folder, the text beside the figure says it was assembled, and so does the figure's
    legend (results.json's ``assembled``, :func:`stnh_tf.paper.fig4_render.fig4_inputs`)."""
    def paths(node):
        if isinstance(node, str):
            return [node]
        return [p for item in (node.values() if isinstance(node, dict) else node)
                for p in paths(item)]

    dirs = paths(cr.value(cr.load_sources(ROOT), "results", "models"))
    readme = _read("README.md")
    figure = readme.index("(docs/reproduce_cpu/figures/fig4_mace_bars.png)")
    beside = readme[figure:].split("\n\n")[1]
    if len({os.path.dirname(d) for d in dirs}) > 1:
        assert "assembled" in beside, beside
        assert cr.value(cr.load_sources(ROOT), "results", "assembled") is True


def _shipped_folders(root=ROOT):
    weights = os.path.join(root, "stnh_tf", "weights")
    return sorted(d for d in os.listdir(weights)
                  if os.path.isfile(os.path.join(weights, d, "model_card.json")))


SCHEDULE = "evaluation/model/stages/after_{}_stages/mace"
SCHEDULE_CARD = [  # docs/weights.md's section on the paper's-schedule weights, from their card
    ("docs/weights.md", rf"91,000 steps for each of the{S}(\d+) stages, on 184,800 pairs",
     [lambda s: str(len(s["schedule_card"]["stages"]))]),
    ("docs/weights.md", rf"\(stage 1: (\d+) chunks, stage 2: (\d+),{S}stage 3: (\d+);",
     [lambda s, k=k: str(len(s["schedule_card"]["stages"][k]["chunks"])) for k in (0, 1, 2)]),
    ("docs/weights.md", rf"\*\*{N} px\*\* after stage 1, \*\*{N}\*\* after stage 2, \*\*{N}\*\* after "
     rf"stage 3 \(identity {N};{S}paper 5\.83 / 2\.6 / 1\.57",
     [num("schedule_card", SCHEDULE.format(k)) for k in (1, 2, 3)]
     + [num("schedule_card", "evaluation/identity/mace")]),
    ("docs/weights.md", rf"search\): {N} px after stage 1, {N} after 2 stages, {N} after 3 "
     rf"\(photometric {N} / {N} /{S}{N}; identity {N}\)",
     [check("", k, "schedule_card") for k in (1, 2, 3)]
     + [check("photometric_", k, "schedule_card") for k in (1, 2, 3)]
     + [num("schedule_card", f"{CHECK}/identity_mace")]),
]


def test_every_shipped_model_is_named_where_users_look():
    """Each folder of shipped weights (a model card in ``stnh_tf/weights/``) is named in
    README's usage and has its section in docs/weights.md, whose numbers come from its card."""
    readme, weights = _read("README.md"), _read("docs/weights.md")
    usage = readme.split("## Estimate a homography")[1].split("\n## ")[0]
    headings = re.findall(r"^## .*$", weights, re.M)
    missing = [f for f in _shipped_folders() if f"`{f}/`" not in usage
               or not any(f"stnh_tf/weights/{f}/" in h for h in headings)]
    assert _shipped_folders() and not missing, missing
    wrong = _prose_wrong(SCHEDULE_CARD)
    assert not wrong, "\n".join(wrong)


def test_ablation_table_is_the_json_s():
    """BENCHMARKS.md's ablation table (issue 79, item 5) is what
    :func:`stnh_tf.evaluation.ablation.table` renders from its committed JSON."""
    from stnh_tf.evaluation import ablation

    text = _read("BENCHMARKS.md")
    for tag, name in (("seed0", "ablation_seed0_20"), ("seed0-60", "ablation_seed0_60"),
                      ("seed0-60-after", "ablation_seed0_60_a02fe78"),
                      ("seed13-60-before", "ablation_seed13_60_aa8d8d3"),
                      ("seed13-60-after", "ablation_seed13_60_b960763"),
                      ("seed0-60-d947ff0", "ablation_seed0_60_d947ff0"),
                      ("seed0-60-d228e4c", "ablation_seed0_60_d228e4c"),
                      ("seed0-60-bc2d7fb", "ablation_seed0_60_bc2d7fb"),
                      ("seed13-60-bc2d7fb", "ablation_seed13_60_bc2d7fb"),
                      ("seed0-60-88a648c", "ablation_seed0_60_88a648c"),
                      ("seed13-60-88a648c", "ablation_seed13_60_88a648c"),
                      ("seed0-60-febe404", "ablation_seed0_60_febe404"),
                      ("seed13-60-febe404", "ablation_seed13_60_febe404"),
                      ("seed0-60-56e6384", "ablation_seed0_60_56e6384"),
                      ("seed0-60-7d229e5", "ablation_seed0_60_7d229e5"),
                      ("seed13-60-56e6384", "ablation_seed13_60_56e6384"),
                      ("seed13-60-7d229e5", "ablation_seed13_60_7d229e5"),
                      ("urban100-b21ba37", "ablation_urban100_b21ba37"),
                      ("urban100-d8ab62b", "ablation_urban100_d8ab62b"),
                      ("seed0-60-d8ab62b", "ablation_seed0_60_d8ab62b"),
                      ("seed13-60-d8ab62b", "ablation_seed13_60_d8ab62b"),
                      ("urban100-5f57abf", "ablation_urban100_5f57abf")):
        start, end = f"<!-- ablation-{tag}:start -->\n", f"\n<!-- ablation-{tag}:end -->"
        block = text[text.index(start) + len(start):text.index(end)]
        assert block == ablation.table(_camera_file(name)), tag


def _good_flagged(name, group="all"):
    return _camera_file(name)["ablations"]["default"]["groups"][group]["good_flagged"]


def test_clipped_pixels_numbers_are_the_json_s():
    """BENCHMARKS.md's counts for the clipped pixels left out (issue 79, 2026-12-06) are those of
    the committed ablations before (bc2d7fb) and after (88a648c)."""
    text = " ".join(_read("BENCHMARKS.md").split())

    def cell(name, group, key):
        return _camera_file(name)["ablations"]["default"]["groups"][group][key]

    pairs = [[f"ablation_seed{s}_60_{c}" for c in ("bc2d7fb", "88a648c")] for s in (0, 13)]
    (b0, a0), (b13, a13) = pairs
    assert (f"successes {cell(b0, 'all', 'successes')} -> {cell(a0, 'all', 'successes')} of 480 "
            f"on seed 0 and {cell(b13, 'all', 'successes')} -> {cell(a13, 'all', 'successes')} "
            f"on seed 13, good estimates flagged {_good_flagged(b0)} -> {_good_flagged(a0)} and "
            f"{_good_flagged(b13)} -> {_good_flagged(a13)}, no silent failure") in text
    assert all(cell(n, "all", "silently_failed") == 0 for n in (a0, a13))
    exposure = [_good_flagged(n, "paper_exposure") for n in (b0, a0, b13, a13)]
    assert (f"good estimates flagged go from {exposure[0]} to {exposure[1]} (seed 0) and from "
            f"{exposure[2]} to {exposure[3]} (seed 13), and seed 0's mean from "
            f"{cell(b0, 'paper_exposure', 'mace'):.3g} to "
            f"{cell(a0, 'paper_exposure', 'mace'):.3g} px") in text
    assert f"the mean rises to {cell(a13, 'paper_exposure', 'mace'):.3g} px" in text


def test_two_flags_measured_where_the_images_say_something_numbers_are_the_json_s():
    """BENCHMARKS.md's counts for the move and ambiguity flags' change (issue 79, 2026-12-06)
    are those of the committed ablation and benchmark JSON."""
    text = " ".join(_read("BENCHMARKS.md").split())
    counts = [_good_flagged(f"ablation_seed0_60_{c}") for c in ("d947ff0", "d228e4c", "bc2d7fb")]
    held = [_good_flagged(f"ablation_seed13_60_{c}") for c in ("b960763", "bc2d7fb")]
    assert (f"go from {counts[0]} to {counts[1]} (the move) and {counts[2]} (both) on seed 0, and "
            f"from {held[0]} to {held[1]} on the held-out seed 13") in text
    low = _camera_file("low_overlap_seed0_bc2d7fb")["groups"]["low_overlap"]
    est, sift = low["estimator"], low["sift_ransac"]
    good = est["count"] - est["flag"]["bad"]
    assert (f"{est['flag']['flagged_good']} of {good} good estimates flagged "
            f"({100 * est['flag']['flagged_good'] / good:.1f}%") in text
    assert (f"SIFT + RANSAC has {round(sift['success_rate'] * sift['count'])} of {sift['count']} "
            f"successes against the estimator's {round(est['success_rate'] * est['count'])}") in text


def test_speed_beside_sift_in_low_light_and_at_640_numbers_are_the_json_s():
    """BENCHMARKS.md's speed table of issue 79 (320 x 240 and 640 x 480, camera and low light)
    and the ratios quoted below it are those of the committed benchmark JSON."""
    text = _read("BENCHMARKS.md")
    ratio = {}

    def cell(m):
        return (f"{round(m['success_rate'] * m['count'])} of {m['count']}, "
                f"{m['mace']:.2f} px, {m['ms_per_pair']:.0f} ms")

    for scale, size in ((1, "320 x 240"), (2, "640 x 480")):
        for deg, label in (("camera", "camera"), ("low_light", "low light")):
            groups = _camera_file(f"speed_seed13_{deg}_scale{scale}")["groups"]
            for group in ("within", "1-2x", "2-4x", "all"):
                e, s = groups[group]["estimator"], groups[group]["sift_ransac"]
                ratio[scale, deg, group] = e["ms_per_pair"] / s["ms_per_pair"]
                assert (f"| {size}, {label} | {group} | {cell(e)} | {cell(s)} | "
                        f"{ratio[scale, deg, group]:.2f}x |") in text
                if scale == 2:  # "with as many successes or more on every group"
                    assert e["success_rate"] >= s["success_rate"], (deg, group)
    prose = " ".join(text.split())
    for scale, head in ((1, "the goal is not met: "), (2, "it takes ")):
        w, lw = ratio[scale, "camera", "within"], ratio[scale, "low_light", "within"]
        a, la = ratio[scale, "camera", "all"], ratio[scale, "low_light", "all"]
        if scale == 1:
            assert (f"{head}{w:.2f}x on `within` and {lw:.2f}x in low light ({a:.1f}x and "
                    f"{la:.1f}x over the set)") in prose
        else:
            assert (f"{head}{w:.2f}x SIFT + RANSAC's time on `within` and {lw:.2f}x in low light "
                    f"({a:.2f}x and {la:.2f}x over the set)") in prose
    assert "with as many successes or more on every group" in prose
    low = _camera_file("speed_seed13_low_light_scale1")["groups"]["within"]["estimator"]
    assert (f"the low-light `within` median is {low['median_ms_per_pair']:.0f} ms against its "
            f"mean's {low['ms_per_pair']:.0f}") in prose


def test_zen4_step_per_onednn_primitive_numbers_are_the_json_s():
    """BENCHMARKS.md's per-convolution table of a stage's step on the Zen 4 (issue 77, item 5)
    and the step times of the settings tried are those of the committed benchmark JSON."""
    text = _read("BENCHMARKS.md")
    with open(os.path.join(ROOT, "paper_schedule", "logs",
                           "training_step_zen4_layers_cpu.json")) as f:
        run = json.load(f)

    def shapes(profile):
        out = {}
        for x in profile["primitives"]:
            if x["kind"] == "convolution":
                ci, co, h = map(int, re.search(r"ic(\d+)oc(\d+)_ih(\d+)", x["problem"]).groups())
                out.setdefault((ci, co, h), {})[x["propagation"]] = x
        return out

    bf16, fp32 = (shapes(run["onednn_layers"][p]) for p in ("mixed_bfloat16", "float32"))
    assert len(bf16) == 6
    for (ci, co, h), passes in bf16.items():
        cells = [" / ".join(f"{d[(ci, co, h)].get(p, {}).get('ms_per_step', 0):.0f}"
                            for p in ("forward_training", "backward_data", "backward_weights"))
                 for d in (bf16, fp32)]
        layers = passes["forward_training"]["calls_per_step"]
        assert f"| {ci} -> {co} at {h} x {h} | {layers} | {cells[0]} | {cells[1]} |" in text
    prose = " ".join(text.split())
    step = {p: f"{v['stn_homography']:.2f}" for p, v in run["train_step_s"].items()}
    by_pass = run["onednn_layers"]["mixed_bfloat16"]["ms_per_step_by_propagation"]
    assert (f"The step took {step['mixed_bfloat16']} s in mixed bfloat16 and {step['float32']} s "
            f"in float32") in prose
    assert (f"Of oneDNN's {run['onednn_layers']['mixed_bfloat16']['ms_per_step']:,.0f} ms in "
            f"mixed bfloat16, the backward-weights passes take {by_pass['backward_weights']:.0f}, "
            f"backward-data {by_pass['backward_data']:.0f}, forward "
            f"{by_pass['forward_training']:.0f}") in prose
    big = bf16[64, 64, 128]
    assert (f"({big['backward_weights']['ms_per_step']:.0f} against "
            f"{big['forward_training']['ms_per_step']:.0f} ms)") in prose
    assert {x["backward_weights"]["implementation"] for x in bf16.values()} == {
        "jit_bf16:avx512_core_bf16"}
    tried_settings = (
        ("caller_thread", "mixed_bfloat16", "TF_ONEDNN_THREADPOOL_USE_CALLER_THREAD", "1"),
        ("no_memuse_opt", "mixed_bfloat16", "TF_MKL_OPTIMIZE_PRIMITIVE_MEMUSE", "false"),
        ("fpmath_bf16", "float32", "TF_SET_ONEDNN_FPMATH_MODE", "BF16"))
    for name, policy, variable, value in tried_settings:
        with open(os.path.join(ROOT, "paper_schedule", "logs",
                               f"training_step_zen4_{name}_cpu.json")) as f:
            tried = json.load(f)
        seconds = tried["train_step_s"][policy]["stn_homography"]
        row = next(line for line in text.splitlines() if f"training_step_zen4_{name}_cpu" in line)
        assert row.startswith(f"| `{variable}={value}`, ") and row.endswith(f" | {seconds:.2f} |")
        assert tried["environment"].get(variable) == value and list(tried["train_step_s"]) == [
            policy]
    assert "TF_ONEDNN" not in str(run["environment"]) and "TF_MKL" not in str(run["environment"])


def test_paper_protocol_pair_by_pair_against_no_feature_start_is_the_json_s():
    """BENCHMARKS.md's pair-by-pair comparison of the default with ``features="none"`` on the
    paper's protocol (issue 79, 2026-12-06) is that of the committed per-pair JSON."""
    text = _read("BENCHMARKS.md")

    def errors(seed, features, group):
        pairs = _camera_file(f"paper_seed{seed}_features_{features}_7d08166")["pairs"]
        return [(p["index"], p["estimator_error"]) for p in pairs if p["group"] == group]

    def cell(e):
        values = [v for _, v in e]
        mean = sum(values) / len(values)
        return (f"{mean:.4f}" if mean < 0.1 else f"{mean:.3g}") + \
            f", {sum(v < 1 for v in values)} of {len(values)}"

    for seed in (0, 13):
        for group in ("paper", "paper_exposure"):
            on, off = errors(seed, "fallback", group), errors(seed, "none", group)
            assert [i for i, _ in on] == [i for i, _ in off]
            worse = sum(a > b + 0.01 for (_, a), (_, b) in zip(on, off))
            assert f"| {seed}, `{group}` | {cell(on)} | {cell(off)} | {worse} |" in text


def test_the_unclipped_pixel_floor_changes_no_ablation_cell():
    """BENCHMARKS.md says the ``default`` rows at a63dbd3 (with ``checks.MIN_UNCLIPPED``) give
    every count and mean of those at 88a648c (before it): the committed JSON agree."""
    assert "give every count and mean of the tables above on every group of both seeds" in " ".join(
        _read("BENCHMARKS.md").split())
    for seed in (0, 13):
        before, after = (_camera_file(f"ablation_seed{seed}_60_{c}")["ablations"]["default"]
                         ["groups"] for c in ("88a648c", "a63dbd3"))
        assert set(before) == set(after) and len(before) == 9
        for group in before:  # every cell but the times: errors, counts, flags, search
            untimed = [{k: v for k, v in cells[group].items() if "ms_per_pair" not in k}
                       for cells in (before, after)]
            assert untimed[0] == untimed[1] and len(untimed[0]) >= 10, group


def test_the_move_confirmation_numbers_are_the_json_s():
    """BENCHMARKS.md's "The move confirmation without its NCC floor" (issue 79, 2026-12-07):
    against a63dbd3 every untimed cell of both seeds is the same but the flag's counts of seed
    0's ``paper_exposure`` (and so of all its groups) and the ``searched`` shares; the counts
    and shares the prose gives are the JSON's."""
    text = " ".join(_read("BENCHMARKS.md").split())
    changed = {}
    for seed in (0, 13):
        before, after = (_camera_file(f"ablation_seed{seed}_60_{c}")["ablations"]["default"]
                         ["groups"] for c in ("a63dbd3", "febe404"))
        assert set(before) == set(after) and len(before) == 9
        for group in before:
            keys = [k for k in before[group] if "ms_per_pair" not in k and k != "searched"]
            differ = [k for k in keys if before[group][k] != after[group][k]]
            if differ:
                changed[seed, group] = differ
        assert after["all"]["silently_failed"] == 0
    assert set(changed) == {(0, "paper_exposure"), (0, "all")}
    assert all(set(k) == {"flag", "flag_patch_frame", "good_flagged"} for k in [
        set(v) for v in changed.values()])
    b0, a0 = (_camera_file(f"ablation_seed0_60_{c}")["ablations"]["default"]["groups"]
              for c in ("a63dbd3", "febe404"))
    before, after = (g["paper_exposure"]["good_flagged"] for g in (b0, a0))
    n = a0["paper_exposure"]["count"]
    assert (f"go from {before} to {after} of {n} ({100 * before / n:.1f}% -> "
            f"{100 * after / n:.1f}%;") in text
    seed13 = _camera_file("ablation_seed13_60_febe404")["ablations"]["default"]["groups"]
    good13 = seed13["paper_exposure"]["successes"]
    assert f"on seed 13 nothing changes ({seed13['paper_exposure']['good_flagged']} of {good13})" \
        in text
    assert (f"seed 0 over all groups {b0['all']['searched']:.3f} -> "
            f"{a0['all']['searched']:.3f})") in text
    assert "give every cell of the two tables above but the times on both seeds" in text
    for seed in (0, 13):  # the review's fix (660f1ff) changes no untimed cell
        runs = [_camera_file(f"ablation_seed{seed}_60_{c}")["ablations"]["default"]["groups"]
                for c in ("febe404", "660f1ff")]
        untimed = [{g: {k: v for k, v in cells.items() if "ms_per_pair" not in k}
                    for g, cells in run.items()} for run in runs]
        assert untimed[0] == untimed[1] and len(untimed[0]) == 9


def _baseline_cells(before, after, group, wide):
    """The row of BENCHMARKS.md's "SIFT + RANSAC's check on whole images" table: SIFT before and
    after, SIFT's wide settings after (where the set has them), ORB before and after, the
    estimator (before: its run is the earlier one)."""
    cells = [(before, "sift_ransac"), (after, "sift_ransac"),
             *([(after, "sift_wide")] if wide else []), (before, "orb_ransac"),
             (after, "orb_ransac"), (before, "estimator")]
    return [f for source, method in cells for f in (cam(source, group, method, "ok"),
                                                     cam(source, group, method, "count"),
                                                     cam(source, group, method, "mace"))]


PROSE += [  # the baselines' plausibility check at image_b's centre (c3ba783)
    ("BENCHMARKS.md",
     rf"\| `{group}` \| " + (rf"(\d+) of (\d+), {N} px \| " * 2)
     + (rf"(\d+) of (\d+), {N} px \| " if wide else r"- \| ")
     + (rf"(\d+) of (\d+), {N} px \| " * 3).rstrip(),
     _baseline_cells(before, after, group, wide))
    for before, after, groups, wide in (
        ("camera0_late", "camera0_baselines_fixed", ("within", "1-2x", "2-4x"), True),
        ("camera0_wide_late", "camera0_wide_baselines_fixed", ("wide", "wide_low_light"), True),
        ("camera0_paper", "camera0_paper_baselines_fixed", ("paper", "paper_exposure"), False))
    for group in groups]


def test_the_80_px_ambiguity_reach_changes_no_untimed_cell():
    """BENCHMARKS.md, "Repeated patterns up to 80 px": before (56e6384) and after (7d229e5) give
    every cell but the times on both seeds, as the prose says."""
    text = " ".join(_read("BENCHMARKS.md").split())
    assert "Every cell but the times is the same before and after on both seeds" in text
    for seed in (0, 13):
        runs = [_camera_file(f"ablation_seed{seed}_60_{c}") for c in ("56e6384", "7d229e5")]
        assert [r["commit"] for r in runs] == ["56e6384", "7d229e5"]
        untimed = [{g: {k: v for k, v in cells.items() if "ms_per_pair" not in k}
                    for g, cells in r["ablations"]["default"]["groups"].items()} for r in runs]
        assert untimed[0] == untimed[1] and len(untimed[0]) == 9


def test_the_tile_ambiguity_numbers_are_the_json_s():
    """BENCHMARKS.md, "Repeated patterns in perspective": Urban100's silent failures with the
    rule and without it (the row switched off), the good estimates it flags more, and the
    coco_mini seeds unchanged from 7d229e5 but for the times."""
    text = " ".join(_read("BENCHMARKS.md").split())
    urban = _camera_file("ablation_urban100_b21ba37")["ablations"]
    on, off = urban["default"]["groups"]["all"], urban["min_tile_ambiguity_gap"]["groups"]["all"]
    assert (f"silent failures go from {off['silently_failed']} to {on['silently_failed']} (those "
            f"10 px or more off from {off['unflagged_far']} to {on['unflagged_far']})") in text
    assert (f"{on['good_flagged'] - off['good_flagged']} right estimates more are flagged (of "
            f"{on['successes']};") in text
    for seed in (0, 13):
        runs = [_camera_file(f"ablation_seed{seed}_60_{c}") for c in ("7d229e5", "b21ba37")]
        untimed = [{g: {k: v for k, v in cells.items() if "ms_per_pair" not in k}
                    for g, cells in r["ablations"]["default"]["groups"].items()} for r in runs]
        assert untimed[0] == untimed[1] and runs[1]["commit"] == "b21ba37"


def test_the_late_start_numbers_are_the_json_s():
    """BENCHMARKS.md, "The late start on a poorly aligned estimate": Urban100's silent failures
    and successes with the trigger and without it (the row switched off, which gives b21ba37's
    default on every untimed cell of the three sets), no good estimate more flagged, and the
    coco_mini seeds' successes, flags and failures unchanged."""
    text = " ".join(_read("BENCHMARKS.md").split())

    def untimed(groups):
        return {g: {k: v for k, v in cells.items() if "ms_per_pair" not in k}
                for g, cells in groups.items()}

    for name in ("urban100", "seed0_60", "seed13_60"):
        run = _camera_file(f"ablation_{name}_d8ab62b")
        assert run["commit"].startswith("d8ab62b")
        rows = run["ablations"]
        before = _camera_file(f"ablation_{name}_b21ba37")["ablations"]["default"]["groups"]
        assert untimed(rows["late_start_below_ncc"]["groups"]) == untimed(before), name
        on, off = rows["default"]["groups"]["all"], rows["late_start_below_ncc"]["groups"]["all"]
        assert on["good_flagged"] == off["good_flagged"], name
        if name == "urban100":
            assert (f"silent failures go from {off['silently_failed']} to "
                    f"{on['silently_failed']} and its successes from {off['successes']} to "
                    f"{on['successes']}") in text
        else:
            for g, cells in rows["default"]["groups"].items():
                for key in ("successes", "good_flagged", "silently_failed", "unflagged_far"):
                    assert cells[key] == before[g][key], (name, g, key)


def test_the_whole_images_floor_numbers_are_the_json_s():
    """BENCHMARKS.md, "The alignment floor on the whole images": Urban100's silent failures
    before (d8ab62b) and with the floor (5f57abf), no good estimate more flagged, and the
    coco_mini seeds' untimed cells unchanged."""
    text = " ".join(_read("BENCHMARKS.md").split())

    def untimed(name):
        groups = _camera_file(name)["ablations"]["default"]["groups"]
        return {g: {k: v for k, v in cells.items() if "ms_per_pair" not in k}
                for g, cells in groups.items()}

    before, after = (untimed(f"ablation_urban100_{c}")["all"] for c in ("d8ab62b", "5f57abf"))
    assert (f"silent failures go from {before['silently_failed']} to "
            f"{after['silently_failed']} (the 67 px estimate flagged), no good estimate more "
            f"flagged") in text
    assert before["good_flagged"] == after["good_flagged"]
    for seed in (0, 13):
        assert untimed(f"ablation_seed{seed}_60_d8ab62b") == untimed(
            f"ablation_seed{seed}_60_5f57abf")
        assert _camera_file(f"ablation_seed{seed}_60_5f57abf")["commit"].startswith("5f57abf")


def test_generated_blocks_read_and_write_a_crlf_checkout(tmp_path):
    """A checkout with CRLF line ends (Windows, ``core.autocrlf``): the generated blocks read as
    current (``differing`` compares the text as LF), and ``write`` of a stale block keeps the
    document's CRLF everywhere (reading it with the newlines kept had made every block stale
    there, and writing mixed the line ends)."""
    import shutil

    from stnh_tf.paper import results_json

    for rel in set(results_json.SOURCES.values()):
        os.makedirs(tmp_path / os.path.dirname(rel), exist_ok=True)
        shutil.copy(os.path.join(ROOT, rel), tmp_path / rel)
    for name in ("README.md", "BENCHMARKS.md"):
        text = _read(name)
        (tmp_path / name).write_bytes(text.replace("\n", "\r\n").encode())
    assert cr.differing(str(tmp_path)) == {}
    readme = (tmp_path / "README.md").read_bytes()
    start = readme.index(cr.START.encode()) + len(cr.START) + 2
    (tmp_path / "README.md").write_bytes(readme[:start] + b"stale\r\n" + readme[start:])
    assert cr.write(str(tmp_path)) == ["README.md"]
    assert (tmp_path / "README.md").read_bytes() == readme
