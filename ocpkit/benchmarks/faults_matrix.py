"""The adversarial matrix of `ocpkit bench faults`: bad data and hard limits against every solver.

Each case must end in a clear ValueError/TypeError at construction, or in a non-success status with a
finite input inside the bounds, within its time budget plus a small overhead — never "success" with a
NaN or a wrong answer. Recovery: after a runtime failure the same controller must solve a good problem
exactly as a fresh controller does.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ocpkit import problems, solvers
from ocpkit.status import SUCCESS
from ocpkit.problems.pendulum import Pendulum

BUDGET = 0.05  # s: the time budget of the budget case, and the slack allowed on top of it
SOLVE_CAP = 20.0  # s: no single case may take longer than this, whatever the solver


@dataclass
class Outcome:
    case: str
    solver: str
    result: str  # "error: …" (rejected at construction/call) or a status
    seconds: float
    finite: bool = True
    within_bounds: bool = True
    recovered: bool | None = None  # None: not a runtime failure, nothing to recover from

    @property
    def acceptable(self) -> bool:
        if self.result.startswith("error"):
            return True
        return (
            self.result != SUCCESS
            and self.finite
            and self.within_bounds
            and self.recovered is not False
            and self.seconds < SOLVE_CAP
        )


# label -> (registry name, constructor options, the option names for the limits it supports)
SOLVERS = {
    "qp sparse proxqp": ("qp", {"form": "sparse", "qp": "proxqp"}),
    "qp sparse osqp": ("qp", {"form": "sparse", "qp": "osqp"}),
    "qp condensed proxqp": ("qp", {"form": "condensed", "qp": "proxqp"}),
    "qp condensed osqp": ("qp", {"form": "condensed", "qp": "osqp"}),
    "qp condensed daqp": ("qp", {"form": "condensed", "qp": "daqp"}),
    "ipopt": ("ipopt", {}),
    "empc": ("empc", {"population": 64, "arch": "cpu"}),
    "cem": ("cem", {"population": 64, "arch": "cpu"}),
    "mppi": ("mppi", {"population": 64, "arch": "cpu"}),
}
ITERATIVE = {"qp", "ipopt"}  # solvers with an iteration limit
SAMPLING = {"empc", "cem", "mppi"}  # state bounds as a penalty in the fitness: no hard bounds


def _controller(label, ocp, **extra):
    name, options = SOLVERS[label]
    return solvers.make(name, ocp, **options, **extra)


PENDULUM = problems.make("pendulum")
X0, GOAL = PENDULUM.sample(0)
# States bounded to |q̇| ≤ 1: a start at q̇ = 3 cannot be brought inside in one step (infeasible).
BOUNDED = {"x_min": [-np.inf, -1.0], "x_max": [np.inf, 1.0]}
BAD_START = np.array([0.0, 3.0])


def _construction_cases():
    """Cases rejected before any solve: (name, callable building and solving)."""
    ocp = lambda **kw: PENDULUM.ocp(knots=3, **kw)  # noqa: E731
    nan_q = np.diag([np.nan, 1.0])
    return {
        "NaN in x0": lambda lbl: _controller(lbl, ocp()).solve([np.nan, 0.0], GOAL),
        "inf in goal": lambda lbl: _controller(lbl, ocp()).solve(X0, [np.inf, 0.0]),
        "NaN in Q": lambda lbl: _controller(lbl, ocp(Q=nan_q)),
        "inf in R": lambda lbl: _controller(lbl, ocp(R=[[np.inf]])),
        "NaN in a bound": lambda lbl: _controller(lbl, ocp(u_min=[np.nan])),
        "l > u": lambda lbl: _controller(lbl, ocp(u_min=[1.0], u_max=[-1.0])),
        "indefinite Q": lambda lbl: _controller(lbl, ocp(Q=np.diag([1.0, -1.0]))),
        "mismatched shapes": lambda lbl: _controller(lbl, ocp(Q=np.eye(3))),
    }


def _runtime_cases():
    """Cases that reach the solver: (name -> (controller factory, x0, how to lift the fault or None))."""
    nan_model = Pendulum(m=float("nan"))
    return {
        "NaN model parameter": (lambda lbl: _controller(lbl, nan_model.ocp(knots=3)), X0, None),
        # Hard state bounds (the QPs' default is soft, under which this start is no fault: see the soft rows).
        "infeasible state bounds": (
            lambda lbl: _controller(lbl, PENDULUM.ocp(knots=3, **BOUNDED), **_hard(lbl)),
            BAD_START,
            "good start",
        ),
        "max_iter = 1": (lambda lbl: _controller(lbl, PENDULUM.ocp(knots=3), max_iter=1), X0, "max_iter"),
        "time budget 1 µs": (lambda lbl: _controller(lbl, PENDULUM.ocp(knots=3), time_limit=1e-6), X0, "time_limit"),
    }


def _hard(label) -> dict:
    """The option that makes a solver's state bounds hard constraints (the QPs default to soft ones)."""
    return {"state_bounds": "hard"} if SOLVERS[label][0] == "qp" else {}


def run_case(case: str, label: str) -> Outcome | None:
    """One cell of the matrix (None where the case does not apply to the solver)."""
    construction = _construction_cases()
    start = time.perf_counter()
    if case in construction:
        try:
            construction[case](label)
        except (ValueError, TypeError) as exc:
            return Outcome(case, label, f"error: {exc}", time.perf_counter() - start)
        return Outcome(case, label, SUCCESS, time.perf_counter() - start, recovered=None)
    factory, x0, lift = _runtime_cases()[case]
    if lift == "max_iter" and SOLVERS[label][0] not in ITERATIVE:
        return None
    if lift == "good start" and SOLVERS[label][0] in SAMPLING:
        return None  # they hold state bounds as an exact penalty only (soft): this start is no fault for them
    try:
        ctrl = factory(label)
    except (ValueError, TypeError) as exc:
        return Outcome(case, label, f"error: {exc}", time.perf_counter() - start)
    if lift == "time_limit":  # a controller already running: its kernels are compiled, its solver set up
        ctrl.time_limit, budget = None, ctrl.time_limit
        ctrl.solve(X0, GOAL)
        ctrl.time_limit = budget
        ctrl.reset()
    start = time.perf_counter()
    sol = ctrl.solve(x0, GOAL)
    seconds = time.perf_counter() - start
    ocp = ctrl.ocp
    outcome = Outcome(
        case,
        label,
        sol.status,
        seconds,
        finite=bool(np.isfinite(sol.u).all()),
        within_bounds=bool(np.all(sol.u >= ocp.u_min - 1e-9) and np.all(sol.u <= ocp.u_max + 1e-9)),
    )
    if lift is not None:
        outcome.recovered = _recovers(ctrl, lift, label)
    return outcome


def _recovers(ctrl, lift: str, label: str) -> bool:
    """After the failure, lift the fault: the same controller must match a fresh one on a good problem."""
    good_x0 = np.array([0.5, 0.0]) if lift == "good start" else X0
    if lift == "max_iter":
        ctrl.max_iter = 10_000 if SOLVERS[label][0] == "qp" else 500
    if lift == "time_limit":
        ctrl.time_limit = None
    ctrl.reset()
    again = ctrl.solve(good_x0, GOAL)
    fresh = _controller(label, ctrl.ocp, **(_hard(label) if lift == "good start" else {})).solve(good_x0, GOAL)
    return again.status == fresh.status == SUCCESS and bool(np.allclose(again.u, fresh.u, atol=1e-6))


def matrix(labels=tuple(SOLVERS)) -> list[Outcome]:
    """Every case against every solver in ``labels``."""
    cases = list(_construction_cases()) + list(_runtime_cases())
    return [o for case in cases for label in labels if (o := run_case(case, label)) is not None]


def format_matrix(outcomes: list[Outcome]) -> str:
    """Cases × solvers with the outcome (and time for runtime cases); BAD marks an unacceptable cell."""
    labels = list(dict.fromkeys(o.solver for o in outcomes))
    cases = list(dict.fromkeys(o.case for o in outcomes))
    cell = {(o.case, o.solver): o for o in outcomes}
    width = 22
    lines = [f"{'case':<24}" + "".join(f"{lbl[:width]:<{width}}" for lbl in labels)]
    for case in cases:
        row = f"{case:<24}"
        for lbl in labels:
            o = cell.get((case, lbl))
            if o is None:
                text = "n/a"
            elif o.result.startswith("error"):
                text = "ValueError"
            else:
                text = f"{o.result} {1e3 * o.seconds:.1f}ms" + (
                    "" if o.recovered is None else (" rec" if o.recovered else " NOREC")
                )
            if o is not None and not o.acceptable:
                text = "BAD " + text
            row += f"{text[: width - 1]:<{width}}"
        lines.append(row)
    return "\n".join(lines)
