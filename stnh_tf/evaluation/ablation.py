"""The ablation table of ``estimate_images``' default (issue 79, item 5), the library core of
``experiments.ablate_estimator``: each rule of :meth:`EstimateOptions.photographs()
<stnh_tf.inference.options.EstimateOptions.photographs>` switched off in turn by an options value
alone (:data:`ABLATIONS`), scored on camera pairs by the camera-pair benchmark's own functions
(:func:`stnh_tf.evaluation.camera_pairs.run_estimator`, ``pair_errors``, ``summarize``).

Per ablation and group of the pairs (and over ``"all"``): successes (error under
``success_px``), the mean and median error, good estimates flagged (error at most
``flag_error_px``, flagged implausible), silent failures (error above ``flag_error_px``, not
flagged), estimates 10 px or more off unflagged, and the time per pair. Errors are the
benchmark's (:mod:`stnh_tf.evaluation.camera_pairs`: at the image's corners, at the central
patch's in the paper's-protocol groups).

Off means off as far as an options value reaches: ``Thresholds`` are finite, so a rule whose
threshold is an upper bound is switched off with :data:`OFF`, which no measure reaches, and an
infinite measure (an undefined corner precision) still trips it; each entry says what stays.
Rules no options value switches off: :data:`WITHOUT_SWITCH`.

    >>> options_for("search").search, options_for("max_corner_std").thresholds.max_corner_std
    ('none', 1000000000.0)
    >>> resolve(["verify", "search"])
    ('default', 'verify', 'search')
"""

from __future__ import annotations

import collections
import dataclasses
import math

import numpy as np

from stnh_tf.data import camera_motions
from stnh_tf.evaluation import camera_pairs
from stnh_tf.inference.options import EstimateOptions, Thresholds

OFF = 1e9
"""A threshold no measure reaches (px or ratio): ``Thresholds`` must be finite."""

UNFLAGGED_FAR_PX = 10.0
"""An estimate this far off or more, unflagged, is counted apart (issue 79's goal: none)."""

DEFAULT = "default"
"""The reference row: ``EstimateOptions.photographs()`` as it is."""

_TRAINED_CORNER_RULE = Thresholds().implausible_corner_shift

ABLATIONS = {
    "features": (
        "the feature start, early and late (SIFT + MAGSAC matches refined by the network), and "
        "with it the wide-motion corner rule: the flag's corner rule is the trained range's "
        "(implausible_corner_shift, 48 px) again", {"features": "none"}),
    "search": ("the search of poorly aligned estimates (translation peaks, then ECC)",
               {"search": "none"}),
    "refine_images": (
        "the whole-image ECC refinement, with its one resolution and the move confirmation; "
        "the patch ECC refinement stays", {"refine": "ecc"}),
    "refine": (
        "every ECC refinement (patch and whole-image, with the move confirmation); the ECC "
        "check of the flag stays", {"refine": "none"}),
    "resolution_sigma": ("the one resolution of the whole-image refinement (no blur of the "
                         "sharper image of a zoom)", {"thresholds": {"resolution_sigma": 0.0}}),
    "max_refine_move": (
        "the guard that drops a patch refinement moving the corners by more than "
        "max_refine_move (16 px)", {"thresholds": {"max_refine_move": OFF}}),
    "verify": (
        "the ECC check of the flag and all it holds: ECC's move and its confirmation, the "
        "corner precision, the undetermined rule, the ambiguity test", {"verify": "none"}),
    "precision_ambiguity": (
        "the corner-precision, undetermined and ambiguity rules together: of the ECC check "
        "only ECC's move (and its confirmation) stays, so that against 'verify' this row "
        "says what the move rule buys; an undefined precision still flags",
        {"thresholds": {"max_corner_std": OFF, "undetermined_corner_std": OFF,
                        "min_ambiguity_gap": 0.0, "min_tile_ambiguity_gap": 0.0}}),
    "max_corner_std": (
        "the corner-precision flag (precision worse than max_corner_std, 1.5 px); an undefined "
        "precision (inf) still flags", {"thresholds": {"max_corner_std": OFF}}),
    "corner_std_classical": (
        "the cluster-robust corner precision: the classical covariance of independent pixels "
        "(corner_std_tile=0) with its 1 px threshold, the rule before issue 64",
        {"thresholds": {"corner_std_tile": 0, "max_corner_std": 1.0}}),
    "undetermined_corner_std": (
        "the identity in place of an estimate the images leave undetermined (precision worse "
        "than 400 px); an undefined precision (inf) still does it",
        {"thresholds": {"undetermined_corner_std": OFF}}),
    "min_ambiguity_gap": (
        "the ambiguity flag (another shift aligning within 0.005 of the estimate); a shift "
        "aligning better than the estimate (a negative gap) still flags",
        {"thresholds": {"min_ambiguity_gap": 0.0}}),
    "min_tile_ambiguity_gap": (
        "the tile-by-tile ambiguity flag (a second peak within 0.1 of the estimate's NCC, the "
        "median over 80 x 80 tiles)", {"thresholds": {"min_tile_ambiguity_gap": 0.0}}),
    "min_alignment_ncc": (
        "the flag's alignment rule (the patch's NCC, and the whole work images', below 0.7); "
        "an undefined or negative NCC still flags",
        {"thresholds": {"min_alignment_ncc": 0.0}}),
    "corner_rule": ("the flag's corner rule (a patch corner moved beyond coarse_corner_shift, "
                    "128 px)", {"thresholds": {"coarse_corner_shift": OFF}}),
    "corner_rule_trained": (
        "the wide-motion corner rule: the flag's corner rule is the trained range's (48 px) "
        "as without the feature start",
        {"thresholds": {"coarse_corner_shift": _TRAINED_CORNER_RULE}}),
    "late_start_below_ncc": (
        "the late feature start's trigger on an unflagged estimate aligning the work images "
        "below late_start_below_ncc (0.95); the trigger on a flagged one stays",
        {"thresholds": {"late_start_below_ncc": 0.0}}),
    "flat": ("the flat rule (the identity, flagged, for a patch varying less than half a grey "
             "level)", {"thresholds": {"min_patch_std": 0.0}}),
}
"""Ablation name -> ``(what it switches off, changes to EstimateOptions.photographs())``: the
changes are ``EstimateOptions`` fields, ``"thresholds"`` a dict of ``Thresholds`` fields
(:func:`options_for`)."""

WITHOUT_SWITCH = {
    "the early feature start (before the search; a confirmed start skips it)":
        "fixed by features='fallback' with a search and no retry (features.estimate)",
    "the late feature start's trigger on a flagged estimate": "no field (features.late_wanted)",
    "the feature start at the images' own resolution":
        "no field; never runs where the images fit in 320 x 240 (make_camera_pairs' default "
        "scale)",
    "the start G itself as the feature start's candidate": "no field (features.from_start)",
    "the ECC move rule alone (max_verify_move)":
        "the same number sets the whole-image refinement's second start and the move "
        "confirmation; 'precision_ambiguity' against 'verify' isolates it",
    "the move confirmation":
        "tied to refine='images' (it compares the whole images' alignments, no threshold of "
        "its own); 'refine_images' removes it with the refinement",
    "the stage gate and the mirror fill":
        "estimate_images sets gate_stages=False and fill='zeros' (the image is the context)",
    "clipped pixels left out of the alignment measures":
        "no field (stnh_tf.pixels.unclipped); measured by runs before and after it (BENCHMARKS.md)",
}
"""Rules of ``photographs()`` that no options value switches off alone, and why. Numbers that
parametrise a measure or an algorithm (``min_overlap``, ``verified_ncc``, ``search_below_ncc``,
``refine_iterations``, ``refine_eps``) are not rules and have no row."""


def options_for(name: str, base: EstimateOptions | None = None) -> EstimateOptions:
    """``base`` (``None``: ``EstimateOptions.photographs()``) with :data:`ABLATIONS`' changes of
    ``name`` (``"default"``: none). Raises ``ValueError`` for an unknown name."""
    resolve([name])
    options = EstimateOptions.photographs() if base is None else base
    if name == DEFAULT:
        return options
    changes = dict(ABLATIONS[name][1])
    thresholds = changes.pop("thresholds", {})
    return dataclasses.replace(options, **changes, thresholds=dataclasses.replace(
        options.thresholds, **thresholds))


def resolve(names) -> tuple:
    """The ablations ``names`` asks for, ``"default"`` first (the reference of the deltas),
    each once, in :data:`ABLATIONS`' order for ``"all"``. Raises ``ValueError`` naming the
    unknown ones and the known ones."""
    names = [n.strip() for n in names if n.strip()]
    unknown = [n for n in names if n not in ABLATIONS and n not in (DEFAULT, "all")]
    if unknown or not names:
        raise ValueError(f"unknown ablation(s) {unknown or names}; choose 'all' or among "
                         f"{', '.join((DEFAULT, *ABLATIONS))}.")
    wanted = tuple(ABLATIONS) if "all" in names else names
    return tuple(dict.fromkeys([DEFAULT, *wanted]))


def _take(pairs, max_pairs_per_group: int, taken: collections.Counter) -> list:
    """The pairs of ``pairs`` whose group has fewer than ``max_pairs_per_group`` in ``taken``
    (0: all), counted there."""
    chosen = []
    for p in pairs:
        if not max_pairs_per_group or taken[p.group] < max_pairs_per_group:
            taken[p.group] += 1
            chosen.append(p)
    return chosen


def cell(run: dict, errors, patch_errs, success_px=camera_pairs.SUCCESS_PX,
         flag_error_px=camera_pairs.FLAG_ERROR_PX) -> dict:
    """One ablation's numbers on one group: :func:`stnh_tf.evaluation.camera_pairs.summarize`
    (``count``, ``mace``: the mean error, ``median``, ``ms_per_pair``, ``flag``, ...) with
    ``successes`` (error under ``success_px``), ``good_flagged`` (at most ``flag_error_px``,
    flagged), ``silently_failed`` (above ``flag_error_px``, not flagged) and
    ``unflagged_far`` (:data:`UNFLAGGED_FAR_PX` or more, not flagged)."""
    out = camera_pairs.summarize(run, errors, patch_errs, success_px, flag_error_px)
    errors, flagged = np.asarray(errors), np.asarray(run["implausible"], bool)
    return {**out, "successes": int((errors < success_px).sum()),
            "good_flagged": out["flag"]["flagged_good"],
            "silently_failed": out["flag"]["bad"] - out["flag"]["flagged_bad"],
            "unflagged_far": int(((errors >= UNFLAGGED_FAR_PX) & ~flagged).sum())}


def run(pair_sets, names, estimator, max_pairs_per_group: int = 0,
        success_px=camera_pairs.SUCCESS_PX, flag_error_px=camera_pairs.FLAG_ERROR_PX) -> dict:
    """Each ablation of ``names`` (:func:`resolve`) on the pairs of ``pair_sets``.

    Args:
      pair_sets: ``[(label, pairs)]``, ``pairs`` a list of
        :class:`~stnh_tf.data.camera_motions.CameraPair` of one image size (a set of
        ``make_camera_pairs``); a group found in several sets is scored over all of them.
      estimator: an object with ``estimate_images_with_info(image_a, image_b, options)``.
      max_pairs_per_group: only the first this many pairs of each group, over the sets in
        order (0: all).
    Returns:
      ``{"ablations": {name: {"switches_off", "changes", "options", "groups": {group: cell}}},
      "groups": [...], "sets": [{label, pairs used by group}], "success_px", "flag_error_px",
      "unflagged_far_px", "max_pairs_per_group"}`` (cells: :func:`cell`; groups in
      :data:`~stnh_tf.data.camera_motions.ALL_GROUPS`' order, then ``"all"``), JSON-ready.
      Each set gets one untimed warm-up call; then every ablation runs on a pair before the next
      pair, so that a change of the machine's load spreads over all ablations alike.
    Raises:
      ValueError: an unknown ablation, no pairs, or sets of different image sizes (each set's
        errors are in its own frame: 3 px at 640 x 480 is not 3 px at 320 x 240).
    """
    names = resolve(names)
    sizes = {label: pairs[0].image_a.shape[:2] for label, pairs in pair_sets if len(pairs)}
    if len(set(sizes.values())) > 1:
        listed = ", ".join(f"{k}: {w} x {h}" for k, (h, w) in sizes.items())
        raise ValueError(f"the sets' images differ in size ({listed}): their errors are in each "
                         "set's own frame and cannot be pooled; ablate each size apart.")
    options = {n: options_for(n) for n in names}
    taken, chosen = collections.Counter(), []
    for label, pairs in pair_sets:
        chosen.append((label, _take(pairs, max_pairs_per_group, taken)))
    if not sum(len(pairs) for _, pairs in chosen):
        raise ValueError("no pairs to run the ablations on.")
    parts = collections.defaultdict(list)  # (name, group) -> [(run, errors, patch errors)]
    for _, pairs in (c for c in chosen if c[1]):
        first = pairs[0]
        estimator.estimate_images_with_info(first.image_a, first.image_b, options[DEFAULT])
        per_pair = collections.defaultdict(list)
        for p in pairs:  # every ablation on a pair before the next pair
            for n in names:
                per_pair[n].append(camera_pairs.run_estimator(estimator, [p], options[n],
                                                              warm_up=False))
        runs = {n: {k: np.concatenate([r[k] for r in rs]) for k in rs[0]}
                for n, rs in per_pair.items()}
        h_true = np.stack([p.h_ba for p in pairs])
        groups = np.array([p.group for p in pairs])
        size = first.image_a.shape[::-1]
        for n, r in runs.items():
            errors, patch = camera_pairs.pair_errors(r["h"], h_true, groups, size)
            for g in set(groups):
                sel = groups == g
                parts[n, g].append(({k: v[sel] for k, v in r.items()}, errors[sel], patch[sel]))
    present = [g for g in camera_motions.ALL_GROUPS if taken[g]]
    present += sorted(g for g in taken if g not in present)
    result = {}
    for n in names:
        cells = {}
        for g in present + ["all"]:
            pieces = [x for key in ([(n, g)] if g != "all" else [(n, h) for h in present])
                      for x in parts[key]]
            joined = {k: np.concatenate([p[0][k] for p in pieces]) for k in pieces[0][0]}
            cells[g] = cell(joined, np.concatenate([p[1] for p in pieces]),
                            np.concatenate([p[2] for p in pieces]), success_px, flag_error_px)
        result[n] = {"switches_off": "nothing" if n == DEFAULT else ABLATIONS[n][0],
                     "changes": {} if n == DEFAULT else ABLATIONS[n][1],
                     "options": options[n].to_json(), "groups": cells}
    return camera_pairs.json_ready({"ablations": result, "groups": present + ["all"],
                    "sets": [{"label": label, "pairs": dict(collections.Counter(
                        p.group for p in pairs))} for label, pairs in chosen],
                    "success_px": success_px, "flag_error_px": flag_error_px,
                    "unflagged_far_px": UNFLAGGED_FAR_PX,
                    "max_pairs_per_group": max_pairs_per_group})


def run_folders(folders, names, model=None, max_pairs_per_group: int = 0) -> dict:
    """:func:`run` on the sets of ``folders`` (written by ``experiments.make_camera_pairs``;
    :func:`stnh_tf.data.camera_pair_files.load_pairs`) with the estimator of ``model``
    (``HomographyEstimator.load``; ``None``: the shipped default), with each set's folder, seed,
    motion set, counts and image size, the model's source, ``commit`` and ``machine``
    (:func:`stnh_tf.evaluation.benchmarks.machine_info`). Raises ``ValueError`` for an unknown
    ablation (before anything is loaded), a folder named twice or a set that does not load."""
    from stnh_tf.data import camera_pair_files
    from stnh_tf.evaluation import benchmarks
    from stnh_tf.inference.estimator import HomographyEstimator

    import os

    names = resolve(names)
    real = [os.path.realpath(f) for f in folders]  # (D, D/, ./D and a link to D: one set)
    if len(set(real)) < len(real) or not folders:
        raise ValueError(f"give each set of pairs once (received {list(folders)}).")
    loaded = [(folder, *camera_pair_files.load_pairs(folder)) for folder in folders]
    estimator = HomographyEstimator.load(model)
    result = run([(folder, pairs) for folder, _, pairs in loaded], names, estimator,
                 max_pairs_per_group)
    sets = [{**used, "seed": manifest.get("seed"), "motion_set": manifest.get("motion_set"),
             "set_counts": manifest.get("counts"),
             "image_size": list(pairs[0].image_a.shape[::-1]) if pairs else None}
            for used, (_, manifest, pairs) in zip(result["sets"], loaded)]
    machine = benchmarks.machine_info()
    return {**result, "sets": sets, "model": estimator.source,
            "commit": machine.get("git_commit"), "machine": machine}


CELL_LEGEND = ("cells: successes/pairs, mean error (px), good estimates flagged, silently failed "
               "(of them 10 px or more off), ms per pair")


def _value(x) -> float:
    return math.inf if x == "inf" else math.nan if x is None else float(x)


def _row(cells, fmt) -> str:
    return "| " + " | ".join(cells[:1] + [fmt(c) for c in cells[1:]]) + " |"


def table(result: dict) -> str:
    """:func:`run`'s result as two markdown tables, rows the ablations and columns the groups:
    the numbers (:data:`CELL_LEGEND`), then each ablation's differences from ``"default"``."""
    groups, rows = result["groups"], result["ablations"]
    order = [n for n in (DEFAULT, *ABLATIONS) if n in rows]  # a JSON read back sorts its keys
    rows = {n: rows[n] for n in order + sorted(set(rows) - set(order))}
    head = ["| ablation | " + " | ".join(groups) + " |", "|---" * (len(groups) + 1) + "|"]

    def numbers(c):
        return (f"{c['successes']}/{c['count']} {_value(c['mace']):.3g} {c['good_flagged']} "
                f"{c['silently_failed']} ({c['unflagged_far']}) {c['ms_per_pair']:.0f}")

    def delta(pair):
        c, d = pair
        return (f"{c['successes'] - d['successes']:+d} "
                f"{_value(c['mace']) - _value(d['mace']):+.3g} "
                f"{c['good_flagged'] - d['good_flagged']:+d} "
                f"{c['silently_failed'] - d['silently_failed']:+d} "
                f"({c['unflagged_far'] - d['unflagged_far']:+d}) "
                f"{c['ms_per_pair'] - d['ms_per_pair']:+.0f}")

    base = rows[DEFAULT]["groups"]
    lines = [CELL_LEGEND, "", *head]
    lines += [_row([n] + [r["groups"][g] for g in groups], numbers) for n, r in rows.items()]
    lines += ["", "differences from the default (the same order)", "", *head]
    lines += [_row([n] + [(r["groups"][g], base[g]) for g in groups], delta)
              for n, r in rows.items() if n != DEFAULT]
    return "\n".join(lines)
