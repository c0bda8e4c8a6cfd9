"""Figures of the paper, drawn with matplotlib (Agg backend, imported lazily).

* :func:`prediction_examples`: the paper's Fig. 5, image_a (the stored context around the
  square) with patch_b's true quadrilateral in green and the predicted one in red, beside
  patch_b.
* :func:`mace_bars`: the paper's Fig. 4, MACE of several methods as bars.
* :func:`hbar_histogram`: the paper's Fig. 1, value histograms of the eight entries of H_bar.
"""

from __future__ import annotations

import os

import numpy as np

from stnh_tf import geometry


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def quadrilateral(a_from_b: np.ndarray, offset: float = 0.0, size: int = geometry.PATCH_SIZE) -> np.ndarray:
    """Where patch_b's four corners lie in patch_a (``H_ba @ c``), shifted by ``offset`` (e.g. the
    context margin), as a closed ``[5, 2]`` polyline."""
    pts = geometry.warp_points(np.asarray(a_from_b, np.float64), geometry.patch_corners(size)) + offset
    return np.concatenate([pts, pts[:1]], axis=0)


def prediction_examples(context_a, patch_b, h_true, h_pred, path: str, titles=None,
                        margin: int = geometry.MAX_PERTURBATION, columns: int = 4) -> str:
    """Fig. 5: for each pair, image_a's context with the true (green) and predicted (red)
    quadrilaterals of patch_b, and patch_b below it. Writes a PNG to ``path``; returns ``path``.

    Args:
      context_a: ``[N, S+2m, S+2m]`` uint8; patch_b: ``[N, S, S(, 1)]`` uint8 or float in [0, 1].
      h_true, h_pred: ``[N, 3, 3]`` pixel ``H_ba`` (patch frame).
    """
    plt = _pyplot()
    n = len(context_a)
    fig, axes = plt.subplots(2, n, figsize=(2.6 * n, 5.4), squeeze=False)
    for i in range(n):
        ax = axes[0, i]
        ax.imshow(context_a[i], cmap="gray", vmin=0, vmax=255)
        for h, colour in ((h_true[i], "lime"), (h_pred[i], "red")):
            q = quadrilateral(h, margin)
            ax.plot(q[:, 0], q[:, 1], color=colour, linewidth=1.5)
        err = float(geometry.corner_errors(np.asarray(h_pred[i]), np.asarray(h_true[i])))
        ax.set_title((titles[i] + "\n" if titles else "") + f"MACE {err:.1f} px", fontsize=8)
        ax.axis("off")
        pb = np.asarray(patch_b[i]).reshape(patch_b[i].shape[0], patch_b[i].shape[1])
        axes[1, i].imshow(pb, cmap="gray", vmin=0, vmax=1 if pb.dtype != np.uint8 else 255)
        axes[1, i].set_title("patch_b", fontsize=8)
        axes[1, i].axis("off")
    fig.suptitle("image_a: true quadrilateral green, predicted red", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def mace_bars(results: dict, path: str, paper: dict | None = None,
              title: str = "Mean corner error (px)") -> str:
    """Fig. 4: one bar per method (``{name: mace}``), the paper's value beside it where given."""
    plt = _pyplot()
    names = list(results)
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(max(6, 1.1 * len(names)), 3.6))
    width = 0.4 if paper else 0.7
    bars = ax.bar(x - (width / 2 if paper else 0), [results[n] for n in names], width, label="this run")
    ax.bar_label(bars, fmt="%.1f", fontsize=7)
    if paper:
        vals = [paper.get(n, np.nan) for n in names]
        pbars = ax.bar(x + width / 2, vals, width, label="paper", color="grey")
        ax.bar_label(pbars, fmt="%.2f", fontsize=7)
        ax.legend(fontsize=8)
    ax.set_xticks(x, names, rotation=20, ha="right", fontsize=8)
    ax.set_ylabel("MACE (px)")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


ENTRY_NAMES = ("h11", "h12", "h13", "h21", "h22", "h23", "h31", "h32")


def read_h_bar(data_dir: str, split: str, max_samples: int = 0) -> np.ndarray:
    """``float32 [N, 8]``: the stored H_bar targets of ``split`` (only that feature is parsed)."""
    from stnh_tf import data

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
    fig.savefig(output, dpi=100)
    plt.close(fig)
    return {"num_samples": int(len(h_bar)), "entries": stats}
