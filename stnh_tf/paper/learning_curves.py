r"""Learning curves read from training logs (issue 78): the library core of
``python -m experiments.plot_learning_curves --logs=paper_schedule/logs/stage3_*.log``.

A run's console log (``train_stage``, ``paper_schedule``; one file per chunk) holds the lines of
:class:`stnh_tf.training.callbacks.ProgressLogger`::

    step 37500/91000 lr=0.032309 h_bar_loss=0.00056884 h_bar_mace=3.3777 ... (1.28 steps/s, ...)
    step 37500 validation val_h_bar_loss=0.00056378 val_h_bar_mace=2.9317 ...

:func:`read_logs` gathers every metric by step from all the files given (a step logged by two
chunks, e.g. a resumed one, keeps the later file's value); :func:`plot` draws the training
metric (its running mean over the Keras epoch, as logged) and the validation metric against the
step, the learning rate on a second axis.

    >>> curve = parse_lines(["I1205 loop.py] step 500/91000 lr=0.025 h_bar_mace=6.98 loss=0.07 "
    ...                      "(129.60 steps/s)", "x] step 500 validation val_h_bar_mace=7.13"])
    >>> curve[500]
    {'lr': 0.025, 'h_bar_mace': 6.98, 'loss': 0.07, 'val_h_bar_mace': 7.13}
"""

from __future__ import annotations

import glob
import os
import re

_NUMBER = r"(?:[-+]?(?:nan|inf)|[-+\d.eE]+)"  # (a diverged run logs nan: kept, not dropped)
_TRAIN = re.compile(rf"\bstep (\d+)/(\d+) ((?:\w+={_NUMBER}(?:\s|$))+)")
_VAL = re.compile(rf"\bstep (\d+) validation ((?:\w+={_NUMBER}(?:\s|$))+)")
_PAIR = re.compile(rf"(\w+)=({_NUMBER})")


def parse_lines(lines) -> dict[int, dict[str, float]]:
    """``{step: {metric: value}}`` of the progress and validation lines among ``lines`` (other
    lines are skipped); a later line of the same step and metric replaces an earlier one."""
    curve: dict[int, dict[str, float]] = {}
    for line in lines:
        for pattern in (_TRAIN, _VAL):
            found = pattern.search(line)
            if found:
                values = found.group(found.lastindex)
                curve.setdefault(int(found.group(1)), {}).update(
                    (k, float(v)) for k, v in _PAIR.findall(values))
                break
    return curve


def read_logs(paths) -> dict[int, dict[str, float]]:
    """:func:`parse_lines` of every file of ``paths`` (glob patterns allowed), in the order given
    (each pattern's matches sorted by the first step in their name, ``..._<from>-<to>_...``, then
    by name).

    Raises:
      FileNotFoundError: a path or pattern that matches no file.
      ValueError: no progress line in any of them.
    """
    files = []
    for pattern in paths:
        found = sorted(glob.glob(pattern), key=_first_step) if glob.has_magic(pattern) else (
            [pattern] if os.path.isfile(pattern) else [])
        if not found:
            raise FileNotFoundError(f"no log file at {pattern}")
        files += found
    curve: dict[int, dict[str, float]] = {}
    for path in files:
        with open(path, errors="replace") as f:
            for step, values in parse_lines(f).items():
                curve.setdefault(step, {}).update(values)
    if not curve:
        raise ValueError(f"no training progress line in {files}")
    return dict(sorted(curve.items()))


def _first_step(path):
    found = re.search(r"_(\d+)-\d+_", os.path.basename(path))
    return (int(found.group(1)) if found else -1, path)


def series(curve: dict, metric: str) -> tuple[list, list]:
    """``(steps, values)`` of ``metric`` over the steps of ``curve`` that log it."""
    steps = [s for s, v in curve.items() if metric in v]
    return steps, [curve[s][metric] for s in steps]


def plot(curve: dict, path: str, metric: str = "h_bar_mace", title: str = "") -> dict:
    """Draw ``metric`` (training, as logged) and ``val_<metric>`` against the step, with the
    learning rate on a second axis, into the PNG ``path``; returns ``{"points": {name: count},
    "last": {name: [step, value]}}`` of what was drawn.

    Raises:
      ValueError: ``curve`` logs neither ``metric`` nor ``val_<metric>``.
    """
    from stnh_tf.paper.figures import _pyplot, save_figure

    drawn = {name: series(curve, name) for name in (metric, f"val_{metric}", "lr")}
    if not drawn[metric][0] and not drawn[f"val_{metric}"][0]:
        raise ValueError(f"the logs hold neither {metric} nor val_{metric}; they log "
                         f"{sorted({k for v in curve.values() for k in v})}.")
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 3.8))
    for name, style in ((metric, {"color": "tab:blue", "linewidth": 0.8}),
                        (f"val_{metric}", {"color": "tab:orange", "marker": ".",
                                           "linestyle": "none", "markersize": 3})):
        steps, values = drawn[name]
        if steps:
            ax.plot(steps, values, label=name, **style)
    ax.set_xlabel("step")
    ax.set_ylabel(f"{metric} (px)" if metric.endswith("mace") else metric)
    if drawn["lr"][0]:
        lr_ax = ax.twinx()
        lr_ax.plot(*drawn["lr"], color="grey", linewidth=0.6, linestyle="--",
                   label="learning rate")
        lr_ax.set_ylabel("learning rate")
        lr_ax.legend(fontsize=7, loc="upper center")
    ax.legend(fontsize=7)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    save_figure(fig, path, 100)
    return {"points": {k: len(v[0]) for k, v in drawn.items()},
            "last": {k: [v[0][-1], v[1][-1]] for k, v in drawn.items() if v[0]}}
