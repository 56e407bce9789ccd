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
from matplotlib.legend_handler import HandlerTuple  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from ocpkit.sim.ticks import count_axis, log_axis, number, numeric_ticks, reference_ticks  # noqa: E402, F401 - plots.number: re-exported

BOX_CONVENTION = "box: quartiles; line: median; whiskers: 1.5 IQR; dots: outliers"
SAVE = {"dpi": 130, "bbox_inches": "tight", "pad_inches": 0.05}  # tight: an outside legend is never cut
STRIP_BELOW = 10  # groups with fewer points are drawn point by point (a box of 5 points hides which they are)
COLOURS = tuple(f"C{i}" for i in range(10))
MARKERS = ("o", "s", "^", "v", "D", "P", "X", "*", "<", ">")
# Quartile bands of one figure's series, one hatch each: overlapping translucent bands otherwise blend into one grey.
HATCHES = ("////", "\\\\", "....", "xxxx", "||||", "----", "++++", "oo")
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


def _band_look(colour, hatch: str) -> dict:
    """A quartile band: faint fill, the series's colour in its own hatch (bands over each other stay apart)."""
    rgb = matplotlib.colors.to_rgb(colour)
    return {"facecolor": (*rgb, 0.08), "edgecolor": (*rgb, 0.55), "hatch": hatch, "lw": 0}


def _missing_look(ax, colour) -> dict:
    """A point with no value: an × at the bottom of the axes, at its x."""
    from matplotlib.transforms import blended_transform_factory

    transform = blended_transform_factory(ax.transData, ax.transAxes)
    return {"marker": "x", "ls": "none", "color": colour, "ms": 7, "mew": 1.5, "transform": transform, "clip_on": False}


def reference(ax, y: float, label: str):
    """A dotted horizontal reference line at ``y``, named in the legend (e.g. "ratio 1: traditional MPC")."""
    return ax.axhline(y, color="k", lw=0.8, ls=":", label=label, zorder=1)


def legend_outside(ax, **kwargs):
    """The axes' legend to the right of it: it covers no data and constrained layout makes room for it."""
    return ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, borderaxespad=0, **kwargs)


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
    names=None,
    unit: str = "seed",
) -> Path:
    """One group of values per label: every value as a dot and the median as a bar when each group has fewer
    than :data:`STRIP_BELOW` (a box of 5 points hides which they are), else box plots in the paper's convention
    (quartile box, median marker, 1.5 IQR whiskers, outliers as dots). Numeric labels (knots, horizons) sit at
    their values on a numeric x axis, logarithmic where they span a decade or more. ``references``: (y, legend
    label) of dotted lines, as :func:`lines` takes them; ``colours``: one per group (default: all C0); ``names``:
    {legend name: colour} when the colours mean something (controllers); ``unit``: what one value is ("seed")."""
    if len(labels) != len(data):
        raise ValueError(f"labels and data must have the same length, got {len(labels)} and {len(data)}")
    data = [np.asarray(d, dtype=float) for d in data]
    colours = list(colours) if colours is not None else ["C0"] * len(labels)
    numeric = len(labels) > 0 and all(isinstance(v, (int, float, np.integer, np.floating)) for v in labels)
    # categories get room each (up to a page's width); a numeric axis places values by scale, not by count
    fig, ax = figure(figsize=(8.0 if numeric else min(16.0, max(6, 0.5 * len(labels) + 2.5)), 3.8))
    positions = np.asarray(labels, dtype=float) if numeric else np.arange(1, len(labels) + 1, dtype=float)
    logx = numeric and positions.min() > 0 and positions.max() / positions.min() >= 10
    half = _half_widths(positions, logx)
    legend = []  # (handle, label) of the marks, in the colours they are drawn in
    one_colour = len(set(colours)) == 1 or names is None
    dot_face = colours[0] if len(set(colours)) == 1 else "0.6"  # a colour that names nothing stays neutral
    if max((len(d) for d in data), default=0) < STRIP_BELOW:
        for x, h, values, colour in zip(positions, half, data, colours):
            order = np.argsort(values)
            # spread the dots sideways in value order: equal values sit side by side, not on top of each other
            t = np.linspace(-0.67, 0.67, len(values)) if len(values) > 1 else np.zeros(1)
            ax.plot(_spread(x, h * t, logx), values[order], "o", color=colour, ms=5, alpha=0.8, mec="k", mew=0.4)
            if len(values):
                ax.hlines(np.median(values), *_spread(x, np.array([-h, h]), logx), color="k", lw=2)
        if one_colour:
            legend.append((Line2D([], [], marker="o", ls="none", color=dot_face, mec="k", mew=0.4), f"one {unit}"))
        else:
            legend += [
                (Line2D([], [], marker="o", ls="none", color=c, mec="k", mew=0.4), f"{n}: one {unit}")
                for n, c in names.items()
            ]
        legend.append((Line2D([], [], color="k", lw=2), "median"))
        counts = {len(d) for d in data}
        ax.set_xlabel(xlabel + f"\n({'/'.join(map(str, sorted(counts)))} {unit}s per group)")
    else:
        widths = _spread(positions, half, logx) - _spread(positions, -half, logx)
        parts = ax.boxplot(
            data,
            positions=positions,
            widths=widths,
            manage_ticks=False,
            patch_artist=True,
            medianprops={"color": "k", "lw": 1.5},
            flierprops={"marker": ".", "markersize": 3},
        )
        for box, colour in zip(parts["boxes"], colours):
            box.set(facecolor=colour, alpha=0.35)
        if not one_colour:
            legend += [(Patch(facecolor=c, alpha=0.35), n) for n, c in names.items()]
        ax.set_xlabel(f"{xlabel}\n({BOX_CONVENTION})")
    if numeric:
        if logx:
            ax.set_xscale("log")
        ax.set_xlim(_spread(positions[0], -1.6 * half[0], logx), _spread(positions[-1], 1.6 * half[-1], logx))
        numeric_ticks(ax, positions, logx)
    else:
        ax.set_xticks(
            positions,
            [str(l) for l in labels],
            fontsize=8,
            rotation=0 if max(len(str(l)) for l in labels) <= 12 else 30,
            ha="center" if max(len(str(l)) for l in labels) <= 12 else "right",
        )
    ax.set_ylabel(ylabel)
    legend += [(reference(ax, y, text), text) for y, text in references]
    if log:
        ax.set_yscale("log")
        log_axis(ax)
    reference_ticks(ax, [y for y, _ in references])
    ax.grid(axis="y", alpha=0.3)
    if legend:
        legend_outside(ax, handles=[h for h, _ in legend], labels=[l for _, l in legend])
    if title:
        set_title(ax, title)
    return save(fig, path)


def _half_widths(positions, logx: bool) -> np.ndarray:
    """Each group's half width on the x axis: 0.3 of the gap to its nearer neighbour (in decades on a log axis), so
    that sparse values (1, 2, 3 knots) get visible boxes beside dense ones (40 … 50); 0.3 for a lone group."""
    where = np.log10(positions) if logx else np.asarray(positions, dtype=float)
    order = np.argsort(where)
    gaps = np.diff(where[order])
    gaps = np.where(gaps > 0, gaps, np.inf)  # equal values share a position: no gap between them
    nearer = np.minimum(np.r_[np.inf, gaps], np.r_[gaps, np.inf])
    half = np.empty(len(positions))
    half[order] = 0.3 * np.where(np.isfinite(nearer), nearer, 1.0)
    return half


def _spread(x, offset, logx: bool):
    """``x`` moved by ``offset`` (decades on a log axis)."""
    return x * 10.0**offset if logx else x + offset


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
        handles, labels, missing = [], [], False
        for i, label in enumerate(group):
            xi = x + (0.012 * width * (i - (len(group) - 1) / 2) if dodge else 0.0)
            (line,) = ax.plot(xi, medians[label], ms=4, lw=1.3, label=label, **looks[label])
            handle = line
            if label in bands:
                band = _band_look(looks[label]["color"], HATCHES[i % len(HATCHES)])
                ax.fill_between(xi, *bands[label], **band)
                handle = (Patch(**band), line)
            handles.append(handle)
            labels.append(label)
            gaps = np.isnan(medians[label])
            if gaps.any() and not gaps.all():  # a point not run or without a value, marked where it would be
                missing = True
                ax.plot(xi[gaps], np.full(gaps.sum(), 0.04), **_missing_look(ax, looks[label]["color"]))
        for y, text in references:
            handles.append(reference(ax, y, text))
            labels.append(text)
        if log:
            ax.set_yscale("log")
            log_axis(ax)
        reference_ticks(ax, [y for y, _ in references])
        if counts:
            count_axis(ax, x)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        if any(label in bands for label in group):
            handles.append(Patch(facecolor="none", edgecolor="0.4", hatch="////", lw=0))
            labels.append(spread_label)
        if missing:
            handles.append(Line2D([], [], marker="x", ls="none", color="0.3", ms=7, mew=1.5))
            labels.append("×: no value at this x (not run or failed)")
        ax.legend(
            handles,
            labels,
            loc="upper left",
            bbox_to_anchor=(1.01, 1.0),
            fontsize=7,
            borderaxespad=0,
            handler_map={tuple: HandlerTuple(ndivide=1)},
        )
    axes[-1, 0].set_xlabel(xlabel)
    if title:
        set_title(axes[0, 0] if len(groups) == 1 else fig, title)
    return save(fig, path)
