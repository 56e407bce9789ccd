"""The paper's pendulum set-up: what its text fixes, what it leaves open, and the one anchor cell that settles it.

Section III-C fixes the model (eq. inverted_pendulum), dt = 0.01 s, T = 50, 100 Hz and a 1 s closed loop; it does
not print Q, R, the torque limit, m, l, b or how start and goal are drawn. We keep ours for all but the cost's shape:
Q's position weight is the scale (the optimum does not depend on it) and the two ratios left, Q's velocity weight
and R, are calibrated on ONE anchor cell of Tables I–II — traditional MPC at error multiplier 1 (4.17 % overshoot,
0.38 s rise time) — by :func:`calibrate`, once; the result is stored with its provenance in
:data:`ocpkit.problems.pendulum.PAPER_COST` and held fixed. Every other cell of the tables is then a prediction,
printed beside the paper's number by :func:`fidelity`. Rerun with ``python -m ocpkit.studies.calibration``.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from ocpkit.problems.pendulum import PAPER_COST, Pendulum
from ocpkit.sim.metrics import step_metrics
from ocpkit.sim.plots import number
from ocpkit.studies.report import markdown_table

# The paper's Tables I–II (inverted pendulum): percent overshoot and rise time [s] per error multiplier, for
# 2, 4 and 8 knots and traditional MPC, as printed (a value's printed digits are its precision).
PAPER_COLUMNS = ("2 knots", "4 knots", "8 knots", "traditional")
PAPER_TABLES = {
    "overshoot": {
        0.5: (37.7, 40.2, 40.3, 43.5),
        0.6: (26.5, 29.3, 29.3, 31.1),
        0.7: (18.6, 19.8, 20.8, 22),
        0.8: (12.1, 12.3, 13.8, 14.6),
        0.9: (6.88, 6.78, 8.13, 8.64),
        1.0: (3.05, 2.96, 3.89, 4.17),
        1.1: (0.772, 0.732, 1.18, 1.3),
        1.2: (0.0252, 0.0171, 0.0729, 0.0919),
        1.3: (0, 0, 0, 0),
        1.4: (0, 0, 0, 0),
        1.5: (0, 0, 0, 0),
    },
    "rise_time": {
        0.5: (0.85, 0.41, 0.3, 0.28),
        0.6: (0.65, 0.36, 0.3, 0.29),
        0.7: (0.56, 0.35, 0.31, 0.3),
        0.8: (0.54, 0.36, 0.32, 0.31),
        0.9: (0.54, 0.38, 0.35, 0.34),
        1.0: (0.59, 0.43, 0.39, 0.38),
        1.1: (0.67, 0.5, 0.45, 0.44),
        1.2: (0.78, 0.6, 0.55, 0.54),
        1.3: (0.89, 0.71, 0.67, 0.66),
        1.4: (0.96, 0.81, 0.77, 0.76),
        1.5: (1.02, 0.88, 0.85, 0.84),
    },
}
ANCHOR = {"error_multiplier": 1.0, "controller": "traditional"}
ANCHOR_VALUES = {m: PAPER_TABLES[m][1.0][PAPER_COLUMNS.index("traditional")] for m in PAPER_TABLES}
SEEDS = range(30)  # the full robustness study's seeds: the anchor is their median, as the report's tables are
# The search (calibrate): Q's velocity weights tried, and the bracket in which R is solved for each.
VELOCITY_WEIGHTS = (0.003, 0.01, 0.03, 0.05, 0.07, 0.1, 0.15, 0.2, 0.3)
INPUT_WEIGHTS = (1e-3, 1.0)

# Each setting of the robustness study: (setting, value, source). "paper": quoted from its text; "ours": why.
SETUP = (
    ("model", "m l² q̈ + b q̇ + m g l sin q = τ", "paper III-C, eq. inverted_pendulum"),
    ("m, l, b, g", "1 kg, 0.5 m, 0.1 N·m·s, 9.81 m/s²", "ours: the paper prints no values"),
    ("torque limit", "|τ| ≤ 5 N·m", "ours: holds any angle against gravity (m g l = 4.9 N·m); the paper prints none"),
    ("Q position weight", "10", "ours: the scale of the cost (the optimum does not depend on it)"),
    ("Q velocity weight, R", "calibrated (below)", "ours: calibrated on the anchor cell; the paper prints neither"),
    ("dt, rate", "0.01 s, 100 Hz", "paper III-C: 'running MPC at a rate of 100 Hz … discretized at .01 s'"),
    ("horizon", "T = 50", "paper III-C: 'a set horizon (50 time steps)' (the knots sweep's; Section IV states none)"),
    (
        "closed loop",
        "1 s, rest to rest",
        "paper III-C: 'for one second from an initial position at rest' (the knots sweep's; Table II's 1.02 s rise "
        "time needs a longer run, but 2 s, tried, adds late overshoot the paper does not have: see below)",
    ),
    ("start, goal", "uniform in [−π, π]", "paper III-C: 'sampled from a random uniform distribution' (range ours)"),
    ("error multiplier", "scales m and l of the model", "paper IV-A: 'applied to both the mass and length'"),
    ("controllers", "2, 4, 8 knots, traditional", "paper Tables I–II"),
    ("Tables' statistic", "median over seeds, steps ≥ 0.1 rad", "ours: the paper does not say how it aggregates"),
    (
        "far from the anchor",
        "not reproduced: error 0.5, traditional MPC overshoots 21.6 % over seeds 0–29 (paper 43.5 %)",
        "ours: no setting we tried and the paper supports reproduces error 0.5 (each tried alone, re-anchored; the "
        "next table)",
    ),
)
# What was tried to reproduce the cells far from the anchor (issue 51): each setting alone on this set-up, R re-fitted
# for the anchor's overshoot at the calibrated velocity weight (30 seeds); then the three together that fit best, both
# weights re-fitted (a linear pendulum without a binding torque limit gives every start the same response: 1 seed).
# None: not predicted (no anchor).
# (setting, what the paper's text says of it, anchor overshoot % and rise time s, traditional MPC's overshoot % at
# error 0.5 (paper 43.5) and rise time s at error 1.5 (paper 0.84), adopted or not and why). Measured 2026-12-04.
TRIED = (
    ("none (this set-up)", "", (4.17, 0.38), 21.56, 0.49, "the set-up"),
    (
        "2 s closed loop",
        "supported: Table II's 1.02 s rise time needs a run longer than 1 s",
        (4.17, 0.385),
        21.56,
        0.51,
        "no: late overshoot 3.3–6.6 % at errors 1.1–1.5, where the paper has 0–1.3",
    ),
    (
        "linear pendulum (g = 0)",
        "open: IV-A does not say which of III-C's two pendulums; IV-B calls the multiplier over/under-estimated "
        "inertia, exact only with g = 0",
        (4.17, 0.455),
        33.56,
        0.56,
        "no: the anchor's rise time breaks (0.455 s)",
    ),
    ("no torque limit", "open: the paper prints none", (4.17, 0.28), 24.99, 0.42, "no: anchor rise time 0.28 s"),
    (
        "horizon T = 100",
        "open: Section IV states no horizon (III-C's reference is 1 s)",
        (4.35, 0.49),
        None,
        None,
        "no: no anchor: rise time ≥ 0.425 s at every Q velocity weight (0, 0.01, 0.07) and R (0.003–1) tried; the "
        "overshoot nearest 4.17 % (4.35) at R = 0.3 with 0.49 s (so not predicted)",
    ),
    (
        "g = 0, no torque limit, T = 100, 2 s (together)",
        "g = 0, no torque limit, T = 100: open (not stated for Section IV); 2 s: supported",
        (4.17, 0.38),
        44.17,
        0.87,
        "no: the paper states none of the first three (all Table I–II cells: 13 of 43 overshoot, 9 of 43 rise time "
        "within its precision; traditional MPC's rise times within 0.05 s, 2 knots' up to 0.24 s too slow)",
    ),
)

# The Puma 560's settings (knots, horizon, robustness: "puma560:paper"), and why traditional MPC at a short horizon
# costs as little as it did before the paper's cost was used (issue 51).
PUMA_SETUP = (
    ("Puma: model", "M(q) q̈ + C(q, q̇) + b q̇ + τ_grav = τ", "paper III-C, eq. puma_dynamics"),
    ("Puma: parameters, b", "Corke & Armstrong-Hélouvry 1994 (RTB mdl_puma560); b = motor B·G²", "ours: none printed"),
    ("Puma: torque limits", "97.6, 186.4, 89.4, 24.2, 20.1, 21.3 N·m", "ours: Armstrong et al. 1986; none printed"),
    ("Puma: Q, R", "Q = diag(100 per angle, 1 per rate), R = 10⁻³ I", "ours: the paper prints no weights"),
    (
        "Puma: terminal weight",
        "Q (x_T weighs as every other state; puma560:paper)",
        "paper III-A, eq. mpc_problem: 'J = Σ_{k=0}^{T−1} [(x_goal − x_k)ᵀ Q (x_goal − x_k) + …]', no terminal "
        "term. Our puma560's default 10 Q made short horizons cheap: traditional MPC at T = 5 over T = 100, per-seed "
        "median over seeds 0–7, 1.105 with 10 Q, 1.735 with Q (T = 10: 1.010 vs 1.109; 4 knots: 1.026 both)",
    ),
    ("Puma: dt, T, closed loop", "0.01 s, T = 50, 1 s rest to rest", "paper III-C (as the pendulum's)"),
    (
        "Puma: start, goal",
        "uniform in the middle half of each joint's range",
        "paper III-C: 'random uniform' (range ours)",
    ),
    (
        "reference horizon",
        "T = 100 (1 s)",
        "paper III-C: 'traditional MPC with a horizon equal to the actual simulation time (one second)'; Fig. 4's "
        "caption says 'a horizon of 50': we follow the text",
    ),
    ("Puma: error multiplier", "scales the whole inertia matrix", "paper IV-A: 'applied to the entire inertia matrix'"),
)


def anchor_cell(velocity_weight: float, input_weight: float, seeds=SEEDS) -> dict:
    """Traditional MPC on the paper's pendulum at error 1 with Q = diag(10, ``velocity_weight``) and R =
    ``input_weight``: median percent overshoot and rise time [s] over ``seeds`` (steps of at least 0.1 rad)."""
    from ocpkit import solvers
    from ocpkit.sim.simulate import simulate

    pb = Pendulum()
    ocp = pb.ocp(error=1.0, Q=np.diag([10.0, velocity_weight]), R=np.array([[input_weight]]))
    ctrl = solvers.make("qp", ocp)
    overshoot, rise = [], []
    for seed in seeds:
        x0, goal = pb.sample(seed)
        steps = step_metrics(simulate(pb.plant(), ctrl, x0, goal, pb.duration))
        overshoot.append(steps["overshoot"][0])
        rise.append(steps["rise_time"][0])
    return {"overshoot": float(np.nanmedian(overshoot)), "rise_time": float(np.nanmedian(rise))}


def calibrate(seeds=SEEDS, velocity_weights=VELOCITY_WEIGHTS, input_weights=INPUT_WEIGHTS) -> dict:
    """Q's velocity weight and R that bring :func:`anchor_cell` to the paper's anchor (4.17 %, 0.38 s). Overshoot
    grows with R, so for each velocity weight R is solved for the anchor's overshoot (Brent's method in log R
    within ``input_weights``); of these, the velocity weight whose rise time is nearest the anchor's is kept (rise
    time moves in steps of dt, so it is matched by choice, not solved). Returns the values and what they achieve,
    in the form of :data:`ocpkit.problems.pendulum.PAPER_COST`."""
    from scipy.optimize import brentq

    target = ANCHOR_VALUES["overshoot"]
    fits = []
    for qd in velocity_weights:

        def miss(log_r, qd=qd):
            return anchor_cell(qd, float(np.exp(log_r)), seeds)["overshoot"] - target

        lo, hi = np.log(input_weights)
        if miss(lo) * miss(hi) > 0:  # this velocity weight cannot reach the anchor's overshoot within the bracket
            continue
        r = float(number(np.exp(brentq(miss, lo, hi, xtol=1e-3)), 3))
        fits.append((qd, r, anchor_cell(qd, r, seeds)))
    if not fits:
        raise ValueError(f"no velocity weight in {list(velocity_weights)} reaches {target} % overshoot")
    qd, r, cell = min(fits, key=lambda f: abs(f[2]["rise_time"] - ANCHOR_VALUES["rise_time"]))
    return {"velocity_weight": float(qd), "input_weight": r, "achieved": cell, "seeds": len(seeds)}


def precision(value, table: dict | None = None) -> float:
    """Half a unit of the last digit the paper prints (4.17 → 0.005, 22 → 0.5, 0.0171 → 0.00005; a string is read as
    printed, trailing zeros kept: ".90" → 0.005). A printed 0 in
    ``table`` (the paper's, rows of values) reads as "none": the finest precision the table prints elsewhere
    (Table I's 0 beside 0.0171 is not ±0.5)."""
    if value == 0 and table is not None:
        return min(precision(v) for row in table.values() for v in row if v != 0)
    text = value if isinstance(value, str) else repr(value)  # a string: as printed (".90" → 0.005)
    return 0.5 * 10.0 ** -(len(text.split(".")[1]) if "." in text else 0)


def fidelity(table, metric: str) -> pd.DataFrame:
    """Every cell of ``table`` (rows: error multiplier, columns: controller; ours) that the paper's table has, beside
    the paper's number: the difference and whether it lies within the paper's printed precision. The anchor cell is
    marked: it was fitted, not predicted."""
    rows = []
    for error in table.index:
        printed = PAPER_TABLES[metric].get(round(float(error), 1))
        for j, controller in enumerate(PAPER_COLUMNS):
            if printed is None or controller not in table:
                continue
            ours, paper = float(table.loc[error, controller]), printed[j]
            anchor = round(float(error), 1) == ANCHOR["error_multiplier"] and controller == ANCHOR["controller"]
            verdict = _within(ours, paper, precision(paper, PAPER_TABLES[metric]))
            rows.append(
                {
                    "error multiplier": error,
                    "controller": controller,
                    "ours": ours,
                    "paper": paper,
                    "ours − paper": ours - paper,
                    "verdict": ("anchor (fitted): " if anchor else "") + verdict,
                }
            )
    return pd.DataFrame(rows).set_index("error multiplier") if rows else pd.DataFrame()


def _within(ours: float, paper: float, band: float) -> str:
    """The fidelity verdict: within the paper's printed precision ``band`` (round-off aside: 0.275 vs 0.28 is within)
    or not."""
    return "within the paper's precision" if abs(ours - paper) <= band * (1 + 1e-9) else f"not within ±{number(band)}"


def stated(values) -> pd.DataFrame:
    """Numbers the paper states beside ours: ``values`` rows (what, the paper's sentence or table, the paper's number
    as printed, ours), each with the difference and its fidelity verdict (within the paper's printed precision or
    not: :func:`precision`); the paper's column as printed. A range (low, high), e.g. "between three and four", is
    its midpoint ± half its width (the difference: from the midpoint)."""
    rows = []
    for what, source, printed, ours in values:
        if isinstance(printed, tuple):
            paper, band = (printed[0] + printed[1]) / 2, (printed[1] - printed[0]) / 2
            printed = f"{printed[0]}–{printed[1]}"
        else:
            paper, band = float(printed), precision(printed)
        rows.append(
            {
                "value": what,
                "paper says": source,
                "paper": printed,
                "ours": ours,
                "ours − paper": ours - paper,
                "verdict": _within(ours, paper, band) if ours == ours else "not measured here",
            }
        )
    return pd.DataFrame(rows).set_index("value")


def within_count(cells: pd.DataFrame) -> tuple[int, int]:
    """How many predicted cells (the anchor excluded) land within the paper's precision, of how many."""
    if cells.empty:
        return 0, 0
    predicted = cells[~cells["verdict"].str.startswith("anchor")]
    return int(predicted["verdict"].str.startswith("within").sum()), len(predicted)


def puma_setup(problems) -> dict:
    """{caption: the Puma's set-up table} for a report whose ``problems`` include the paper's Puma, else {}."""
    if "puma560:paper" not in set(problems):
        return {}
    return {
        "The Puma's set-up: each setting, from the paper (quoted) or ours (why)": markdown_table(
            setup_table(PUMA_SETUP)
        )
    }


def tried_table() -> pd.DataFrame:
    """:data:`TRIED` as a table: each setting tried for the cells far from the anchor, beside the paper's numbers."""
    rows = [
        {
            "setting tried": setting,
            "the paper's text": text or "–",
            "anchor (4.17 %, 0.38 s)": f"{number(anchor[0], 3)} %, {number(anchor[1], 3)} s",
            "traditional, error 0.5: overshoot % (paper 43.5)": "–" if overshoot is None else overshoot,
            "traditional, error 1.5: rise time s (paper 0.84)": "–" if rise is None else rise,
            "adopted": adopted,
        }
        for setting, text, anchor, overshoot, rise, adopted in TRIED
    ]
    return pd.DataFrame(rows).set_index("setting tried")


def setup_table(rows=None) -> pd.DataFrame:
    """``rows`` (setting, value, source) as a table; by default the robustness study's: the pendulum's settings, the
    calibrated cost with its provenance, and the Puma's (:data:`PUMA_SETUP`)."""
    if rows is not None:
        return pd.DataFrame(rows, columns=["setting", "value", "source"]).set_index("setting")
    rows = list(SETUP) + [
        (
            "calibrated Q velocity weight, R",
            f"{number(PAPER_COST['velocity_weight'])}, {number(PAPER_COST['input_weight'])}",
            f"ours: {PAPER_COST['provenance']}",
        )
    ]
    return setup_table(rows + list(PUMA_SETUP))


if __name__ == "__main__":
    print(calibrate())
