"""Figures of the paper, drawn with matplotlib (Agg backend, imported lazily).

* :func:`prediction_examples`: the paper's Fig. 5, as the paper draws it: image_a (the stored
  context around the square) with patch_b's true quadrilateral in green and the predicted one in
  red, and image_b around the square (:func:`image_b_window`) with the true one (the square) in
  green.
* :func:`mace_bars`: the paper's Fig. 4, MACE of several methods as bars (:func:`fig4_bars`: what
  each bar shows: its value, the paper's, its rejected-prediction mark; the identity as a dashed
  line).
* :func:`hbar_histogram`: the paper's Fig. 1, value histograms of the eight entries of H_bar.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from stnh_tf import geometry, pixels


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path, dpi: int) -> None:
    """``fig.savefig`` through memory into ``path``, by
    :func:`stnh_tf.paths.atomic_write_bytes`: a kill or a full disk leaves the old figure whole
    (the format from ``path``'s extension, PNG without one); the figure is closed."""
    import io

    from stnh_tf import paths

    buffer = io.BytesIO()
    try:
        fig.savefig(buffer, dpi=dpi, format=os.path.splitext(path)[1][1:].lower() or "png")
    finally:
        _pyplot().close(fig)
    paths.atomic_write_bytes(path, buffer.getvalue())


def quadrilateral(a_from_b: np.ndarray, offset: float = 0.0,
                  size: int = geometry.PATCH_SIZE) -> np.ndarray:
    """Where patch_b's four corners lie in patch_a (``H_ba @ c``), shifted by ``offset`` (e.g. the
    context margin), as a closed ``[5, 2]`` polyline."""
    pts = geometry.warp_points(np.asarray(a_from_b, np.float64),
                               geometry.patch_corners(size)) + offset
    return np.concatenate([pts, pts[:1]], axis=0)


def _as_uint8(patch) -> np.ndarray:
    """A ``[S, S(, 1)]`` patch, uint8 (0..255) or float in [0, 1], as uint8 ``[S, S]``."""
    patch = np.asarray(patch)
    patch = patch.reshape(patch.shape[0], patch.shape[1])
    if patch.dtype == np.uint8:
        return patch
    return pixels.to_uint8(patch)


def image_b_window(context_a, a_from_b, patch_b=None,
                   margin: int = geometry.MAX_PERTURBATION) -> np.ndarray:
    """image_b around the square, re-made from image_a's stored context: the ``S+2m`` window of
    image_b whose centre is the square, ``out(q) = context_a(T_m @ H_ba @ T_m^-1 @ q)`` (``T_m``
    the translation by ``(m, m)``; ``image_b(p) = image_a(H_ba @ p)`` in the patch frame),
    bilinear, black where that point lies beyond the context. With ``patch_b`` its stored pixels
    replace the centre (they are image_b's own).

    Args:
      context_a: ``[S+2m, S+2m]`` uint8 context of image_a.
      a_from_b: ``[3, 3]`` true pixel ``H_ba`` (patch frame, patch_b -> patch_a).
      patch_b: optional ``[S, S(, 1)]`` uint8 or float in [0, 1].
    Returns:
      uint8 ``[S+2m, S+2m]``.
    Raises:
      ValueError: ``context_a`` is not square or ``patch_b`` does not fit its centre.
    """
    from stnh_tf import hierarchy

    context_a = np.asarray(context_a)
    side = context_a.shape[0]
    if context_a.ndim != 2 or context_a.shape[1] != side or side <= 2 * margin:
        raise ValueError(f"context_a must be a square [S+2m, S+2m] image with m = {margin}; "
                         f"received shape {context_a.shape}.")
    h = np.asarray(a_from_b, np.float64) @ geometry.translation(-margin, -margin)
    window = np.clip(np.rint(hierarchy.warp_crop(context_a, h, (margin, margin), side)),
                     0, 255).astype(np.uint8)
    if patch_b is not None:
        pb = _as_uint8(patch_b)
        if pb.shape != (side - 2 * margin,) * 2:
            s = side - 2 * margin
            raise ValueError(f"patch_b must be [{s}, {s}(, 1)] to fit the centre of a {side}-px "
                             f"context; received shape {np.shape(patch_b)}.")
        window[margin:side - margin, margin:side - margin] = pb
    return window


def example_title(h_true, h_pred, title: str = "") -> str:
    """The title of one pair of Fig. 5: its MACE beside the identity's, and ``rejected: drawn at
    the identity`` where the prediction is exactly the identity (what the hierarchy keeps when
    the degenerate-prediction rule rejects every stage's prediction; a network's own output never
    is).

    >>> example_title(np.diag([1.0, 1.0, 1.0]) + [[0, 0, 3], [0, 0, 4], [0, 0, 0]], np.eye(3))
    'image_a, MACE 5.0 px (identity 5.0)\\nrejected: drawn at the identity'
    """
    h_true, h_pred = np.asarray(h_true, np.float64), np.asarray(h_pred, np.float64)
    err = float(geometry.corner_errors(h_pred, h_true))
    identity = float(geometry.corner_errors(np.eye(3), h_true))
    text = (title + "\n" if title else "") + f"image_a, MACE {err:.1f} px (identity {identity:.1f})"
    return text + ("\nrejected: drawn at the identity" if np.array_equal(h_pred, np.eye(3))
                   else "")


def prediction_figure(context_a, patch_b, h_true, h_pred, titles=None,
                      margin: int = geometry.MAX_PERTURBATION):
    """The matplotlib figure of :func:`prediction_examples` (2 rows x N columns of axes): row 0
    image_a (``context_a``) with the true (green, ``lime``) and predicted (red) quadrilaterals
    ``H_ba @ c``, titled by :func:`example_title`; row 1 image_b around the square
    (:func:`image_b_window`) with the true one, the square itself, in green. The caller closes
    it."""
    plt = _pyplot()
    n = len(context_a)
    fig, axes = plt.subplots(2, n, figsize=(2.6 * n, 5.4), squeeze=False)
    for i in range(n):
        ax = axes[0, i]
        ax.imshow(context_a[i], cmap="gray", vmin=0, vmax=255)
        for h, colour in ((h_true[i], "lime"), (h_pred[i], "red")):
            q = quadrilateral(h, margin)
            ax.plot(q[:, 0], q[:, 1], color=colour, linewidth=1.5)
        ax.set_title(example_title(h_true[i], h_pred[i], titles[i] if titles else ""),
                     fontsize=8)
        ax.axis("off")
        ax = axes[1, i]
        ax.imshow(image_b_window(context_a[i], h_true[i], patch_b[i], margin), cmap="gray",
                  vmin=0, vmax=255)
        q = quadrilateral(np.eye(3), margin)
        ax.plot(q[:, 0], q[:, 1], color="lime", linewidth=1.5)
        ax.set_title("image_b", fontsize=8)
        ax.axis("off")
    fig.suptitle("Ground truth green (image_a and image_b), prediction red (image_a)", fontsize=9)
    fig.tight_layout()
    return fig


def prediction_examples(context_a, patch_b, h_true, h_pred, path: str, titles=None,
                        margin: int = geometry.MAX_PERTURBATION) -> str:
    """Fig. 5 as the paper draws it ("the green boxes in image_a and image_b represent the ground
    truth corresponding points, and the red boxes in image_a are our predictions"): for each
    pair, image_a's context with the true (green) and predicted (red) quadrilaterals of patch_b,
    and below it image_b around the square with the true box (:func:`prediction_figure`).
    image_a and image_b are the ``S+2m`` windows the stored pairs hold, not the whole 320x240
    images. Writes a PNG to ``path``; returns ``path``.

    Args:
      context_a: ``[N, S+2m, S+2m]`` uint8; patch_b: ``[N, S, S(, 1)]`` uint8 or float in [0, 1].
      h_true, h_pred: ``[N, 3, 3]`` pixel ``H_ba`` (patch frame).
    """
    save_figure(prediction_figure(context_a, patch_b, h_true, h_pred, titles, margin), path, 110)
    return path


@dataclasses.dataclass(frozen=True)
class Bar:
    """One method's bar of Fig. 4: its MACE (px), the paper's (``None``: none), where the
    hierarchy's degenerate-prediction rule rejected some of its stage predictions the ``note``
    written over it and ``hatched``, the MACE of each seed trained (``seeds``, drawn as dots) and
    the same method trained at the paper's schedule (``schedule``, its own bar; ``None``: none)."""

    name: str
    value: float
    paper: float | None = None
    note: str = ""
    hatched: bool = False
    seeds: tuple = ()
    schedule: float | None = None


def fig4_bars(results: dict, paper: dict | None = None, rejected: dict | None = None,
              predictions: dict | None = None, seeds: dict | None = None,
              schedule: dict | None = None) -> list:
    """What :func:`mace_bars` draws, one :class:`Bar` per method of ``results`` (``{name: mace}``)
    in order. A method with ``rejected[name] > 0`` stage predictions rejected (of
    ``predictions[name]``) is hatched and noted ``rejected: n of m``, plus ``at the identity``
    where its MACE is the identity's (drawn at the identity's height; the identity's method: the
    one named ``identity``, any case). ``seeds`` and ``schedule`` (``{name: ...}``) fill
    :class:`Bar`'s fields of the same names.

    >>> [b.note for b in fig4_bars({"Identity": 23.5, "2 stages": 23.5, "1 stage": 9.0},
    ...                            rejected={"2 stages": 8}, predictions={"2 stages": 8})]
    ['', 'rejected: 8 of 8\\nat the identity', '']
    """
    rejected, predictions, paper = rejected or {}, predictions or {}, paper or {}
    seeds, schedule = seeds or {}, schedule or {}
    identity = next((v for n, v in results.items() if n.lower() == "identity"), None)
    bars = []
    for name, value in results.items():
        n, note = rejected.get(name, 0), ""
        if n:
            note = f"rejected: {n}" + (f" of {predictions[name]}" if name in predictions else "")
            if identity is not None and abs(value - identity) < 1e-6:
                note += "\nat the identity"
        bars.append(Bar(name, float(value), paper.get(name), note, bool(n),
                        tuple(float(v) for v in seeds.get(name, ())),
                        None if schedule.get(name) is None else float(schedule[name])))
    return bars


def mace_bars_figure(bars, title: str = "Mean corner error (px)", label: str = "this run",
                     seeds_label: str = "each seed"):
    """The matplotlib figure of :func:`mace_bars` for :func:`fig4_bars`' ``bars``: the bars
    named ``label`` (hatched ``//`` where noted, the note above the method's bars), each seed's
    MACE as a dot on them (``seeds_label`` in the legend), the paper's-schedule bars beside them
    where any bar has one, the paper's in grey where any is given, and the identity's MACE as a
    dashed line. The caller closes it."""
    plt = _pyplot()
    names = [b.name for b in bars]
    x = np.arange(len(names))
    columns = [("ours", [b.value for b in bars])]
    if any(b.schedule is not None for b in bars):
        columns.append(("schedule", [np.nan if b.schedule is None else b.schedule for b in bars]))
    if any(b.paper is not None for b in bars):
        columns.append(("paper", [np.nan if b.paper is None else b.paper for b in bars]))
    fig, ax = plt.subplots(figsize=(max(6, 1.3 * len(names)), 3.8))
    width = 0.8 / len(columns) if len(columns) > 1 else 0.7
    offsets = (np.arange(len(columns)) - (len(columns) - 1) / 2) * width
    styles = {"ours": {"label": label, "hatch": ["//" if b.hatched else "" for b in bars],
                       "edgecolor": "black", "linewidth": 0.3},
              "schedule": {"label": "ours, the paper's schedule", "color": "tab:green"},
              "paper": {"label": "paper", "color": "grey"}}
    for (kind, values), offset in zip(columns, offsets):
        drawn = ax.bar(x + offset, values, width, **styles[kind])
        ax.bar_label(drawn, fmt="%.1f" if kind == "ours" else "%.2f", fontsize=7)
    dots = [(xi + offsets[0], v) for xi, b in zip(x, bars) for v in b.seeds]
    if dots:
        ax.scatter(*zip(*dots), s=9, color="black", zorder=3, label=seeds_label)
    for xi, b in zip(x, bars):
        if b.note:
            ax.annotate(b.note, (xi, b.value), xytext=(0, 10),
                        textcoords="offset points", ha="center", va="bottom", fontsize=6,
                        color="darkred")
    identity = next((b.value for b in bars if b.name.lower() == "identity"), None)
    if identity is not None:
        ax.axhline(identity, color="black", linestyle="--", linewidth=0.8, label="identity")
    top = max([b.value for b in bars if np.isfinite(b.value)] + [1.0])
    ax.set_ylim(0, top * (1.35 if any(b.note for b in bars) else 1.12))
    ax.legend(fontsize=7, ncol=2)
    ax.set_xticks(x, names, rotation=20, ha="right", fontsize=8)
    ax.set_ylabel("MACE (px)")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return fig


def mace_bars(results: dict, path: str, paper: dict | None = None,
              title: str = "Mean corner error (px)", rejected: dict | None = None,
              predictions: dict | None = None, seeds: dict | None = None,
              schedule: dict | None = None, label: str = "this run",
              seeds_label: str = "each seed") -> str:
    """Fig. 4: one bar per method (``{name: mace}``), the paper's value beside it where given,
    rows whose predictions the degenerate rule rejected marked, each seed a dot, the paper's
    schedule's bars (:func:`fig4_bars`), the identity's MACE as a dashed line; writes a PNG to
    ``path`` and returns it."""
    save_figure(mace_bars_figure(fig4_bars(results, paper, rejected, predictions, seeds, schedule),
                                 title, label, seeds_label), path, 110)
    return path


ENTRY_NAMES = ("h11", "h12", "h13", "h21", "h22", "h23", "h31", "h32")


def read_h_bar(data_dir: str, split: str, max_samples: int = 0) -> np.ndarray:
    """``float32 [N, 8]``: the stored H_bar targets of ``split`` (only that feature is parsed)."""
    from stnh_tf.data import tfrecords as data

    ds = data.load_raw(data_dir, split, fields=("h_bar",)).batch(4096)
    if max_samples > 0:
        ds = ds.unbatch().take(max_samples).batch(4096)
    parts = [b["h_bar"].numpy() for b in ds]
    return np.concatenate(parts) if parts else np.zeros((0, 8), np.float32)


def hbar_histogram(h_bar, output: str, bins: int = 100, title: str = "") -> dict:
    """Fig. 1: the 2 x 4 histogram figure of ``h_bar [N, 8]`` written to ``output``; returns
    the statistics (mean, std, min, max of each entry)."""
    plt = _pyplot()
    h_bar = np.asarray(h_bar, np.float64)
    if h_bar.ndim != 2 or h_bar.shape[1] != 8 or len(h_bar) == 0:
        raise ValueError(f"h_bar must be a non-empty [N, 8] array; received shape {h_bar.shape}.")
    stats = {}
    fig, axes = plt.subplots(2, 4, figsize=(14, 6), constrained_layout=True)
    for j, ax in enumerate(axes.ravel()):
        v = h_bar[:, j]
        stats[ENTRY_NAMES[j]] = {"mean": float(v.mean()), "std": float(v.std()),
                                 "min": float(v.min()), "max": float(v.max())}
        ax.hist(v, bins=bins, color="tab:blue")
        ax.set_title(f"{ENTRY_NAMES[j]}: mean {v.mean():.3f}, std {v.std():.3f}", fontsize=10)
        ax.set_xlabel("value")
        ax.set_ylabel("count")
    fig.suptitle(title or f"Value histogram of normalized H_bar ({len(h_bar)} samples)")
    os.makedirs(os.path.dirname(os.path.abspath(output)), exist_ok=True)
    save_figure(fig, output, 100)
    return {"num_samples": int(len(h_bar)), "entries": stats}
