"""Figures are readable and honest, checked on each figure as :func:`ocpkit.sim.plots.save` writes it: no text outside
the saved image or over another title, label or legend; no legend entry whose series another one draws over
(same look, same pixels) and no blended histogram colours the legend does not have; integer ticks on count
axes (links, knots); every seed drawn where a group has few. Each figure kind is rendered through
``ocpkit.sim.plots`` and through the studies' reports on small synthetic tables."""

from itertools import combinations

import matplotlib as mpl
import numpy as np
import pandas as pd
import pytest
from matplotlib.collections import PolyCollection
from matplotlib.container import BarContainer
from matplotlib.lines import Line2D
from matplotlib.figure import Figure
from matplotlib.transforms import TransformedBbox

from ocpkit.sim import plots
from ocpkit.sim.simulate import Trajectory
from ocpkit.studies import baxter, comparison, horizon, keepout, knots, robustness, solve_times

TOLERANCE_PX = 1.0


class Saved:
    """A figure as saved: what is wrong with it, its width (inches), and the x tick labels of each of its axes."""

    def __init__(self, fig, kwargs):
        self.width = float(fig.get_size_inches()[0])
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        self.problems = []
        canvas = _canvas(fig, kwargs, renderer)
        for name, text in _texts(fig):
            box = text.get_window_extent(renderer)
            if (
                box.x0 < canvas.x0 - TOLERANCE_PX
                or box.x1 > canvas.x1 + TOLERANCE_PX
                or box.y0 < canvas.y0 - TOLERANCE_PX
                or box.y1 > canvas.y1 + TOLERANCE_PX
            ):
                self.problems.append(f"{name} {text.get_text()!r} outside the saved canvas")
        self.problems += _overlapping(fig, renderer)
        for ax in fig.axes:
            self.problems += _hidden_series(ax) + _blended(ax) + _bands_alike(ax) + _legend_colours(ax)
            self.problems += _unlabelled_references(ax)
        self.xticks = [[t.label1.get_text() for t in _ticks_in_view(ax.xaxis)] for ax in fig.axes]
        self.xlocs = [[t.get_loc() for t in _ticks_in_view(ax.xaxis)] for ax in fig.axes]
        self.axes = fig.axes


@pytest.fixture
def saved(monkeypatch):
    """Every figure saved during the test, checked as it was written (the first file of each figure)."""
    records, original = {}, Figure.savefig

    def savefig(fig, fname, **kwargs):
        original(fig, fname, **kwargs)
        if id(fig) not in records:
            records[id(fig)] = Saved(fig, kwargs)

    monkeypatch.setattr(Figure, "savefig", savefig)
    return records


@pytest.fixture
def figures_only(monkeypatch):
    """The studies' reports without their claims (other tests check those; some read trial arrays from a store)."""
    for module in (robustness, solve_times, knots, horizon, comparison, keepout):
        if hasattr(module, "claims"):
            monkeypatch.setattr(module, "claims", lambda *args, **kwargs: [])


def _canvas(fig, kwargs, renderer):
    """The saved image's extent in display pixels, as savefig computes it from the same arguments."""
    if kwargs.get("bbox_inches") == "tight":
        pad = kwargs.get("pad_inches", mpl.rcParams["savefig.pad_inches"])
        inches = fig.get_tightbbox(renderer).padded(0 if pad == "layout" else pad)
        return TransformedBbox(inches, fig.dpi_scale_trans)
    return fig.bbox


def _ticks_in_view(axis):
    lo, hi = sorted(axis.get_view_interval())
    eps = 1e-9 * max(abs(lo), abs(hi), 1.0)
    return [
        t
        for t in axis.get_major_ticks() + axis.get_minor_ticks()
        if lo - eps <= t.get_loc() <= hi + eps and t.label1.get_visible() and t.label1.get_text()
    ]


def _texts(fig):
    """Every text artist drawn: suptitle, figure texts and legends; per axes its titles, labels, tick labels,
    texts and legend."""
    out = [("suptitle", fig._suptitle)] if fig._suptitle is not None else []
    out += [("figure text", t) for t in fig.texts]
    for legend in fig.legends:
        out += [("legend", t) for t in legend.get_texts()]
    for ax in fig.axes:
        out += [("title", t) for t in (ax.title, ax._left_title, ax._right_title)]
        out += [("axis label", ax.xaxis.label), ("axis label", ax.yaxis.label)]
        out += [("tick label", t.label1) for axis in (ax.xaxis, ax.yaxis) for t in _ticks_in_view(axis)]
        out += [("text", t) for t in ax.texts]
        if ax.get_legend() is not None:
            out += [("legend", t) for t in ax.get_legend().get_texts()]
    return [(name, t) for name, t in out if t.get_visible() and t.get_text().strip()]


def _overlapping(fig, renderer) -> list:
    """Titles, axis labels, suptitle and legends drawn over each other; tick labels of one axis over each other."""
    boxes = [
        (f"{name} {t.get_text()!r}", t.get_window_extent(renderer))
        for name, t in _texts(fig)
        if name in ("suptitle", "title", "axis label")
    ]
    legends = list(fig.legends) + [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
    boxes += [(f"legend {[t.get_text() for t in g.get_texts()][:2]}", g.get_window_extent(renderer)) for g in legends]
    out = [f"{a} over {b}" for (a, p), (b, q) in combinations(boxes, 2) if _intersection(p, q) > 4]
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            labels = [t.label1 for t in _ticks_in_view(axis)]
            out += [
                f"tick labels {a.get_text()!r} and {b.get_text()!r} overlap"
                for a, b in combinations(labels, 2)
                if _intersection(a.get_window_extent(renderer), b.get_window_extent(renderer)) > 4
            ]
    return out


def _intersection(p, q) -> float:
    return max(0.0, min(p.x1, q.x1) - max(p.x0, q.x0)) * max(0.0, min(p.y1, q.y1) - max(p.y0, q.y0))


def _look(line):
    return (
        line.get_marker() if line.get_marker() not in ("None", "", " ", None) else None,
        line.get_linestyle(),
        str(line.get_markevery()),
    )


def _hidden_series(ax) -> list:
    """Legend entries whose line another labelled line draws over: the same look on the same pixels."""
    shown = [l for l in ax.get_lines() if l.get_visible() and not l.get_label().startswith("_") and len(l.get_xdata())]
    out = []
    for a, b in combinations(shown, 2):
        if _look(a) != _look(b):
            continue
        pa, pb = (l.get_transform().transform(np.asarray(l.get_xydata(), float)) for l in (a, b))
        if pa.shape == pb.shape and np.nanmax(np.abs(pa - pb)) < 1.5:
            out.append(f"{a.get_label()!r} and {b.get_label()!r} draw the same pixels in the same style")
    return out


def _blended(ax) -> list:
    """Translucent bars of different series over each other: colours the legend does not have."""
    bars = [c for c in ax.containers if isinstance(c, BarContainer)]
    out = []
    for a, b in combinations(bars, 2):
        for p in a.patches:
            for q in b.patches:
                translucent = min(p.get_facecolor()[3], q.get_facecolor()[3]) < 1
                if (
                    translucent
                    and p.get_height() > 0
                    and q.get_height() > 0
                    and _intersection(p.get_bbox(), q.get_bbox()) > 0
                ):
                    out.append(f"bars of {a.get_label()!r} and {b.get_label()!r} blend")
                    break
            else:
                continue
            break
    return out


def _bands_alike(ax) -> list:
    """Shaded bands of different series that overlap in the same hatch: their translucent fills blend into one
    colour that hides which series is which (issue 51, robustness_pendulum.png)."""
    bands = [c for c in ax.collections if isinstance(c, PolyCollection) and len(c.get_paths())]
    out = []
    for a, b in combinations(bands, 2):
        if a.get_hatch() == b.get_hatch() and _intersection(a.get_datalim(ax.transData), b.get_datalim(ax.transData)):
            out.append(f"two overlapping bands share hatch {a.get_hatch()!r}")
    return out


def _legend_colours(ax) -> list:
    """Legend markers whose colour no drawn point has, and point colours the legend does not name where it names
    colours (issue 51: points coloured per controller under a legend of one blue "one seed")."""
    legend = ax.get_legend()
    if legend is None:
        return []
    dots = [
        l
        for l in ax.get_lines()
        if l.get_marker() == "o" and l.get_linestyle() in ("None", "none", "") and len(l.get_xdata())
    ]
    drawn = {mpl.colors.to_hex(l.get_markerfacecolor()) for l in dots}
    handles = [
        h
        for h in legend.legend_handles
        if isinstance(h, Line2D) and h.get_marker() == "o" and h.get_linestyle() in ("None", "none", "")
    ]
    named = {mpl.colors.to_hex(h.get_markerfacecolor()) for h in handles}
    neutral = mpl.colors.to_hex("0.6")
    out = [f"legend marker colour {c} is no drawn point's" for c in sorted(named - drawn - {neutral})]
    if drawn and named and neutral not in named:
        out += [f"points in {c} have no legend entry" for c in sorted(drawn - named)]
    return out


def _unlabelled_references(ax) -> list:
    """Dotted reference lines (y = 1: 'the same as traditional MPC') whose value no y tick label names."""
    labels = {t.label1.get_text().replace("−", "-") for t in _ticks_in_view(ax.yaxis)}
    out = []
    for line in ax.get_lines():
        y = line.get_ydata()
        if line.get_linestyle() == ":" and not line.get_label().startswith("_") and len(set(y)) == 1:
            lo, hi = sorted(ax.get_ylim())
            if lo <= y[0] <= hi and not any(_same_number(t, y[0]) for t in labels):
                out.append(f"reference line {line.get_label()!r} at y = {y[0]} has no tick label")
    return out


def _same_number(text, value) -> bool:
    try:
        return np.isclose(float(text), value)
    except ValueError:
        return False


def _assert_clean(saved):
    assert saved, "no figure was saved"
    problems = [p for record in saved.values() for p in record.problems]
    assert not problems, "\n".join(problems)


def _integer_ticks(labels):
    values = [float(s.replace("−", "-")) for s in labels]
    assert values and all(v == int(v) for v in values), labels


FORMULATIONS = [solve_times.label(f, k) for f in solve_times.FORMS for k in (5, None)]


def test_lines_with_long_labels_on_counts(saved, tmp_path):
    links = np.array([1, 3, 7, 13])
    series = {label: np.geomspace(1, 10 ** (i + 1), 4) for i, label in enumerate(FORMULATIONS)}
    plots.lines(
        links,
        series,
        tmp_path / "t",
        xlabel="number of links",
        ylabel="median solve time [ms]",
        log=True,
        title="Median optimization solve time, horizon 50 (20 cold solves each)",
    )
    _assert_clean(saved)
    _integer_ticks(next(iter(saved.values())).xticks[0])


def test_lines_near_equal_series_are_all_visible(saved, tmp_path):
    links = np.array([1, 3, 6, 9, 13])
    near = np.array([1.10, 1.11, 1.09, 1.10, 1.11])
    series = {
        "knots 3 (QP)": near,
        "EMPC 1 gen": near,
        "EMPC 3 gen": near * 1.001,
        "CEM": near * 1.01,
        "MPPI": near * 0.99,
        "EMPC 1 gen (paper)": np.array([1.2, 12, 66, 210, 500]),
        "EMPC 3 gen (paper)": np.array([1.2, 14, 21, 320, 230]),
    }
    plots.lines(
        links,
        series,
        tmp_path / "r",
        xlabel="number of links",
        ylabel="actual cost / traditional MPC",
        log=True,
        title="Actual cost relative to traditional MPC (3 start/goal pairs per robot)",
    )
    _assert_clean(saved)


def test_closed_loop_with_sixteen_controllers(saved, tmp_path):
    """The demo's figure: 16 controllers on one pendulum, the QP configurations on the same trajectory."""
    t = np.linspace(0, 2, 201)
    qp = Trajectory(t=t, x=np.column_stack([np.sin(t), np.cos(t)]), u=np.cos(t[:-1])[:, None], goal=np.array([1, 0.0]))
    trajs = {}
    for knots_label in ("traditional", "knots=5"):
        for form in ("sparse", "condensed"):
            for qp_name in ("proxqp", "osqp"):
                trajs[f"qp {form} {qp_name} {knots_label}"] = qp
        for k, name in enumerate(("cem", "empc", "ipopt", "mppi")):
            shift = 0.02 * (k + 1) * (knots_label == "knots=5")
            trajs[f"{name} {knots_label}"] = Trajectory(t=t, x=qp.x + shift, u=qp.u + shift, goal=qp.goal)
    plots.closed_loop(
        trajs,
        tmp_path / "demo.png",
        title="pendulum: closed loop, seed 0",
        state_names=["q [rad]", "qd [rad/s]"],
        input_names=["tau [N·m]"],
    )
    _assert_clean(saved)


def test_small_groups_show_every_seed(saved, tmp_path):
    values = [np.array([900.0, 1200, 1500, 8000, 15000]), np.array([700.0, 800, 1000, 1100, 1300])]
    plots.boxes(
        ["knots 3 (QP)", "EMPC, penalized fitness"],
        values,
        tmp_path / "k",
        xlabel="controller",
        ylabel="actual penalized cost",
        title="keep-out",
    )
    _assert_clean(saved)
    ax = next(iter(saved.values())).axes[0]
    points = np.vstack(
        [l.get_xydata() for l in ax.get_lines() if l.get_marker() not in ("None", "", None)]
        + [c.get_offsets() for c in ax.collections if len(c.get_offsets())]
        + [np.empty((0, 2))]
    )
    for i, group in enumerate(values, start=1):
        for v in group:
            assert np.any((np.abs(points[:, 0] - i) < 0.5) & np.isclose(points[:, 1], v)), f"group {i}: {v} not drawn"


def _robustness_table():
    rng = np.random.default_rng(0)
    rows = [
        {
            "status": "ok",
            "problem": p,
            "knots": k,
            "error_multiplier": e,
            "seed": s,
            "actual_cost": (1 + abs(e - 1) * (2 if k == 2 else 1)) * (1 + 0.05 * rng.random()) * (10 + s),
            "overshoot": 5 * rng.random(),
            "rise_time": 0.3 + 0.1 * rng.random(),
        }
        for p in ("pendulum:paper", "puma560")
        for k in (2, 4, 8, np.nan)
        for e in (0.5, 1.0, 1.5)
        for s in range(3)
    ]
    return pd.DataFrame(rows)


def test_robustness_report(saved, figures_only, tmp_path):
    robustness.report(_robustness_table(), tmp_path)
    _assert_clean(saved)


def _solve_times_table():
    rows = []
    for links in (1, 3, 7, 13):
        for h in solve_times.HORIZONS:
            for form in solve_times.FORMS:
                for k in (5, np.nan):
                    m = 1e-3 * links * (3 if form == "condensed" and k != k else 1) * h / 50
                    rows.append(
                        {
                            "status": "ok",
                            "links": links,
                            "horizon": h,
                            "form": form,
                            "knots": k,
                            "qp": "osqp",
                            "states": 20,
                            "seed": 0,
                            "solve_median": m,
                            "solve_q1": 0.8 * m,
                            "solve_q3": 1.3 * m,
                            "total_median": 2 * m,
                            "total_q1": 1.6 * m,
                            "total_q3": 2.6 * m,
                            "model_median": 1e-4 * links,
                            "build_median": 1e-4,
                            "failures": 0,
                            "load": 1.0,
                        }
                    )
    return pd.DataFrame(rows)


def test_solve_times_report(saved, figures_only, tmp_path):
    table = _solve_times_table()
    gone = (table["links"] == 13) & (table["horizon"] == 100) & (table["form"] == "condensed") & table["knots"].isna()
    solve_times.report(table[~gone], tmp_path)
    _assert_clean(saved)
    for record in saved.values():
        _integer_ticks(record.xticks[-1])
    # the 13-link point not run at T = 100 is marked where it would be (issue 51), not silently left out
    marks = [l for record in saved.values() for ax in record.axes for l in ax.get_lines() if l.get_marker() == "x"]
    assert [list(l.get_xdata()) for l in marks] == [[13.0], [13.0]]  # the solve and the total time at T = 100


def test_overlapping_bands_and_coloured_points_are_told_apart(saved, tmp_path):
    """Two series' quartile bands over each other get different hatches; points coloured per controller get a
    legend entry per colour (issue 51: robustness_pendulum.png, robustness_mujoco_*.png)."""
    rng = np.random.default_rng(1)
    plots.lines(
        [1, 2, 3],
        {c: [1 + rng.random(5) for _ in range(3)] for c in ("a", "b", "c")},
        tmp_path / "bands",
        xlabel="x",
        ylabel="y",
        references=[(1.0, "1: reference")],
    )
    plots.boxes(
        ["A\nf", "B\nf"],
        [rng.random(3) + 0.5, rng.random(3) + 0.5],
        tmp_path / "dots",
        xlabel="x",
        ylabel="y",
        colours=["C1", "C2"],
        names={"A": "C1", "B": "C2"},
        references=[(1.0, "1: no change")],
    )
    _assert_clean(saved)
    bands, dots = (record.axes[0] for record in saved.values())
    assert len({c.get_hatch() for c in bands.collections}) == 3
    assert [t.get_text() for t in dots.get_legend().get_texts()][:2] == ["A: one seed", "B: one seed"]


def _closed_loop_rows(key, values, seeds, cost):
    return pd.DataFrame(
        [{"status": "ok", key: v, "seed": s, "actual_cost": cost(v, s)} for v in values for s in range(seeds)]
    )


def test_knots_and_horizon_reports(saved, figures_only, tmp_path):
    knots_df = pd.concat(
        [
            _closed_loop_rows("knots", [1, 2, 4, 10], 5, lambda k, s: 1 + 1 / k + 0.01 * s).assign(
                horizon=knots.HORIZON
            ),
            _closed_loop_rows("knots", [np.nan], 5, lambda k, s: 1.0).assign(horizon=knots.REFERENCE_HORIZON),
        ]
    ).assign(problem="pendulum")
    knots.report(knots_df.reset_index(drop=True), tmp_path)
    horizon_df = _closed_loop_rows("horizon", [5, 10, 50, 100], 5, lambda h, s: 1 + 20 * (s == 4) / h + 1 / h).assign(
        problem="pendulum", knots=np.nan
    )
    horizon.report(horizon_df, tmp_path)
    _assert_clean(saved)
    knots_fig, horizon_fig = saved.values()
    # numeric x axes (issue 51): the knot counts at their values on a log axis, not evenly spaced categories
    assert knots_fig.axes[0].get_xscale() == "log" and knots_fig.xlocs[0] == [1, 2, 4, 10]
    assert horizon_fig.axes[0].get_xscale() == "log" and horizon_fig.xlocs[0] == [5, 10, 50, 100]


def _comparison_table():
    rows = []
    for links in (1, 3, 6):
        for c in comparison.CONTROLLERS:
            for s in range(3):
                paper = "paper" in c
                rows.append(
                    {
                        "status": "ok",
                        "links": links,
                        "controller": c,
                        "seed": s,
                        "record": False,
                        "actual_cost": 10 * (1 + (50 * links if paper else 0.1 * (c != comparison.REFERENCE))),
                        "final_error": 0.01,
                        "solve_median": 1e-3 * links,
                        "total_median": 2e-3 * links,
                        "model_median": 1e-4,
                        "hessian_condition": 1e3,
                        "duration": 10.0,
                        "population": 1024,
                        "device": "cpu",
                        "fallbacks": 0,
                        "load": 1.0,
                        "fallback_causes": "",
                        "child_win_rate": np.nan,
                    }
                )
    return pd.DataFrame(rows)


def test_comparison_report(saved, figures_only, tmp_path):
    comparison.report(_comparison_table(), tmp_path)
    _assert_clean(saved)


def test_comparison_sample_response(saved, tmp_path):
    t = np.linspace(0, 10, 101)
    trajs = {
        c: Trajectory(
            t=t, x=np.column_stack([np.sin(t + k) * (k + 1) for k in range(12)]), u=np.zeros((100, 6)), goal=np.ones(12)
        )
        for c in list(comparison.CONTROLLERS)[:3]
    }
    comparison.responses(
        trajs, tmp_path / "sample", title="6-link robot, start/goal seed 0: joint angles (dotted: goals)"
    )
    _assert_clean(saved)


def test_keepout_report(saved, figures_only, tmp_path):
    rows = [
        {
            "status": "ok",
            "controller": c,
            "seed": s,
            "actual_cost": 1000 * (1 + k + s),
            "penalty": 10.0,
            "steps_inside": 3,
            "final_error": 0.01,
            "solve_median": 1e-3,
            "duration": 5.0,
            "population": 1024,
            "device": "cpu",
            "fallbacks": 0,
            "load": 1.0,
        }
        for k, c in enumerate(keepout.CONTROLLERS)
        for s in range(5)
    ]
    keepout.report(pd.DataFrame(rows), tmp_path)
    _assert_clean(saved)


def test_baxter_solve_time_histograms(saved, tmp_path):
    rng = np.random.default_rng(1)
    times = {
        baxter.QP: rng.lognormal(-6, 0.3, 400),
        baxter.EMPC: rng.lognormal(-5.8, 0.3, 400),
        baxter.EMPC_PAPER: rng.lognormal(-5.9, 0.3, 400),
    }
    baxter._histogram(times, pd.Series({c: 1e3 * np.median(t) for c, t in times.items()}), tmp_path / "h")
    _assert_clean(saved)


def test_robustness_mujoco_report_legend_names_each_controller(saved, tmp_path):
    """Points coloured per controller, a legend entry per controller in its colour (issue 51)."""
    rows = [
        {
            "status": "ok",
            "problem": "nlink:2",
            "controller": c,
            "plant": plant,
            "mismatch": mismatch,
            "level": level,
            "seed": s,
            "actual_cost": (10.0 + s) * (1 if plant == "ocpkit" else 1.2 + 0.1 * k),
            "final_error": 0.1,
            "fallbacks": 0,
            "fallback_causes": "",
            "child_win_rate": np.nan,
            "load": 1.0,
        }
        for k, c in enumerate(robustness.MUJOCO_CONTROLLERS)
        for plant, mismatch, level in (("ocpkit", "none", 0.0), ("mujoco", "friction", 0.1))
        for s in range(3)
    ]
    robustness.mujoco_report(pd.DataFrame(rows), tmp_path)
    _assert_clean(saved)
    texts = [t.get_text() for t in next(iter(saved.values())).axes[0].get_legend().get_texts()]
    assert texts[:3] == [f"{c}: one seed" for c in robustness.MUJOCO_CONTROLLERS]


def test_a_numeric_axis_keeps_a_page_width_however_many_values(saved, tmp_path):
    """The full knots sweep (50 knot counts) was drawn 3,577 px wide: the width grew with the number of groups."""
    rng = np.random.default_rng(2)
    knot_counts = list(range(1, 51))
    plots.boxes(knot_counts, [1 + rng.random(30) for _ in knot_counts], tmp_path / "knots", xlabel="p", ylabel="r")
    plots.boxes(
        [f"c{i}" for i in range(60)], [rng.random(30) for _ in range(60)], tmp_path / "many", xlabel="c", ylabel="y"
    )
    _assert_clean(saved)
    widths = [record.width for record in saved.values()]
    assert widths[0] <= 8.0 and widths[1] <= 16.0
    # each box as wide as its nearer neighbour allows: 1 and 2 knots visible beside 49 and 50
    half = plots._half_widths(np.array([2.0, 1.0, 50.0, 49.0]), logx=True)
    assert half[1] == half[0] == pytest.approx(0.3 * np.log10(2)) and half[2] == pytest.approx(0.3 * np.log10(50 / 49))
