"""PNG plots of a figure's results: mean over seeds with a 95% confidence band."""
from __future__ import annotations

from typing import Dict, List

import numpy as np

from experiments.stats import mean_ci


def plot_figure(path: str, title: str, x_label: str, records: List[Dict],
                reference: Dict[str, float]) -> None:
    """records: run_variant records; reference: {label: steps} horizontal lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    for rec in records:
        xs = np.asarray(rec["points"] if rec["x_axis"] == "points" else rec["episodes"], float)
        x = xs.mean(axis=0)
        mean, half = mean_ci(np.asarray(rec["mean_steps"]), axis=0)
        n = len(rec["seeds"])
        line, = ax.plot(x, mean, marker="o", ms=3, label=f"{rec['label']} (n={n})")
        ax.fill_between(x, mean - half, mean + half, color=line.get_color(), alpha=0.2)
    styles = iter(["--", ":", "-.", (0, (5, 1))])
    for label, value in reference.items():
        if value is None or not np.isfinite(value):
            continue
        ax.axhline(value, color="grey", ls=next(styles, "--"), lw=1)
        ax.annotate(f"{label} ({value:.0f})", (0.01, value), xycoords=("axes fraction", "data"),
                    ha="left", va="bottom", fontsize=8, color="dimgrey")
    ax.set_xlabel(x_label)
    ax.set_ylabel("mean steps to goal (evaluation)")
    ax.set_title(title, fontsize=10)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="center right")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
