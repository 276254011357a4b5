"""Learning curves as PNG, drawn headless with matplotlib (Agg): per run, next to its metrics."""
from __future__ import annotations

from pathlib import Path

CURVE_FILE = "learning_curve.png"
METRIC = "episode_return"


def learning_curve(rows: list[dict], path: Path, title: str, metric: str = METRIC) -> Path | None:
    """Plot `metric` (and the best so far) against iteration and against wall time; None if no row has it."""
    points = [(r["iteration"], r["wall_time"], r[metric]) for r in rows if metric in r]
    if not points:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    iteration, wall, value = zip(*points)
    best = [max(value[:i + 1]) for i in range(len(value))]
    fig, axes = plt.subplots(1, 2, figsize=(8, 3), sharey=True, constrained_layout=True)
    for ax, x, label in ((axes[0], iteration, "iteration"), (axes[1], wall, "wall time (s)")):
        ax.plot(x, value, marker=".", label=metric.replace("_", " "))
        ax.plot(x, best, linestyle="--", label="best so far")
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(metric.replace("_", " "))
    axes[0].legend(loc="best", fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
