"""Figures (matplotlib, Agg): closed-loop responses and solve-time comparisons."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def closed_loop(trajectories: dict, path, *, title: str = "", state_names=None, input_names=None) -> Path:
    """Joint positions against their goals and applied inputs, one line per labelled trajectory."""
    first = next(iter(trajectories.values()))
    n_q = first.x.shape[1] // 2
    m = first.u.shape[1]
    fig, axes = plt.subplots(n_q + m, 1, figsize=(8, 2.2 * (n_q + m)), sharex=True, squeeze=False)
    axes = axes[:, 0]
    for label, traj in trajectories.items():
        for i in range(n_q):
            axes[i].plot(traj.t, traj.x[:, i], label=label)
        for j in range(m):
            axes[n_q + j].step(traj.t[:-1], traj.u[:, j], where="post", label=label)
    for i in range(n_q):
        axes[i].axhline(first.goal[i], color="k", ls="--", lw=0.8, label="goal")
        axes[i].set_ylabel(state_names[i] if state_names else f"q{i} [rad]")
    for j in range(m):
        axes[n_q + j].set_ylabel(input_names[j] if input_names else f"u{j}")
    axes[-1].set_xlabel("time [s]")
    axes[0].legend(fontsize=7, ncol=2, loc="best")
    if title:
        axes[0].set_title(title)
    return save(fig, path)


def save(fig, path) -> Path:
    """Write a figure and close it: to ``path`` if it has a suffix, else to ``path``.png and ``path``.pdf."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    targets = [path] if path.suffix else [path.with_suffix(".png"), path.with_suffix(".pdf")]
    for target in targets:
        fig.savefig(target, dpi=130)
    plt.close(fig)
    return targets[0]


def boxes(labels, data, path, *, xlabel: str, ylabel: str, title: str = "", log: bool = True) -> Path:
    """Box plots in the paper's convention: quartile box, median marker, 1.5 IQR whiskers, outliers as dots."""
    fig, ax = plt.subplots(figsize=(max(6, 0.35 * len(labels)), 3.6))
    ax.boxplot(data, showmeans=False, medianprops={"marker": "o", "markersize": 3, "color": "C3"},
               flierprops={"marker": ".", "markersize": 3})
    ax.set_xticks(range(1, len(labels) + 1), [str(l) for l in labels], fontsize=8)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if log:
        ax.set_yscale("log")
    ax.axhline(1.0, color="k", lw=0.6, ls=":")
    ax.grid(axis="y", alpha=0.3)
    if title:
        ax.set_title(title, fontsize=10)
    return save(fig, path)


def lines(x, series: dict, path, *, xlabel: str, ylabel: str, title: str = "", log: bool = False) -> Path:
    """One marked line per labelled series over a shared x."""
    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    for label, y in series.items():
        ax.plot(x, y, marker="o", ms=3, label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if log:
        ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    return save(fig, path)


def bar_times(labels, medians, path, *, ylabel: str = "median solve time [ms]", title: str = "") -> Path:
    """A bar chart of median times in milliseconds."""
    fig, ax = plt.subplots(figsize=(max(6, 0.6 * len(labels)), 3.5))
    ax.bar(range(len(labels)), np.asarray(medians) * 1e3)
    ax.set_xticks(range(len(labels)), labels, rotation=45, ha="right", fontsize=8)
    ax.set_ylabel(ylabel)
    ax.set_yscale("log")
    if title:
        ax.set_title(title)
    return save(fig, path)
