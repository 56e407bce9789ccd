"""Figures (matplotlib, Agg): closed-loop responses and solve-time comparisons, and the one number style
(:func:`number`) every report table, figure tick and note uses."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib import ticker  # noqa: E402

BOX_CONVENTION = "box: quartiles; line: median; whiskers: 1.5 IQR; dots: outliers"


def number(value, digits: int = 4) -> str:
    """A number as reports print it: ``digits`` significant digits in plain decimals (scientific only below
    1e-4 or from 10^digits on), "–" for a missing value, ints as ints: 1.0037 → "1.004", 0.5 → "0.5"."""
    if value is None:
        return "–"
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return str(int(value))
    v = float(value)
    if np.isnan(v):
        return "–"
    if np.isinf(v):
        return "∞" if v > 0 else "−∞"
    return format(v, f".{digits}g")


def log_axis(ax, axis: str = "y") -> None:
    """A log axis with readable ticks: plain decimals; over less than 1.5 decades, evenly spaced values
    (a log locator would label only 10⁰ on a ratio axis spanning 0.98–1.4)."""
    which = ax.yaxis if axis == "y" else ax.xaxis
    lo, hi = ax.get_ylim() if axis == "y" else ax.get_xlim()
    if lo > 0 and hi / lo < 10 ** 1.5:
        which.set_major_locator(ticker.MaxNLocator(nbins=6))
    else:
        which.set_major_locator(ticker.LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    which.set_major_formatter(ticker.FuncFormatter(lambda v, _: number(v, 3)))
    which.set_minor_formatter(ticker.NullFormatter())


def closed_loop(trajectories: dict, path, *, title: str = "", state_names=None, input_names=None,
                task: dict | None = None) -> Path:
    """Joint positions against their goals and applied inputs, one line per labelled trajectory.

    Up to three joints get a panel each (position, then input); more joints share one position panel and one
    input panel, a colour per joint and a line style per trajectory. ``task`` (a reach task) adds a first panel:
    label -> values at every recorded state of the first trajectory (the end effector's distance to its target,
    the smallest clearance to the obstacles, on a line at zero).
    """
    first = next(iter(trajectories.values()))
    n_q = first.x.shape[1] // 2
    m = first.u.shape[1]
    if n_q > 3 or task:
        return _closed_loop_compact(trajectories, path, title, n_q, m, task)
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
    axes[0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # outside: every entry, no trace hidden
    if title:
        axes[0].set_title(title)
    return save(fig, path)


def _closed_loop_compact(trajectories, path, title, n_q, m, task=None) -> Path:
    rows = 3 if task else 2
    fig, axes = plt.subplots(rows, 1, figsize=(9, 3.2 * rows), sharex=True)
    ax_q, ax_u = axes[-2:]
    styles = ["-", "--", ":", "-."]
    first = next(iter(trajectories.values()))
    if task:
        for k, (label, values) in enumerate(task.items()):
            axes[0].plot(first.t, values, color=f"C{k}", label=label)
        axes[0].axhline(0.0, color="k", lw=0.6)
        axes[0].set_ylabel("task [m]")
        axes[0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    for k, (label, traj) in enumerate(trajectories.items()):
        ls = styles[k % len(styles)]
        for i in range(n_q):
            ax_q.plot(traj.t, traj.x[:, i], color=f"C{i % 10}", ls=ls, lw=1.2,
                      label=f"q{i + 1}" if k == 0 else None)
        for j in range(m):
            ax_u.step(traj.t[:-1], traj.u[:, j], where="post", color=f"C{j % 10}", ls=ls, lw=1.0)
        ax_u.plot([], [], color="k", ls=ls, label=label)
    for i in range(n_q):
        ax_q.axhline(first.goal[i], color=f"C{i % 10}", ls=(0, (1, 3)), lw=0.8)
    ax_q.set_ylabel("joint positions" + ("" if np.isnan(first.goal[:n_q]).all() else " (dotted: goals)"))
    ax_u.set_ylabel("inputs")
    ax_u.set_xlabel("time [s]")
    ax_q.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), ncol=1 + n_q // 8)
    if len(trajectories) > 1:
        ax_u.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    else:  # one controller: named under the title, where its long label does not squeeze the panels
        title = f"{title}\n{next(iter(trajectories))}" if title else next(iter(trajectories))
    if title:
        axes[0].set_title(title, fontsize=9)
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


def boxes(labels, data, path, *, xlabel: str, ylabel: str, title: str = "", log: bool = True,
          reference: float | None = 1.0) -> Path:
    """Box plots in the paper's convention: quartile box, median marker, 1.5 IQR whiskers, outliers as dots;
    a dotted line at ``reference`` (ratio 1 by default; None for none)."""
    fig, ax = plt.subplots(figsize=(max(6, 0.35 * len(labels)), 3.6))
    ax.boxplot(data, showmeans=False, medianprops={"marker": "o", "markersize": 3, "color": "C3"},
               flierprops={"marker": ".", "markersize": 3})
    ax.set_xticks(range(1, len(labels) + 1), [number(l) if isinstance(l, float) else str(l) for l in labels],
                  fontsize=8)
    ax.set_xlabel(f"{xlabel}\n({BOX_CONVENTION})")
    ax.set_ylabel(ylabel)
    if reference is not None:
        ax.axhline(reference, color="k", lw=0.6, ls=":")
    if log:
        ax.set_yscale("log")
        log_axis(ax)
    ax.grid(axis="y", alpha=0.3)
    if title:
        ax.set_title(title, fontsize=10)
    return save(fig, path)


def lines(x, series: dict, path, *, xlabel: str, ylabel: str, title: str = "", log: bool = False) -> Path:
    """One marked line per labelled series over a shared x."""
    fig, ax = plt.subplots(figsize=(6.5, 4.6))
    for label, y in series.items():
        ax.plot(x, y, marker="o", ms=3, label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if log:
        ax.set_yscale("log")
        log_axis(ax)
    ax.grid(alpha=0.3)
    # Outside the data: below the axes, as many columns as fit.
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=min(len(series), 4), frameon=False)
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
    log_axis(ax)
    if title:
        ax.set_title(title)
    return save(fig, path)
