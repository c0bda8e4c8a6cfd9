"""Figures of the paper, drawn with matplotlib (Agg backend, imported lazily).

* :func:`prediction_examples`: the paper's Fig. 5, image_a (the stored context around the
  square) with patch_b's true quadrilateral in green and the predicted one in red, beside
  patch_b.
* :func:`mace_bars`: the paper's Fig. 4, MACE of several methods as bars.
"""

from __future__ import annotations

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
