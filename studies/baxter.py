"""Baxter arm step commands: bare servo vs parameterized QP MPC vs EMPC (paper Section VI-C/D, Table III).

The simulated 7-DoF arm behind its underdamped 500 Hz PD servo (``problems.make("baxter")``) receives
three step commands that move all seven joints at once, each from rest to rest:

    neutral → A → B → neutral,   neutral = (0, −0.55, 0, 0.75, 0, 1.26, 0) rad (s0 … w2),
    A = neutral + (0.5, 0.3, −0.5, 0.5, 0.5, −0.5, 0.5),
    B = neutral + (−0.5, −0.3, 0.5, −0.4, −0.5, 0.4, −0.5)

(Baxter's neutral pose; every pose is inside the joint limits; steps of 0.3–1.0 rad). Controllers at
100 Hz, horizon 100: the bare servo with its set point at the goal (the paper's "Step Input"), the
condensed QP with 3 knot points on OSQP, and EMPC with 3 knot points. ITAE is taken per joint and
command (21 values per controller and seed); Table III reports their mean and median.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from ocpkit import problems, solvers
from ocpkit.sim import plots
from ocpkit._checks import choice
from ocpkit.controller import Controller
from ocpkit.status import SUCCESS, Solution
from ocpkit.codegen.kernels.runtime import current_arch
from ocpkit.sim.metrics import itae
from ocpkit.problems.baxter import JOINTS
from ocpkit.sim.simulate import Trajectory, simulate
from ocpkit.runs.study import Study, grid
from ocpkit.studies.closed_loop import run_record, steady
from ocpkit.studies.calibration import stated, within_count
from ocpkit.studies.comparison import responses, row_arrays
from ocpkit.sim.plots import number
from ocpkit.studies.evidence import NOT_TESTED, median_claim, on_gpu, paired, quartiles, series, timing
from ocpkit.studies.report import ANSWERED, Claim, answered, markdown_table, section, timing_context, trials_line

NAME = "baxter"
TITLE = "Baxter arm step commands: servo vs parameterized QP MPC vs EMPC (Table III)"
NEUTRAL = np.array([0.0, -0.55, 0.0, 0.75, 0.0, 1.26, 0.0])
POSES = (NEUTRAL, NEUTRAL + [0.5, 0.3, -0.5, 0.5, 0.5, -0.5, 0.5], NEUTRAL + [-0.5, -0.3, 0.5, -0.4, -0.5, 0.4, -0.5])
COMMANDS = tuple(zip(POSES, POSES[1:] + POSES[:1]))  # (start, goal) joint angles of each step command
SHORT = tuple(j.removeprefix("right_") for j in JOINTS)
SERVO, QP, EMPC, EMPC_PAPER = "servo (step input)", "knots 3 (QP)", "EMPC", "EMPC (paper)"
# Every MPC linearizes about the plan's input ("plan"). "EMPC" is the default, preconditioned planner; "EMPC
# (paper)" is Algorithm 1 as the paper prints it (as on the paper's hardware) with set-point noise σ = 0.1 rad.
# Measured over these commands (4 s, population 512, CPU), the paper variant's mean ITAE was 10.0 linearized about
# the goal set point with the default σ (10 % of each joint's range: 0.27–0.61 rad), 1.16 about the plan, 0.66
# about the plan with σ = 0.1 rad; the bare servo's was 1.0.
CONTROLLERS = {
    QP: ("qp", {"form": "condensed", "qp": "osqp", "linearization": "plan"}),
    EMPC: ("empc", {"generations": 1, "linearization": "plan"}),
    EMPC_PAPER: ("empc", {"generations": 1, "sigma": 0.1, "linearization": "plan", "variant": "paper"}),
}
KNOTS = 3
# Table III (hardware, Section VI-D) as printed: mean and median ITAE over 21 values (7 joints × 3 commands); the
# paper's EMPC row stands beside both of ours. The text's median reductions are its table's: 0.90 / 1.30 − 1 = −31 %.
PAPER_ITAE = {SERVO: ("1.61", "1.30"), QP: ("1.29", ".90"), EMPC: ("1.17", ".75"), EMPC_PAPER: ("1.17", ".75")}
PAPER_NAMES = {SERVO: "Step Input", QP: "Parameterized OSQPMPC", EMPC: "EMPC", EMPC_PAPER: "EMPC"}
REDUCED = {QP: "31", EMPC: "42", EMPC_PAPER: "42"}
REDUCED_QUOTE = "VI-D: 'Parameterized OSQPMPC and EMPC reduce the median ITAE by 31% and 42% respectively'"
SIZES = {
    "quick": {"seeds": 1, "duration": 4.0, "population": 512, "arch": "cpu"},
    "full": {"seeds": 5, "duration": 4.0, "population": 1024, "arch": "auto"},
}


class ServoSetPoint(Controller):
    """No MPC: the servo's set point is the goal itself (Table III's "Step Input")."""

    def _solve(self, x, goal):
        u = self.ocp.input_goal(goal)
        return Solution(u=u, knots=np.tile(u, (self.ocp.knots, 1)), status=SUCCESS)


def trial(command: int, controller: str, duration: float, population: int, arch: str, seed: int) -> dict:
    """One step command (index into :data:`COMMANDS`) under ``controller``: ITAE per joint, solve times, the run.

    ``population`` and ``arch`` configure EMPC only; ``seed`` seeds EMPC's random stream.
    """
    choice(command, tuple(range(len(COMMANDS))), "command")
    choice(controller, (SERVO, *CONTROLLERS), "controller")
    pb = problems.make("baxter")
    ocp = pb.ocp(knots=KNOTS)
    if controller == SERVO:
        ctrl = ServoSetPoint(ocp)
    else:
        solver, options = CONTROLLERS[controller]
        if solver == "empc":
            options = {**options, "population": population, "arch": arch, "seed": seed}
        ctrl = solvers.make(solver, ocp, **options)
    start, goal = (np.r_[q, np.zeros(len(q))] for q in COMMANDS[command])
    steady(ctrl, start, goal)
    traj = simulate(pb.plant(), ctrl, start, goal, duration)
    solve, total = traj.times("solve"), traj.times("total")
    return {
        **{f"itae_{j}": itae(traj, [i]) for i, j in enumerate(SHORT)},
        **quartiles("solve", solve),
        **quartiles("total", total),
        **run_record(traj, ctrl),
        "final_error": float(np.abs(traj.x[-1, : ocp.nu] - goal[: ocp.nu]).max()),
        "device": current_arch() if controller in (EMPC, EMPC_PAPER) else "cpu",
        "t": traj.t,
        "x": traj.x,
        "u": traj.u,
        "goal": goal,
        "solve_times": solve,
        "total_times": total,
    }


def study(size: str) -> Study:
    choice(size, tuple(SIZES), "size")
    s = SIZES[size]
    return Study(
        NAME,
        trial,
        grid(
            command=list(range(len(COMMANDS))),
            controller=[SERVO, *CONTROLLERS],
            duration=s["duration"],
            population=s["population"],
            arch=s["arch"],
            seeds=s["seeds"],
        ),
    )


def per_seed_rows(df):
    """Each seed's ITAE per controller, command and joint, and its ratio to the servo's (the verdicts' unit), for
    the report's appendix."""
    ok = df[df["status"] == "ok"]
    itae = ok.set_index(["controller", "command", "seed"])[[f"itae_{j}" for j in SHORT]]
    itae.columns = pd.Index(SHORT, name="joint")
    itae = itae.stack().reorder_levels(["controller", "command", "joint", "seed"]).sort_index()
    servo = itae.xs(SERVO, level="controller").reindex(itae.index.droplevel("controller")).to_numpy()
    return pd.DataFrame({"ITAE": itae, "ITAE / the servo's": itae.to_numpy() / servo}, index=itae.index)


def report(df, out_dir) -> str:
    ok = df[df["status"] == "ok"]
    trials = trials_line(
        df,
        {"commands": df["command"].nunique(), "controllers": df["controller"].nunique(), "seeds": df["seed"].nunique()},
    )
    if ok.empty:
        return section(TITLE, [], {}, trials=trials, claims=[], notes=["No trial succeeded."])
    order = [c for c in (SERVO, *CONTROLLERS) if c in set(ok["controller"])]
    columns = [f"itae_{j}" for j in SHORT]
    values = {c: ok.loc[ok["controller"] == c, columns].to_numpy().ravel() for c in order}
    table = _table(values)
    figs = []
    first = ok[ok["seed"] == ok["seed"].min()]
    for command in sorted(first["command"].unique()):
        trajs = {}
        for row in first.index[first["command"] == command]:
            a = row_arrays(df, row, out_dir)
            trajs[df.at[row, "controller"]] = Trajectory(t=a["t"], x=a["x"], u=a["u"], goal=a["goal"])
        figs.append(
            responses(
                {c: trajs[c] for c in order if c in trajs},
                out_dir / f"baxter_command{command}",
                title=f"Baxter step command {command}: joint angles (dotted: goals)",
                joint_names=SHORT,
            )
        )
    solve = ok[ok["controller"] != SERVO].groupby("controller")[["solve_median", "total_median"]].median() * 1e3
    times = {
        c: np.concatenate([row_arrays(df, r, out_dir)["total_times"] for r in ok.index[ok["controller"] == c]])
        for c in order
        if c != SERVO
    }
    if times:
        figs.append(_histogram(times, solve["total_median"], out_dir / "baxter_solve_times"))
    solve.columns = ["optimization solve time", "MPC solve time"]
    caption = f"ITAE over {len(COMMANDS)} commands × {len(SHORT)} joints × {ok['seed'].nunique()} seed(s) (Table III)"
    paper = paper_values(values)
    tables = {
        caption: table,
        "Table III and the text's reductions beside ours (hardware against this simulation: a prediction, not a "
        "fit)": markdown_table(paper),
        "Median over runs of the per-step median solve times [ms]": markdown_table(solve),
        ANSWERED: answered(ok),
    }
    n_in, n = within_count(paper)
    notes = [
        f"Table III: {n_in} of {n} of the paper's numbers lie within its printed precision (half a unit of its last "
        "digit; ours: the paper prints no uncertainty). The paper's are hardware (a real Baxter, its own gains and "
        "weights, run length not stated); ours a simulated arm over 4 s, so ITAE's scale need not match.",
        f"Fallback steps (solver failures): {int(ok['fallbacks'].sum())} in {len(ok)} runs; EMPC ran on "
        + ", ".join(sorted(set(ok.loc[ok["controller"].isin([EMPC, EMPC_PAPER]), "device"])))
        + ".",
    ]
    return section(
        TITLE, figs, tables, trials=trials + " " + timing_context(ok), notes=notes, claims=claims(ok, values)
    )


def paper_values(values: dict):
    """Every Table III cell and the text's median reductions (Section VI-D) beside ours: difference and fidelity
    verdict (:func:`ocpkit.studies.calibration.stated`)."""
    rows = []
    for c, v in values.items():
        mean, median = PAPER_ITAE[c]
        table = f"Table III, {PAPER_NAMES[c]}"
        rows += [
            (f"{c}: mean ITAE", table, mean, float(v.mean())),
            (f"{c}: median ITAE", table, median, float(np.median(v))),
        ]
        if c in REDUCED and SERVO in values:
            cut = 100 * (1 - np.median(v) / np.median(values[SERVO]))
            rows.append((f"{c}: median ITAE reduction vs the servo [%]", REDUCED_QUOTE, REDUCED[c], float(cut)))
    return stated(rows)


def _table(values: dict) -> str:
    servo = np.median(values[SERVO]) if SERVO in values else np.nan
    rows = {
        c: {
            "mean ITAE": v.mean(),
            "median ITAE": np.median(v),
            "median change vs servo [%]": 100 * (np.median(v) / servo - 1),
        }
        for c, v in values.items()
    }
    df = pd.DataFrame.from_dict(rows, orient="index")
    df.index.name = "controller"
    return markdown_table(df)


def _histogram(times: dict, medians, path):
    """Histograms of the per-step MPC solve times (as in the paper's hardware results), log-spaced bins in ms;
    the legend gives the same median as the table (median over runs of each run's median)."""
    fig, ax = plots.figure(figsize=(7.5, 4.2))
    ms = {c: 1e3 * t for c, t in times.items()}
    lo, hi = min(t.min() for t in ms.values()), max(t.max() for t in ms.values())
    bins = np.geomspace(max(lo, 1e-3), hi, 40)
    for label, t in ms.items():  # outlines, not translucent bars: overlaps would show colours no legend entry has
        look = plots.style(label)
        ax.hist(
            t,
            bins=bins,
            histtype="step",
            lw=1.5,
            color=look["color"],
            ls=look["linestyle"],
            label=f"{label} (median {number(medians[label], 3)} ms)",
        )
    ax.set_xscale("log")
    plots.log_axis(ax, "x")
    ax.set_xlabel("MPC solve time per step [ms]")
    ax.set_ylabel("steps [count per bin]")
    plots.count_axis(ax, axis="y")
    plots.legend_outside(ax)
    ax.set_title("Baxter: MPC solve times", fontsize=10)
    return plots.save(fig, path)


def claims(ok, values) -> list:
    """The paper's Table III claims (hardware) against this simulation, decided on the ITAE of each command and
    joint paired with the bare servo's (same command, joint and seed)."""
    out = []

    def itae(c):
        """ITAE per (command, seed, joint)."""
        return ok[ok["controller"] == c].set_index(["command", "seed"])[[f"itae_{j}" for j in SHORT]].stack()

    for c, paper in ((QP, 31), (EMPC, 42), (EMPC_PAPER, 42)):
        if c in values and SERVO in values:
            change = 100 * (np.median(values[c]) / np.median(values[SERVO]) - 1)
            v, e = median_claim(paired(itae(c), itae(SERVO)), 1.0, "<")
            out.append(
                Claim(
                    f"{c} reduces the median ITAE vs the bare servo",
                    f"per command and joint, ITAE / the "
                    f"servo's < 1 (medians: {number(change, 3)} %; simulation, exact model)",
                    v,
                    e,
                    paper=f"hardware: by {paper} %",
                )
            )
    if {QP, EMPC} <= set(ok["controller"]):
        empc = ok[ok["controller"] == EMPC]
        med = ok.groupby("controller")["total_median"].median()
        devices = ", ".join(sorted(set(empc["device"])))
        ours = (
            f"median MPC solve time {number(1e3 * med[EMPC], 3)} ms for EMPC ({devices}) "
            f"vs {number(1e3 * med[QP], 3)} ms for the QP"
        )
        if not on_gpu(empc["device"]):
            out.append(Claim("EMPC solves faster than the QP (GPU)", ours, NOT_TESTED, "needs a GPU"))
        else:
            runs = [series(ok, "total_median", ["command", "seed"], controller=c) for c in (EMPC, QP)]
            v, e = median_claim(paired(*runs), 1.0, "<")
            out.append(Claim("EMPC solves faster than the QP (GPU)", ours, timing(v, ok["load"]), e))
    return out
