"""Crocoddyl's FDDP against ocpkit's IPOPT and RTI, solve by solve, on the very same OCPs (the peer:
:mod:`ocpkit.benchmarks.crocoddyl_peer`): the per-solve table ``ocpkit bench nlp`` prints after its closed-loop one."""

from __future__ import annotations

import time

import numpy as np

from ocpkit._checks import integer
from ocpkit.benchmarks.crocoddyl_peer import CrocoddylMPC, objective, require, rollout, undamped
from ocpkit.model.ocp import OCP

PROBLEMS = ("puma560", "panda", "nlink:7")


def compare(
    problems=PROBLEMS,
    horizon: int | None = 50,
    knots: int | None = 5,
    seeds: int = 3,
    steps: int = 10,
    repeats: int = 10,
    echo: bool = True,
) -> list[dict]:
    """Per-solve figures of FDDP against ocpkit on the same OCPs (p = T, the problems
    :func:`~ocpkit.benchmarks.crocoddyl_peer.undamped`).

    For each problem and seeded start/goal every solver runs ``steps`` MPC steps on ocpkit's own discrete model
    (no plant mismatch: the warm starts are what a converged MPC sees): the first step is cold (states held at
    x_0, inputs at the input goal), the others warm (the previous solution shifted; FDDP's states are the shifted
    inputs' rollout, see :class:`~ocpkit.benchmarks.crocoddyl_peer.CrocoddylMPC`). Rows, with the median and the
    worst over the ``seeds``: "fddp rk4" (the equal comparison), "fddp euler" (Crocoddyl's default, semi-implicit
    Euler, on the OCP with ``integrator="euler"``: its plan's inputs scored on RK4), "ipopt" (NonlinearMPC's IPOPT
    on the p = T OCP, the reference optimum), "rti" (one Gauss–Newton step a control step) and ocpkit's IPOPT and
    RTI on ``knots`` knots (none for ``knots`` None). Columns: the time of one iteration (FDDP: a solve with
    maxiter 1 from the cold guess, median of ``repeats``, as Crocoddyl's benchmarks time it; IPOPT: its cold solve
    over its iterations), cold and warm step time (``Solution.times["total"]``, ms) and iterations (RTI's step is
    one Gauss–Newton iteration), and ocpkit's cost of the cold plan's inputs rolled out on its model over that of
    IPOPT's p = T optimum (not for RTI's single iteration). Each FDDP problem is built for its goal before the
    timed steps.
    """
    from ocpkit.solvers.nlp import NonlinearMPC
    from ocpkit.solvers.rti import RealTimeIteration

    require()
    seeds, steps, repeats = integer(seeds, "seeds", 1), integer(steps, "steps", 2), integer(repeats, "repeats", 1)
    if isinstance(problems, str):
        raise TypeError(f"problems must be a list of problem specs, got the string {problems!r}")
    # name -> (controller of (problem, its OCP), its OCP: "T" (p = T, RK4), "euler" (p = T) or "knots")
    solvers = {
        "fddp rk4": (CrocoddylMPC, "T"),
        "fddp euler": (CrocoddylMPC, "euler"),
        "ipopt": (lambda prob, ocp: NonlinearMPC(ocp), "T"),
        "rti": (lambda prob, ocp: RealTimeIteration(ocp), "T"),
    }
    if knots is not None:
        solvers[f"ipopt p={knots}"] = (lambda prob, ocp: NonlinearMPC(ocp), "knots")
        solvers[f"rti p={knots}"] = (lambda prob, ocp: RealTimeIteration(ocp), "knots")
    rows = []
    for spec in problems:
        prob = undamped(spec)
        ocps = {
            "T": prob.ocp(knots=None, horizon=horizon),
            "euler": prob.ocp(knots=None, horizon=horizon, integrator="euler"),
        }
        if knots is not None:
            ocps["knots"] = prob.ocp(knots=knots, horizon=horizon)
        ocp = ocps["T"]
        runs = {name: [] for name in solvers}
        calc = []
        for seed in range(seeds):
            x0, goal = prob.sample(seed)
            for name, (make, which) in solvers.items():
                ctrl = make(prob, ocps[which])
                runs[name].append(_run(ctrl, ocp, x0, goal, steps, repeats))
                if name == "fddp rk4":
                    calc.append(_calc_times(ctrl, x0, goal, repeats))
        reference = [run["cost"] for run in runs["ipopt"]]
        for name, seen in runs.items():
            ratio = [run["cost"] / ref for run, ref in zip(seen, reference)]
            row = {
                "problem": spec,
                "solver": name,
                "knots": knots if solvers[name][1] == "knots" else "T",
                "horizon": ocp.horizon,
                "seeds": seeds,
                "cost_ratio": ratio,
            }
            for key in ("iteration_ms", "cold_ms", "cold_iterations", "warm_ms", "warm_iterations", "failures"):
                row[key] = [run[key] for run in seen]
            rows.append(row)
        if echo:
            _print(spec, ocp, rows[-len(solvers) :], np.median(calc, axis=0), knots)
    return rows


def _run(ctrl, ocp: OCP, x0, goal, steps: int, repeats: int) -> dict:
    """``steps`` MPC steps of ``ctrl`` on ocpkit's discrete model from x0: cold/warm times, iterations, cost."""
    from ocpkit.solvers.rti import RealTimeIteration

    croc = isinstance(ctrl, CrocoddylMPC)
    # One untimed solve first: a new controller's first step pays one-offs that are no solver's work (the thread
    # limiter's scan of the loaded libraries, first calls; FDDP's problem built for this goal; RTI's QP set-up).
    ctrl.solve(x0, goal)
    ctrl.reset()
    F, x, sols = ocp.discrete(), np.asarray(x0, dtype=float), []
    for _ in range(steps):
        sols.append(ctrl.solve(x, goal))
        x = np.asarray(F(x, sols[-1].u), dtype=float).ravel()
    cold, warm = sols[0], sols[1:]
    inputs = ctrl.ocp.parameterization.inputs(cold.knots)
    rti = isinstance(ctrl, RealTimeIteration)
    out = {
        "cold_ms": 1e3 * cold.times["total"],
        "warm_ms": 1e3 * float(np.median([s.times["total"] for s in warm])),
        "cold_iterations": np.nan if rti else cold.iterations,
        "warm_iterations": np.nan if rti else float(np.median([s.iterations for s in warm])),
        "failures": sum(not s.ok for s in sols),
        "cost": objective(ocp, goal, rollout(ocp, x0, inputs), inputs) if cold.ok and not rti else np.nan,
        "iteration_ms": np.nan if rti else 1e3 * cold.times["solve"] / max(cold.iterations, 1),
    }
    if croc:
        out["iteration_ms"] = 1e3 * float(np.median([ctrl.one_iteration(x0, goal) for _ in range(repeats)]))
    return out


def _calc_times(ctrl: CrocoddylMPC, x0, goal, repeats: int) -> tuple[float, float]:
    """Median ms of ``ShootingProblem.calc`` and ``calcDiff`` at the cold guess (node lists from Python)."""
    xs, us, _ = ctrl.prepare(x0, goal)
    problem, out = ctrl.shooting.problem, []
    for call in (problem.calc, problem.calcDiff):
        seen = []
        for _ in range(repeats):
            start = time.perf_counter()
            call(xs, us)
            seen.append(time.perf_counter() - start)
        out.append(1e3 * float(np.median(seen)))
    return tuple(out)


def _cell(values, fmt: str, worst=max) -> str:
    values = [v for v in values if np.isfinite(v)]
    if not values:
        return "-"
    return f"{format(float(np.median(values)), fmt)} [{format(float(worst(values)), fmt)}]"


def _print(spec: str, ocp: OCP, rows: list[dict], calc, knots: int) -> None:
    seeds = rows[0]["seeds"]
    print(
        f"\n{spec}: p = T = {ocp.horizon}, dt = {ocp.dt}, without damping; median [worst] over {seeds} "
        f"seed{'s' if seeds > 1 else ''}; "
        f"Crocoddyl problem.calc {calc[0]:.2f} ms, calcDiff {calc[1]:.2f} ms (nthreads 1)",
        flush=True,
    )
    print(
        f"{'solver':<12}{'knots':>6}{'iter ms':>16}{'cold ms':>18}{'cold it':>12}{'warm ms':>18}{'warm it':>12}"
        f"{'cost/ipopt':>24}{'fail':>5}"
    )
    worst_ratio = lambda v: max(v, key=lambda r: abs(r - 1.0))  # noqa: E731  the ratio farthest from 1
    for row in rows:
        print(
            f"{row['solver']:<12}{row['knots']!s:>6}{_cell(row['iteration_ms'], '.2f'):>16}"
            f"{_cell(row['cold_ms'], '.1f'):>18}{_cell(row['cold_iterations'], '.0f'):>12}"
            f"{_cell(row['warm_ms'], '.1f'):>18}{_cell(row['warm_iterations'], '.0f'):>12}"
            f"{_cell(row['cost_ratio'], '.8f', worst_ratio):>24}{sum(row['failures']):>5d}"
        )
    by = {row["solver"]: row for row in rows}
    fddp, ipopt, rti = by["fddp rk4"], by["ipopt"], by["rti"]

    def ratio(a, b, key):
        return float(np.median(np.divide(a[key], b[key])))

    knot_rti = (
        ""
        if knots is None
        else (f"; FDDP warm / ocpkit's {knots}-knot RTI step {ratio(fddp, by[f'rti p={knots}'], 'warm_ms'):.2f}")
    )
    print(
        f"ratios (median over seeds): FDDP / IPOPT at p = T: cold {ratio(fddp, ipopt, 'cold_ms'):.3f}, warm "
        f"{ratio(fddp, ipopt, 'warm_ms'):.3f}; FDDP warm / RTI step {ratio(fddp, rti, 'warm_ms'):.2f}{knot_rti}; "
        f"FDDP cost / IPOPT cost − 1: {float(np.median(fddp['cost_ratio'])) - 1.0:.2e}",
        flush=True,
    )
