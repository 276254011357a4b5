"""Learning curves as PNG, drawn headless with matplotlib (Agg): per run, next to its metrics, and
per sweep (mean and spread over seeds of each configuration), next to its summary."""
from __future__ import annotations

from pathlib import Path
from typing import Any

CURVE_FILE = "learning_curve.png"
METRIC = "episode_return"


def pyplot() -> Any:
    """matplotlib.pyplot, headless (Agg): charts are files, never windows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def learning_curve(rows: list[dict], path: Path, title: str, metric: str = METRIC) -> Path | None:
    """Plot `metric` (and the best so far) against iteration and against wall time; None if no row has it."""
    points = [(r["iteration"], r["wall_time"], r[metric]) for r in rows if metric in r]
    if not points:
        return None
    plt = pyplot()
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


def mean_and_std(runs: list[list[dict]], metric: str) -> tuple[list[int], list[float], list[float]]:
    """Per iteration that every run reached: the metric's mean and std (n - 1; 0 for one run) over runs."""
    import numpy as np

    series = [{r["iteration"]: r[metric] for r in rows if metric in r} for rows in runs]
    iterations = sorted(set.intersection(*(set(s) for s in series))) if series else []
    values = np.array([[s[i] for i in iterations] for s in series], dtype=float).reshape(len(series), -1)
    std = values.std(0, ddof=1) if len(series) > 1 else np.zeros(len(iterations))
    return iterations, values.mean(0).tolist(), std.tolist()


def sweep_curves(curves: dict[str, list[list[dict]]], path: Path, title: str, metric: str = METRIC) -> Path | None:
    """Plot, per configuration (label -> its runs' metric rows, one list per seed), the mean of
    `metric` against iteration with a band of one std over seeds; None if no run logged `metric`."""
    lines = {label: mean_and_std(runs, metric) for label, runs in curves.items()}
    lines = {label: line for label, line in lines.items() if line[0]}
    if not lines:
        return None
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    for label, (iterations, mean, std) in lines.items():
        (drawn,) = ax.plot(iterations, mean, marker=".", label=label)
        low = [m - s for m, s in zip(mean, std)]
        high = [m + s for m, s in zip(mean, std)]
        ax.fill_between(iterations, low, high, color=drawn.get_color(), alpha=0.2)
    ax.set_xlabel("iteration")
    ax.set_ylabel(f"{metric.replace('_', ' ')} (mean +- std over seeds)")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=7)
    ax.set_title(title, fontsize=10)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
