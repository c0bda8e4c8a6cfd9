r"""The paper's Fig. 1: value histograms of the eight regressed entries of H_bar.

  python -m experiments.plot_hbar_histogram --data_dir=data/coco_mini --output=hbar_hist.png

Reads only the ``h_bar`` feature of a split (all samples, or ``--max_samples``), draws one
histogram per entry ``h11 .. h32`` (2 x 4 panels, mean and standard deviation in each title) with
matplotlib's Agg backend, and writes the summary statistics beside the figure as JSON.
"""

from __future__ import annotations

import json
import os

from absl import app, flags

flags.DEFINE_string("data_dir", None, "Dataset directory (metadata.json + shards).")
flags.DEFINE_string("split", "train", "Split to histogram.")
flags.DEFINE_string("output", None, "Output PNG path.")
flags.DEFINE_integer("bins", 100, "Histogram bins per entry.")
flags.DEFINE_integer("max_samples", 0, "Use only the first N samples (0 = all).")
FLAGS = flags.FLAGS

ENTRY_NAMES = ("h11", "h12", "h13", "h21", "h22", "h23", "h31", "h32")


def read_h_bar(data_dir: str, split: str, max_samples: int = 0):
    """``float32 [N, 8]``: the stored H_bar targets of ``split`` (only that feature is parsed)."""
    import numpy as np

    from stnh_tf import data

    ds = data.load_raw(data_dir, split, fields=("h_bar",)).batch(4096)
    if max_samples > 0:
        ds = ds.unbatch().take(max_samples).batch(4096)
    parts = [b["h_bar"].numpy() for b in ds]
    return np.concatenate(parts) if parts else np.zeros((0, 8), np.float32)


def plot_histogram(h_bar, output: str, bins: int = 100, title: str = "") -> dict:
    """Draw the 2 x 4 histogram figure of ``h_bar [N, 8]`` to ``output``; returns statistics."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

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


def main(argv):
    del argv
    if not FLAGS.data_dir or not FLAGS.output:
        raise app.UsageError("--data_dir and --output are required.")
    h_bar = read_h_bar(FLAGS.data_dir, FLAGS.split, FLAGS.max_samples)
    stats = plot_histogram(h_bar, FLAGS.output, FLAGS.bins,
                           f"Value histogram of H_bar, {FLAGS.split} split of {FLAGS.data_dir} "
                           f"({len(h_bar)} samples)")
    stats.update(data_dir=os.path.abspath(FLAGS.data_dir), split=FLAGS.split)
    with open(os.path.splitext(FLAGS.output)[0] + ".json", "w") as f:
        json.dump(stats, f, indent=2)
    print(json.dumps(stats["entries"], indent=1))


if __name__ == "__main__":
    app.run(main)
