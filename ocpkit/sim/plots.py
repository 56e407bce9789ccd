"""Figures (matplotlib, Agg): closed-loop responses, lines over a count or a parameter, per-seed strips and box
plots, in one style: a fixed look per controller (:func:`style`), constrained layout with legends outside the
axes, spread wherever a median is drawn, labelled reference lines, units on the axes; and the one number style
(:func:`number`) every report table, figure tick and note uses."""

from __future__ import annotations

import textwrap
import zlib
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib import ticker  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

BOX_CONVENTION = "box: quartiles; line: median; whiskers: 1.5 IQR; dots: outliers"
SAVE = {"dpi": 130, "bbox_inches": "tight", "pad_inches": 0.05}  # tight: an outside legend is never cut
STRIP_BELOW = 10  # groups with fewer points are drawn point by point (a box of 5 points hides which they are)
COLOURS = tuple(f"C{i}" for i in range(10))
MARKERS = ("o", "s", "^", "v", "D", "P", "X", "*", "<", ">")
LINESTYLES = ("-", "--", "-.", ":")
# The studies' controllers, one look each wherever they appear: black for the reference a ratio is taken to, the
# paper's variants dashed beside their preconditioned counterparts, a marker each so coinciding lines stay apart.
_KNOWN = {
    "traditional": ("k", "s", "-"),
    "IPOPT": ("k", "X", "-"),
    "knots 3 (QP)": ("C0", "o", "-"),
    "LinearMPC": ("C0", "o", "-"),
    "LinearMPC (trajectory)": ("C9", "s", "--"),
    "EMPC 1 gen": ("C1", "^", "-"),
    "EMPC": ("C1", "^", "-"),
    "EMPC 3 gen": ("C2", "v", "-"),
    "EMPC 1 gen (paper)": ("C3", "<", "--"),
    "EMPC (paper)": ("C3", "<", "--"),
    "EMPC 3 gen (paper)": ("C4", ">", "--"),
    "CEM": ("C5", "D", "-"),
    "MPPI": ("C6", "P", "-"),
    "RTI": ("C8", "*", "-"),
    "servo (step input)": ("C7", "x", ":"),
    # robustness: parameterized MPC by knot count
    "2 knots": ("C0", "o", "-"),
    "4 knots": ("C2", "D", "-"),
    "8 knots": ("C4", "v", "-"),
    # solve times: colour by formulation, dashed and square for traditional
    "large matrix (sparse), 5 knots": ("C0", "o", "-"),
    "large matrix (sparse), traditional": ("C0", "s", "--"),
    "small matrix (condensed), 5 knots": ("C3", "^", "-"),
    "small matrix (condensed), traditional": ("C3", "D", "--"),
    # keep-out: the QP, EMPC with the penalty in its fitness, EMPC without; and reach's fair baseline
    "EMPC, penalized fitness": ("C1", "^", "-"),
    "EMPC, quadratic fitness": ("C2", "v", "--"),
    "IPOPT, squared hinge term": ("k", "X", "-"),
    "RTI, squared hinge term": ("C8", "*", "-"),
    "EMPC, hinge fitness": ("C1", "^", "-"),
    "EMPC, squared hinge term": ("C2", "v", "--"),
}
# Looks for other labels, colour first: ten colours with solid lines, then the ten again dashed, and so on.
_LOOKS = [(c, MARKERS[(i + j) % len(MARKERS)], ls) for j, ls in enumerate(LINESTYLES) for i, c in enumerate(COLOURS)]


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


def _look(look) -> dict:
    colour, marker, linestyle = look
    return {"color": colour, "marker": marker, "linestyle": linestyle}


def style(label: str) -> dict:
    """A label's look (matplotlib ``color``, ``marker``, ``linestyle``): fixed for the studies' controllers; for
    any other label a look drawn from the label's text alone, so it is the same in every figure. In one figure
    use :func:`styles`, which keeps the looks apart."""
    if label in _KNOWN:
        return _look(_KNOWN[label])
    return _look(_LOOKS[zlib.crc32(str(label).encode()) % len(_LOOKS)])


def styles(labels) -> dict:
    """label -> look for the labels of one figure, no two alike: the known controllers' fixed looks; the other
    labels, in sorted order, the first free looks (distinct colours while they last), so the same set of labels
    always gets the same looks."""
    labels = list(dict.fromkeys(labels))
    out = {label: _look(_KNOWN[label]) for label in labels if label in _KNOWN}
    taken = {tuple(v.values()) for v in out.values()}
    free = iter([look for look in _LOOKS if look not in taken])
    for label in sorted(set(labels) - set(out), key=str):
        out[label] = _look(next(free))
    return {label: out[label] for label in labels}


def figure(nrows: int = 1, ncols: int = 1, **kwargs):
    """``plt.subplots`` in constrained layout (titles, labels and outside legends are given room)."""
    return plt.subplots(nrows, ncols, layout="constrained", **kwargs)


def set_title(target, text: str, *, fontsize: float = 10) -> None:
    """A title wrapped to its axes' (or figure's) width, so it never runs off the image."""
    fig = target if isinstance(target, plt.Figure) else target.figure
    width = fig.get_figwidth() * (1 if target is fig else target.get_position().width)
    # about 0.6 em per character: never wider than the axes
    wrapped = textwrap.fill(text, max(30, int(width * 120 / fontsize)))
    (target.suptitle if target is fig else target.set_title)(wrapped, fontsize=fontsize)


def reference(ax, y: float, label: str) -> None:
    """A dotted horizontal reference line at ``y``, named in the legend (e.g. "ratio 1: traditional MPC")."""
    ax.axhline(y, color="k", lw=0.8, ls=":", label=label, zorder=1)


def legend_outside(ax, **kwargs):
    """The axes' legend to the right of it: it covers no data and constrained layout makes room for it."""
    return ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, borderaxespad=0, **kwargs)


def count_axis(ax, values=None, axis: str = "x") -> None:
    """Integer ticks on an axis that counts (links, knots): at ``values`` if given and few, else integer steps."""
    which = ax.xaxis if axis == "x" else ax.yaxis
    values = None if values is None else sorted({int(v) for v in values})
    if values is not None and len(values) <= 15:
        which.set_major_locator(ticker.FixedLocator(values))
    else:
        which.set_major_locator(ticker.MaxNLocator(integer=True))
    which.set_major_formatter(ticker.FuncFormatter(lambda v, _: str(int(round(v)))))
    which.set_minor_locator(ticker.NullLocator())


class _Ticks(ticker.Formatter):
    """One notation for all ticks of an axis: plain decimals, or powers of ten when a tick needs them."""

    ticks = ()

    def set_locs(self, locs):
        self.ticks = tuple(locs)

    def __call__(self, value, pos=None):
        ticks = [abs(v) for v in self.ticks if v] or [abs(value) or 1.0]
        if max(ticks) >= 1e5 or min(ticks) < 1e-3:
            return f"{value:.0e}".replace("e+0", "e").replace("e-0", "e-").replace("e+", "e")
        return number(value, max(3, int(np.floor(np.log10(abs(value)))) + 1) if value else 3)


def log_axis(ax, axis: str = "y") -> None:
    """A log axis with readable ticks in one notation; within one decade, evenly spaced values (a log locator
    would label only 10⁰ on a ratio axis spanning 0.98–1.4), else 1, 2, 5 per decade."""
    which = ax.yaxis if axis == "y" else ax.xaxis
    which.set_major_locator(_LogTicks())
    which.set_major_formatter(_Ticks())
    which.set_minor_formatter(ticker.NullFormatter())


class _LogTicks(ticker.Locator):
    """:func:`log_axis`'s tick positions, chosen when the axis is drawn: from the final limits, which series and
    bands drawn after the call may still widen (a range chosen too early left a 0.9–12 axis without its 1)."""

    def __init__(self):
        self._linear = ticker.MaxNLocator(nbins=6)
        self._log = ticker.LogLocator(base=10, subs=(1.0, 2.0, 5.0))

    def set_axis(self, axis):
        super().set_axis(axis)
        self._linear.set_axis(axis)
        self._log.set_axis(axis)

    def __call__(self):
        return self.tick_values(*self.axis.get_view_interval())

    def tick_values(self, vmin, vmax):
        lo, hi = sorted((vmin, vmax))
        return (self._linear if lo > 0 and hi / lo < 10 else self._log).tick_values(lo, hi)


def closed_loop(
    trajectories: dict, path, *, title: str = "", state_names=None, input_names=None, task: dict | None = None
) -> Path:
    """Joint positions against their goals and applied inputs, one line per labelled trajectory.

    Up to three joints get a panel each (position, then input), each trajectory in its :func:`styles` look with
    its markers offset from the others', so trajectories that coincide stay visible; more joints share one
    position panel and one input panel, a colour per joint and a line style per trajectory. ``state_names`` and
    ``input_names`` label the axes (with their units). ``task`` (a reach task) adds a first panel: label ->
    values at every recorded state of the first trajectory (the end effector's distance to its target, the
    smallest clearance to the obstacles, on a line at zero).
    """
    first = next(iter(trajectories.values()))
    n_q = first.x.shape[1] // 2
    m = first.u.shape[1]
    if n_q > 3 or task:
        return _closed_loop_compact(
            trajectories, path, title, n_q, m, task, _unit(state_names and state_names[:n_q]), _unit(input_names)
        )
    fig, axes = figure(n_q + m, 1, figsize=(8, 2.2 * (n_q + m) + 0.12 * len(trajectories)), sharex=True, squeeze=False)
    axes = axes[:, 0]
    looks = styles(trajectories)
    every = max(1, len(first.t) // 12)
    for k, (label, traj) in enumerate(trajectories.items()):
        # markers on every `every`-th sample, each trajectory starting at its own offset: none sits on another's
        marks = {**looks[label], "markevery": (k * every // len(trajectories), every), "ms": 4}
        for i in range(n_q):
            axes[i].plot(traj.t, traj.x[:, i], label=label, lw=1.2, **marks)
        for j in range(m):
            axes[n_q + j].step(traj.t[:-1], traj.u[:, j], where="post", label=label, lw=1.0, **marks)
    for i in range(n_q):
        axes[i].axhline(first.goal[i], color="k", ls=(0, (1, 3)), lw=0.8, label="goal")
        axes[i].set_ylabel(state_names[i] if state_names else f"q{i} [rad]")
    for j in range(m):
        axes[n_q + j].set_ylabel(input_names[j] if input_names else f"input u{j} (model units)")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    # below the panels, as wide as the figure: a long controller label beside them squeezed them to a third
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(
        handles,
        labels,
        loc="outside lower center",
        fontsize=7,
        ncol=min(len(labels), max(1, 110 // (max(map(len, labels)) + 8))),
    )
    if title:
        set_title(axes[0], title)
    return save(fig, path)


def _unit(names) -> str:
    """The unit ("[rad]") all ``names`` end with, or "(model units)"."""
    units = {name[name.rfind("[") :] for name in names or () if name.endswith("]") and "[" in name}
    return units.pop() if len(units) == 1 and all(name.endswith("]") for name in names) else "(model units)"


def _closed_loop_compact(
    trajectories, path, title, n_q, m, task=None, q_unit="(model units)", u_unit="(model units)"
) -> Path:
    rows = 3 if task else 2
    fig, axes = figure(rows, 1, figsize=(9, 3.2 * rows), sharex=True)
    ax_q, ax_u = axes[-2:]
    first = next(iter(trajectories.values()))
    if task:
        for k, (label, values) in enumerate(task.items()):
            axes[0].plot(first.t, values, color=f"C{k}", label=label)
        reference(axes[0], 0.0, "zero")
        axes[0].set_ylabel("task [m]")
        legend_outside(axes[0])
    for k, (label, traj) in enumerate(trajectories.items()):
        ls = LINESTYLES[k % len(LINESTYLES)]
        for i in range(n_q):
            ax_q.plot(traj.t, traj.x[:, i], color=f"C{i % 10}", ls=ls, lw=1.2, label=f"q{i + 1}" if k == 0 else None)
        for j in range(m):
            ax_u.step(traj.t[:-1], traj.u[:, j], where="post", color=f"C{j % 10}", ls=ls, lw=1.0)
        ax_u.plot([], [], color="k", ls=ls, label=label)
    for i in range(n_q):
        ax_q.axhline(first.goal[i], color=f"C{i % 10}", ls=(0, (1, 3)), lw=0.8)
    ax_q.set_ylabel(f"joint positions {q_unit}" + ("" if np.isnan(first.goal[:n_q]).all() else "\n(dotted: goals)"))
    ax_u.set_ylabel(f"inputs {u_unit}")
    ax_u.set_xlabel("time [s]")
    legend_outside(ax_q, ncol=1 + n_q // 8)
    if len(trajectories) > 1:
        legend_outside(ax_u)
    else:  # one controller: named under the title, where its long label does not squeeze the panels
        title = f"{title}\n{next(iter(trajectories))}" if title else next(iter(trajectories))
    if title:
        axes[0].set_title(title, fontsize=9)
    return save(fig, path)


def save(fig, path) -> Path:
    """Write a figure and close it: to ``path`` if it has a suffix, else to ``path``.png and ``path``.pdf; in
    constrained layout, cropped to everything drawn (:data:`SAVE`), so an outside legend or long title is whole."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if fig.get_layout_engine() is None:
        fig.set_layout_engine("constrained")
    targets = [path] if path.suffix else [path.with_suffix(".png"), path.with_suffix(".pdf")]
    for target in targets:
        fig.savefig(target, **SAVE)
    plt.close(fig)
    return targets[0]


def boxes(
    labels,
    data,
    path,
    *,
    xlabel: str,
    ylabel: str,
    title: str = "",
    log: bool = True,
    references=(),
    colours=None,
    unit: str = "seed",
) -> Path:
    """One group of values per label: every value as a dot and the median as a bar when each group has fewer
    than :data:`STRIP_BELOW` (a box of 5 points hides which they are), else box plots in the paper's convention
    (quartile box, median marker, 1.5 IQR whiskers, outliers as dots). ``references``: (y, legend label) of
    dotted lines, as :func:`lines` takes them; ``colours``: one per group (default: all C0); ``unit``: what one
    value is ("seed")."""
    if len(labels) != len(data):
        raise ValueError(f"labels and data must have the same length, got {len(labels)} and {len(data)}")
    data = [np.asarray(d, dtype=float) for d in data]
    colours = list(colours) if colours is not None else ["C0"] * len(labels)
    fig, ax = figure(figsize=(max(6, 0.5 * len(labels) + 2.5), 3.8))
    positions = np.arange(1, len(labels) + 1)
    if max((len(d) for d in data), default=0) < STRIP_BELOW:
        for x, values, colour in zip(positions, data, colours):
            order = np.argsort(values)
            # spread the dots sideways in value order: equal values sit side by side, not on top of each other
            offsets = np.linspace(-0.2, 0.2, len(values)) if len(values) > 1 else np.zeros(1)
            ax.plot(
                x + offsets,
                values[order],
                "o",
                color=colour,
                ms=5,
                alpha=0.8,
                mec="k",
                mew=0.4,
                label=f"one {unit}" if x == 1 else None,
            )
            if len(values):
                ax.hlines(np.median(values), x - 0.3, x + 0.3, color="k", lw=2, label="median" if x == 1 else None)
        counts = {len(d) for d in data}
        ax.set_xlabel(xlabel + f"\n({'/'.join(map(str, sorted(counts)))} {unit}s per group)")
    else:
        parts = ax.boxplot(
            data,
            positions=positions,
            patch_artist=True,
            medianprops={"color": "k", "lw": 1.5},
            flierprops={"marker": ".", "markersize": 3},
        )
        for box, colour in zip(parts["boxes"], colours):
            box.set(facecolor=colour, alpha=0.35)
        ax.set_xlabel(f"{xlabel}\n({BOX_CONVENTION})")
    ax.set_xticks(
        positions,
        [number(l) if isinstance(l, (float, np.floating)) else str(l) for l in labels],
        fontsize=8,
        rotation=0 if max(len(str(l)) for l in labels) <= 12 else 30,
        ha="center" if max(len(str(l)) for l in labels) <= 12 else "right",
    )
    ax.set_ylabel(ylabel)
    for y, text in references:
        reference(ax, y, text)
    if log:
        ax.set_yscale("log")
        log_axis(ax)
    ax.grid(axis="y", alpha=0.3)
    if ax.get_legend_handles_labels()[1]:
        legend_outside(ax)
    if title:
        set_title(ax, title)
    return save(fig, path)


def lines(
    x,
    series: dict,
    path,
    *,
    xlabel: str,
    ylabel: str,
    title: str = "",
    log: bool = False,
    spread: dict | None = None,
    spread_label: str = "shaded: quartiles",
    counts: bool = False,
    references=(),
    panels=None,
    dodge: bool = False,
) -> Path:
    """One marked line per labelled series over a shared x, each in its :func:`style`.

    ``series[label]``: one value per x, or the values at each x (a sequence of arrays, e.g. one per seed): the
    line is then their median and a shaded band spans their quartiles. ``spread[label]``: (low, high) per x, a
    band measured elsewhere (the quartiles over a trial's states). ``counts``: x counts things (links, knots),
    ticks at the integers given. ``references``: (y, label) dotted lines named in the legend. ``panels``: groups
    of labels, one panel each with its own y-range (series orders of magnitude apart). ``dodge``: each series
    shifted a little along x, so equal values do not hide each other.
    """
    x = np.asarray(x, dtype=float)
    medians, bands = {}, dict(spread or {})
    for label, y in series.items():
        if len(y) != len(x):
            raise ValueError(f"series {label!r} has {len(y)} values for {len(x)} x values")
        if any(np.ndim(v) > 0 for v in y):
            samples = [np.asarray(v, dtype=float)[~np.isnan(np.asarray(v, dtype=float))] for v in y]
            medians[label] = np.array([np.median(v) if len(v) else np.nan for v in samples])
            bands[label] = tuple(
                np.array([np.percentile(v, q) if len(v) else np.nan for v in samples]) for q in (25, 75)
            )
        else:
            medians[label] = np.asarray(y, dtype=float)
    groups = [list(g) for g in panels] if panels else [list(series)]
    unknown = [label for g in groups for label in g if label not in series]
    if unknown:
        raise ValueError(f"panels name series that are not given: {unknown}")
    fig, axes = figure(len(groups), 1, figsize=(7.5, 3.8 + 2.4 * (len(groups) - 1)), sharex=True, squeeze=False)
    looks = styles(series)
    width = (x.max() - x.min()) if len(x) > 1 else 1.0
    for ax, group in zip(axes[:, 0], groups):
        for i, label in enumerate(group):
            xi = x + (0.012 * width * (i - (len(group) - 1) / 2) if dodge else 0.0)
            ax.plot(xi, medians[label], ms=4, lw=1.3, label=label, **looks[label])
            if label in bands:
                lo, hi = bands[label]
                ax.fill_between(xi, lo, hi, color=looks[label]["color"], alpha=0.15, lw=0)
        for y, text in references:
            reference(ax, y, text)
        if log:
            ax.set_yscale("log")
            log_axis(ax)
        if counts:
            count_axis(ax, x)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        handles, labels = ax.get_legend_handles_labels()
        if any(label in bands for label in group):
            handles.append(Patch(color="0.5", alpha=0.3, lw=0))
            labels.append(spread_label)
        ax.legend(handles, labels, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, borderaxespad=0)
    axes[-1, 0].set_xlabel(xlabel)
    if title:
        set_title(axes[0, 0] if len(groups) == 1 else fig, title)
    return save(fig, path)
