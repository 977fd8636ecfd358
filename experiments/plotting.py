"""PNG plots of a figure's results: mean over seeds with a 95 % confidence band."""
from __future__ import annotations

from typing import Dict, List, Optional

import numpy as np

from experiments.stats import mean_ci

#: Figure size (inches) and resolution: 2100 x 1350 pixels, fit for a paper.
FIGSIZE, DPI = (7.0, 4.5), 300


def plot_figure(path: str, title: str, x_label: str, records: List[Dict],
                reference: Dict[str, float], paper: Optional[Dict[str, float]] = None) -> None:
    """records: ``run_sweep`` records (a line each: the mean over seeds with its 95 %
    t-interval shaded); reference: {label: steps} horizontal lines; paper: {label: steps}
    the paper's reported result(s), drawn as a dark dashed line. Every horizontal line is
    named in the legend (with its value), so no label sits on the plot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=FIGSIZE, dpi=DPI)
    for rec in records:
        xs = np.asarray(rec["points"] if rec["x_axis"] == "points" else rec["episodes"], float)
        x = xs.mean(axis=0)
        mean, half = mean_ci(np.asarray(rec["mean_steps"]), axis=0)
        n = len(rec["seeds"])
        line, = ax.plot(x, mean, marker="o", ms=3, label=f"{rec['label']} (n={n})")
        ax.fill_between(x, mean - half, mean + half, color=line.get_color(), alpha=0.2)
    styles = iter([":", "-.", (0, (5, 1)), (0, (1, 3)), (0, (3, 1, 1, 1))])
    for label, value in reference.items():
        if value is None or not np.isfinite(value):
            continue
        ax.axhline(value, color="grey", ls=next(styles, ":"), lw=1,
                   label=f"{label}: {value:.0f}")
    for label, value in (paper or {}).items():
        ax.axhline(value, color="black", ls="--", lw=1.2, label=f"{label}: {value:.0f}")
    ax.set_xlabel(x_label)
    ax.set_ylabel("mean steps to goal (evaluation)")
    ax.set_title(title, fontsize=10)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    ax.legend(handles, labels, fontsize=7, loc="upper right", framealpha=0.9,
              title="shaded: 95 % interval over seeds", title_fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_robustness(path: str, title: str, rows: List[Dict],
                    reference: Optional[Dict[str, float]] = None) -> None:
    """Steps after the last run against the initial bandwidth, one line per method (mean
    over seeds, 95 % t-interval shaded), log x-axis. rows: ``bandwidth_study`` rows
    (method, bandwidth, per_seed_final); reference: {label: steps} dashed lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=FIGSIZE, dpi=DPI)
    for method in dict.fromkeys(r["method"] for r in rows):
        mine = sorted((r for r in rows if r["method"] == method), key=lambda r: r["bandwidth"])
        h = np.asarray([r["bandwidth"] for r in mine])
        stats = np.asarray([mean_ci(np.asarray(r["per_seed_final"])) for r in mine])
        n = len(mine[0]["per_seed_final"])
        line, = ax.plot(h, stats[:, 0], marker="o", ms=4, label=f"{method} (n={n} seeds)")
        ax.fill_between(h, stats[:, 0] - stats[:, 1], stats[:, 0] + stats[:, 1],
                        color=line.get_color(), alpha=0.2)
    for label, value in (reference or {}).items():
        ax.axhline(value, color="grey", ls="--", lw=1, label=f"{label}: {value:.0f}")
    ax.set_xscale("log")
    ax.set_xlabel("initial bandwidth setting h (scaled units)")
    ax.set_ylabel("mean steps to goal after the last run")
    ax.set_title(title, fontsize=10)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper left", framealpha=0.9,
              title="shaded: 95 % interval over seeds", title_fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
