"""The trial behind the closed-loop studies: one controller, one seeded start and goal, one run.

``problem`` is any problem spec (``ocpkit.problems.make``): a registered name, ``package.module:Name`` or
``path/to/file.py:Name``; worker processes resolve it themselves (a relative path from the study's folder).
"""

from __future__ import annotations

import os

import numpy as np

from ocpkit import problems, solvers
from ocpkit.sim.metrics import actual_cost, itae, step_metrics
from ocpkit.sim.simulate import simulate


def trial(
    problem: str,
    seed: int,
    solver: str = "qp",
    knots: int | None = None,
    horizon: int | None = None,
    error_multiplier: float = 1.0,
    form: str = "condensed",
    qp: str | None = None,
    duration: float | None = None,
    options: dict | None = None,
) -> dict:
    """Run MPC on ``problem`` from the seeded start to goal and measure it (paper Sections III–IV, VII).

    The controller's model carries the error multiplier; the plant is the true model. ``options`` go to
    the solver (e.g. ``{"generations": 3}`` for EMPC).
    """
    pb = problems.make(problem)
    ocp = pb.ocp(knots=knots, horizon=horizon, error=error_multiplier)
    opts = {"form": form, "qp": qp} if solver == "qp" else {}
    ctrl = solvers.make(solver, ocp, **opts, **(options or {}))
    if solver == "qp":  # time the steady state: LinearMPC's C step (or compiled model) once built
        ctrl.wait_compiled()
    x0, goal = pb.sample(seed)
    traj = simulate(pb.plant(), ctrl, x0, goal, duration or pb.duration)
    steps = step_metrics(traj)
    solve, total = traj.times("solve"), traj.times("total")
    return {
        "actual_cost": actual_cost(traj, ocp),
        "itae": itae(traj),
        "overshoot": _mean(steps["overshoot"]),
        "rise_time": _mean(steps["rise_time"]),
        "final_error": float(np.abs(traj.x[-1] - goal).max()),
        **run_record(traj, ctrl),
        "solve_median": float(np.median(solve)),
        "total_median": float(np.median(total)),
        "total_p90": float(np.percentile(total, 90)),
    }


def steady(ctrl, x0, goal) -> None:
    """Bring ``ctrl`` to the state a running loop is in before a timed run: one step (it compiles kernels and
    functions; simulate() resets the controller) and its background builds waited for (the compiled model, LinearMPC's
    C step), so that no timed step runs on a path the loop leaves after its first seconds."""
    ctrl.solve(x0, goal)
    ctrl.wait_compiled()


def run_record(traj, ctrl) -> dict:
    """What every closed-loop trial stores about how its steps were answered: what answered them (the controller's
    path: the C or the Python step, a fallback), the fallback steps and their causes (statuses), EMPC's child win rate
    (NaN for other controllers: see ``EvolutionaryMPC.child_win_rate``) and the 1-min load average at the end of the
    run (timing verdicts are withheld when it exceeds the CPUs)."""
    return {
        "paths": traj.paths(),
        "fallbacks": traj.fallbacks,
        "fallback_causes": traj.fallback_causes(),
        "child_win_rate": float(getattr(ctrl, "child_win_rate", float("nan"))),
        "load": os.getloadavg()[0],
    }


def _mean(values) -> float:
    """Mean over the joints that have a value (NaN when none has)."""
    values = values[~np.isnan(values)]
    return float(values.mean()) if values.size else float("nan")


def grid_size(sizes: dict, size: str, specs, user_quick: dict) -> dict:
    """A study's grid ``sizes[size]``, with ``problems`` (a spec or a list of specs) replacing the paper's
    problems and, at the quick size, ``user_quick`` replacing its axes (a user's problem gets a test-sized grid)."""
    if size not in sizes:
        raise ValueError(f"size must be one of {', '.join(sizes)}, got {size!r}")
    s = dict(sizes[size])
    if specs is not None:
        specs = [specs] if isinstance(specs, str) else list(specs)
        if not specs:
            raise ValueError("problems must name at least one problem spec")
        for spec in specs:
            problems.make(spec)  # fail now, naming the bad spec, rather than in every trial
        s.update(user_quick if size == "quick" else {})
        s["problems"] = list(dict.fromkeys(specs))
    return s
