"""`ocpkit bench faults`: the adversarial matrix — bad data and hard limits against every solver.

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
from ocpkit.benchmarks.step import load_medians
from ocpkit.status import SOFT, SUCCESS
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
        return (self.result != SUCCESS and self.finite and self.within_bounds and self.recovered is not False
                and self.seconds < SOLVE_CAP)


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
        "infeasible state bounds": (lambda lbl: _controller(lbl, PENDULUM.ocp(knots=3, **BOUNDED), **_hard(lbl)),
                                    BAD_START, "good start"),
        "max_iter = 1": (lambda lbl: _controller(lbl, PENDULUM.ocp(knots=3), max_iter=1), X0, "max_iter"),
        "time budget 1 µs": (lambda lbl: _controller(lbl, PENDULUM.ocp(knots=3), time_limit=1e-6), X0,
                             "time_limit"),
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
    outcome = Outcome(case, label, sol.status, seconds, finite=bool(np.isfinite(sol.u).all()),
                      within_bounds=bool(np.all(sol.u >= ocp.u_min - 1e-9) and np.all(sol.u <= ocp.u_max + 1e-9)))
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
                text = f"{o.result} {1e3 * o.seconds:.1f}ms" + ("" if o.recovered is None else
                                                              (" rec" if o.recovered else " NOREC"))
            if o is not None and not o.acceptable:
                text = "BAD " + text
            row += f"{text[:width - 1]:<{width}}"
        lines.append(row)
    return "\n".join(lines)


def bench_faults(labels=tuple(SOLVERS), realtime: bool = True, out=print) -> list:
    """Print the matrix ("rec" = the same controller then matched a fresh one on a good problem), then the
    real-time rows (:func:`realtime_rows`) with their measured wall times and statuses, then the cache rows
    (:func:`cache_rows`)."""
    outcomes = matrix(labels)
    out(format_matrix(outcomes))
    bad = [o for o in outcomes if not o.acceptable]
    out(f"{len(outcomes)} cells, {len(bad)} unacceptable")
    if not realtime:
        return outcomes
    rows = realtime_rows()
    out("")
    out(format_realtime(rows))
    out(f"{len(rows)} real-time rows, {sum(not r.acceptable for r in rows)} unacceptable")
    cache = cache_rows(out)
    out("")
    out(format_realtime(cache))
    out(f"{len(cache)} cache rows, {sum(not r.acceptable for r in cache)} unacceptable")
    return outcomes + rows + cache


# --- Real-time rows: step budgets, absurd states, the warm/cold budget spiral, goals beyond bounds, threads, load.

@dataclass
class RealTimeRow:
    """One real-time check: the measured wall time (s) the criterion is about, the statuses seen, the verdict."""

    case: str
    solver: str
    detail: str
    seconds: float
    statuses: str
    acceptable: bool
    criterion: str


def _counts(statuses) -> str:
    from collections import Counter
    return ", ".join(f"{k} {v}" for k, v in Counter(statuses).most_common())


BUDGET_SOLVERS = {  # label -> (options, knots): nlink:13, T = 100
    "qp condensed proxqp": ({"form": "condensed", "qp": "proxqp"}, 5),
    "qp condensed osqp": ({"form": "condensed", "qp": "osqp"}, 5),
    "qp condensed daqp": ({"form": "condensed", "qp": "daqp"}, 5),  # the default: the compiled C step
    "qp condensed daqp, Python step": ({"form": "condensed", "qp": "daqp", "native": False}, 5),
    "qp sparse proxqp": ({"form": "sparse", "qp": "proxqp"}, 5),
    "qp sparse osqp": ({"form": "sparse", "qp": "osqp"}, 5),
    "qp sparse hpipm (p=T)": ({"form": "sparse", "qp": "hpipm"}, None),
}


def _replayed_states(problem, ocp, steps, seed=0):
    """A closed loop of the default controller on the OCP's discrete model: the states every row replays."""
    x, goal = problem.sample(seed)
    F, ref, xs = ocp.discrete(), solvers.make("qp", ocp), []
    for _ in range(steps):
        xs.append(x)
        x = np.asarray(F(x, ref.solve(x, goal).u)).ravel()
    return xs, goal


def budget_rows(budgets=(1e-3, 5e-3, 50e-3), steps=10, labels=tuple(BUDGET_SOLVERS)) -> list[RealTimeRow]:
    """nlink:13, T=100: each backend and form, calibrated by one unbudgeted step, then ``steps`` replayed steps
    per budget; acceptable if the slowest step took at most 2 × budget + 2 ms. IPOPT: nlink:7, T=50."""
    rows = []
    problem = problems.make("nlink:13")
    xs, goal = _replayed_states(problem, problem.ocp(horizon=100, knots=5), steps)
    for label in labels:
        options, knots = BUDGET_SOLVERS[label]
        ocp = problem.ocp(horizon=100, knots=knots) if knots else problem.ocp(horizon=100)
        rows += _budgeted(solvers.make("qp", ocp, **options), label, "nlink:13 T=100", xs, goal, budgets)
    problem = problems.make("nlink:7")
    ocp = problem.ocp(horizon=50)
    xs, goal = _replayed_states(problem, ocp, steps)
    rows += _budgeted(solvers.make("ipopt", ocp), "ipopt", "nlink:7 T=50", xs, goal, (10e-3, 50e-3))
    return rows


def _budgeted(ctrl, label, name, xs, goal, budgets):
    ctrl.wait_compiled()  # the steady state: LinearMPC's C step, or the compiled affine model, in place
    ctrl.warm_up(xs[0], goal)  # calibration: the unbounded steps of a new controller
    rows = []
    for budget in budgets:
        ctrl.time_limit = budget
        walls, statuses = [], []
        for x in xs:
            t0 = time.perf_counter()
            sol = ctrl.solve(x, goal)
            walls.append(time.perf_counter() - t0)
            statuses.append(sol.status)
        worst = max(walls)
        rows.append(RealTimeRow("step budget", label, f"{name}, budget {1e3 * budget:g} ms, {len(xs)} steps, "
                                f"median {1e3 * float(np.median(walls)):.2f} ms", worst, _counts(statuses),
                                worst <= 2 * budget + 2e-3, "slowest step ≤ 2 × budget + 2 ms"))
    return rows


def huge_state_rows(labels=tuple(SOLVERS)) -> list[RealTimeRow]:
    """Pendulum at x = [1e20, 0]: every solver answers in ≤ 50 ms with a non-success status and a finite input."""
    rows = []
    for label in labels:
        ctrl = _controller(label, PENDULUM.ocp(knots=3))
        t0 = time.perf_counter()
        sol = ctrl.solve([1e20, 0.0], GOAL)
        wall = time.perf_counter() - t0
        ok = sol.status != SUCCESS and bool(np.isfinite(sol.u).all()) and wall <= 0.05
        rows.append(RealTimeRow("x = 1e20", label, f"pendulum: {sol.raw_status[:48]}", wall, sol.status, ok,
                                "non-success, finite u, ≤ 50 ms"))
    return rows


def spiral_row(steps=50, links=7, horizon=100, knots=None) -> RealTimeRow:
    """The warm/cold budget spiral: sparse OSQP with a budget halfway between its warm and cold step times (both
    measured here); from a cold start, ≥ 90% of ``steps`` closed-loop steps must succeed."""
    problem = problems.make(f"nlink:{links}")
    ocp = problem.ocp(horizon=horizon, knots=knots) if knots else problem.ocp(horizon=horizon)
    x, goal = problem.sample(0)
    F = ocp.discrete()
    ctrl = solvers.make("qp", ocp, form="sparse", qp="osqp")
    cold = ctrl.solve(x, goal).times["total"]
    warm = float(np.median([ctrl.solve(x, goal).times["total"] for _ in range(3)]))
    ctrl.reset()  # keeps the measured costs, drops the workspace: the next step is cold again
    budget = 0.5 * (cold + warm)
    ctrl.time_limit = budget
    statuses, walls = [], []
    for _ in range(steps):
        sol = ctrl.solve(x, goal)
        statuses.append(sol.status)
        walls.append(sol.times["total"])
        x = np.asarray(F(x, sol.u)).ravel()
    ok = statuses.count(SUCCESS) >= 0.9 * steps
    return RealTimeRow("warm/cold spiral", "qp sparse osqp",
                       f"nlink:{links} T={horizon}: cold {1e3 * cold:.0f} ms, warm {1e3 * warm:.0f} ms, budget "
                       f"{1e3 * budget:.0f} ms, {statuses.count(SUCCESS)}/{steps} success", max(walls),
                       _counts(statuses), ok, "≥ 90% of the steps succeed")


BEYOND_TOL = 1e-3  # a success's predicted states beyond a soft bound by more than this count as beyond it


def beyond_bounds_rows(labels=("qp condensed daqp", "qp condensed proxqp", "qp condensed osqp", "qp sparse proxqp",
                               "qp sparse osqp"),
                       duration=1.0) -> list[RealTimeRow]:
    """Pendulum with |q| ≤ 1 and goal q = 1.5 (soft state bounds, the default): from rest the angle must end at
    the bound (within 0.02) and no success may predict a state beyond it. The exact and interior-point backends must
    answer every step (a success, or "soft" where the plan on the nonlinear model passes the bound: the QP's model
    about the goal beyond it mispredicts gravity there); OSQP, first-order, is accepted with its success rate reported (at eps 1e-9 its ADMM needs
    10⁴–6.5·10⁴ iterations on this QP: README, "for state bounds that may be active, use DAQP or ProxQP") as long
    as each step stays within the default budget."""
    from ocpkit.sim.simulate import simulate

    ocp = PENDULUM.ocp(knots=5, x_min=[-1.0, -np.inf], x_max=[1.0, np.inf])
    rows = []
    for label in labels:
        ctrl = _controller(label, ocp)
        t0 = time.perf_counter()
        traj = simulate(PENDULUM.plant(), ctrl, [0.0, 0.0], [1.5, 0.0], duration)
        wall = time.perf_counter() - t0
        q_end, n_ok, n_soft = float(traj.x[-1, 0]), traj.statuses.count(SUCCESS), traj.statuses.count(SOFT)
        beyond = max((float(np.abs(s.x_pred[:, 0]).max()) for s in traj.solutions
                      if s.ok and s.x_pred is not None), default=0.0)
        first_order = "osqp" in label
        slowest = float(traj.times().max())
        ok = (abs(q_end - 1.0) <= 0.02 and beyond <= 1.0 + BEYOND_TOL
              and (slowest <= ctrl.ceiling if first_order else n_ok + n_soft == len(traj.statuses)))
        rule = ("success rate reported, each step within the default budget" if first_order
                else "every step answered (success or soft)")
        rows.append(RealTimeRow("goal beyond bounds", label, f"q_end {q_end:.4f}, {n_ok}/{len(traj.statuses)} "
                                f"success, {n_soft} soft, max |q| {np.abs(traj.x[:, 0]).max():.4f}, successes' predictions "
                                f"|q| ≤ {beyond:.4f}", wall, _counts(traj.statuses),
                                ok, f"|q_end − 1| ≤ 0.02, no success predicts |q| > 1 + {BEYOND_TOL:g}, {rule}"))
    return rows


def two_threads_rows(labels=("qp condensed daqp", "qp condensed proxqp", "qp sparse osqp"), per_thread=160) -> list[RealTimeRow]:
    """One controller shared by two threads, each solving its own stream of states: every success must equal a
    single-threaded cold solve of the same state (1e-5) with u within bounds, and nothing may raise."""
    import threading

    ocp = PENDULUM.ocp(knots=3)
    rng = np.random.default_rng(0)
    states = [np.array([rng.uniform(-np.pi, np.pi), rng.uniform(-2, 2)]) for _ in range(16)]
    rows = []
    for label in labels:
        ref_ctrl = _controller(label, ocp)
        ref = []
        for x in states:
            ref_ctrl.reset()
            ref.append(ref_ctrl.solve(x, GOAL).u)
        shared = _controller(label, ocp)
        results, errors = [], []

        def worker(offset):
            try:
                for k in range(per_thread):
                    i = (k + offset) % len(states)
                    results.append((i, shared.solve(states[i], GOAL)))
            except Exception as exc:  # noqa: BLE001 - counted and reported
                errors.append(repr(exc))

        t0 = time.perf_counter()
        threads = [threading.Thread(target=worker, args=(o,)) for o in (0, 7)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wall = time.perf_counter() - t0
        wrong = sum(1 for i, s in results if s.ok and (not np.allclose(s.u, ref[i], atol=1e-5)
                                                        or (s.u < ocp.u_min - 1e-9).any() or (s.u > ocp.u_max + 1e-9).any()))
        n_ok = sum(s.ok for _, s in results)
        rows.append(RealTimeRow("two threads", label, f"{len(results)} steps, {n_ok} success, {wrong} wrong, "
                                f"{len(errors)} raised", wall, _counts(s.status for _, s in results),
                                wrong == 0 and not errors and len(results) == 2 * per_thread,
                                "no wrong success, nothing raised"))
    return rows


def loaded_row(busy=2, steps=30) -> RealTimeRow:
    """nlink:13 T=100 condensed knots step: median beside ``busy`` busy processes ≤ 2 × the quiet median."""
    med = load_medians(steps=steps, busy=busy)
    q, l = med[(1, "quiet")], med[(1, "loaded")]
    return RealTimeRow("loaded machine", "qp condensed daqp",
                       f"nlink:13 T=100 median quiet {1e3 * q:.2f} ms, {busy} busy processes {1e3 * l:.2f} ms "
                       f"(unlimited BLAS threads: {1e3 * med[(None, 'quiet')]:.2f} / {1e3 * med[(None, 'loaded')]:.2f} ms)",
                       l, "", l <= 2 * q, "loaded median ≤ 2 × quiet median")


def unbounded_default_rows() -> list[RealTimeRow]:
    """No budget given: sparse ProxQP at x = 9e5 on nlink:3 (74.5 s once) and with max_iter=5 on nlink:13 (45 s) must
    stop within 2 × LinearMPC's default ceiling; a pendulum at T = 10⁶ in the sparse form must be announced by
    ``ocpkit solve`` before any work (within 1 s)."""
    import contextlib
    import io

    from ocpkit import cli
    from ocpkit.cli.checks import check_size

    rows = []
    for name, options, start in (("nlink:3", {}, 9e5), ("nlink:13", {"max_iter": 5}, None)):
        problem = problems.make(name)
        ocp = problem.ocp(knots=5, horizon=100) if name == "nlink:13" else problem.ocp(knots=5)
        ctrl = solvers.make("qp", ocp, form="sparse", qp="proxqp", native=False, **options)
        x, goal = problem.sample(0)
        if start is not None:
            x, goal = np.r_[start, np.zeros(ocp.nx - 1)], np.zeros(ocp.nx)
        t0 = time.perf_counter()
        sol = ctrl.solve(x, goal)
        wall = time.perf_counter() - t0
        rows.append(RealTimeRow("no budget given", "qp sparse proxqp", f"{name}{', max_iter 5' if options else ''}"
                                f"{f', x_0 = {start:g}' if start else ''}: {sol.raw_status[:50]}", wall, sol.status,
                                wall <= 2 * ctrl.ceiling, f"≤ 2 × the default ceiling ({ctrl.ceiling:g} s)"))
    args = cli._parser().parse_args(["solve", "pendulum", "--horizon", "1000000", "--form", "sparse"])
    err = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stderr(err):
        check_size(problems.make("pendulum"), args)
    wall = time.perf_counter() - t0
    said = "warning" in err.getvalue()
    rows.append(RealTimeRow("no budget given", "cli solve --form sparse", "pendulum T = 10⁶: "
                            + ("announced" if said else "not announced"), wall, "warning" if said else "-",
                            said and wall <= 1.0, "announced before any work, ≤ 1 s"))
    return rows


def realtime_rows() -> list[RealTimeRow]:
    """Every real-time row (about a minute and a half here: calibrating sparse ProxQP at nlink:13, and the
    unbounded-default rows' 10-15 s steps)."""
    return (budget_rows() + sampling_budget_rows() + huge_state_rows() + [spiral_row()] + beyond_bounds_rows()
            + two_threads_rows() + [loaded_row()] + unbounded_default_rows() + not_dask_rows())


def format_realtime(rows: list[RealTimeRow]) -> str:
    lines = [f"{'case':20} {'solver':30} {'wall ms':>9}  {'ok':3} statuses | detail | criterion"]
    for r in rows:
        lines.append(f"{r.case:20} {r.solver:30} {1e3 * r.seconds:9.2f}  {'yes' if r.acceptable else 'BAD':3} "
                     f"{r.statuses} | {r.detail} | {r.criterion}")
    return "\n".join(lines)


# --- Cache rows: a read-only cache with and without the C step, and four scripts that want one entry at once.

# One default LinearMPC of nlink:13 (5 knots) from a script: construction and first step timed, its warnings, as JSON.
_CACHE_SCRIPT = """
import json, time, warnings
from ocpkit import problems
from ocpkit.solvers.qp import LinearMPC
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    p = problems.make("nlink:13")
    x, goal = p.sample(0)
    t0 = time.perf_counter()
    c = LinearMPC(p.ocp(knots=5))
    native = c.native
    status = c.solve(x, goal).status
    wall = time.perf_counter() - t0
    ready = c.wait_compiled(WAIT)
print(json.dumps({"native": native, "status": status, "wall": wall, "ready": ready, "now_native": c.native,
                  "warnings": [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]}))
"""


def _cache_script(wait: float) -> list[str]:
    import sys

    return [sys.executable, "-c", _CACHE_SCRIPT.replace("WAIT", repr(wait))]


def _script_result(run) -> dict:
    """The script's JSON line, or {"error": its last stderr line} where it raised."""
    import json

    lines = run.stdout.strip().splitlines()
    if run.returncode or not lines:
        err = run.stderr.strip().splitlines()
        return {"error": err[-1] if err else f"exit status {run.returncode}"}
    return json.loads(lines[-1])


def cache_rows(out=print) -> list[RealTimeRow]:
    """A read-only cache (:mod:`ocpkit.benchmarks.readonly`: a read-only bind mount as root, write permission
    removed otherwise) holding nlink:13's C step (from ``ocpkit build``): the first step must run in C with no
    warning and nothing raised; without it: the Python step, one warning, nothing raised; and four scripts
    started together on an empty cache: one build (``make`` counted through a wrapper on PATH), all four in C."""
    import os
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    from ocpkit.benchmarks import readonly

    rows = []
    with tempfile.TemporaryDirectory(prefix="ocpkit-bench-cache-") as tmp:
        tmp = Path(tmp)
        if readonly.method() is None:
            out("cache rows: the read-only ones skipped (this machine cannot make a folder read-only: root without "
                "mount namespaces)")
        else:
            filled, empty = tmp / "filled", tmp / "empty"
            empty.mkdir(mode=0o700)
            subprocess.run([sys.executable, "-m", "ocpkit.cli", "build", "nlink:13", "--knots", "5"], check=True,
                           env={**os.environ, "OCPKIT_CACHE_DIR": str(filled)}, capture_output=True, timeout=900,
                           cwd=tmp)  # the scripts run outside any checkout, which would shadow the installed ocpkit
            for label, root in (("sound entry", filled), ("no entry", empty)):
                before = sorted(p.name for p in root.rglob("*"))
                run = readonly.run(root, _cache_script(0), env={**os.environ, "OCPKIT_CACHE_DIR": str(root)},
                                   capture_output=True, text=True, timeout=600, cwd=tmp)
                r = _script_result(run)
                written = sorted(p.name for p in root.rglob("*")) != before
                if "error" in r:
                    rows.append(RealTimeRow("read-only cache", label, f"raised: {r['error'][:100]}", float("nan"),
                                            "exception", False, "nothing raised"))
                    continue
                if label == "sound entry":
                    ok = r["native"] and r["status"] == SUCCESS and not r["warnings"] and not written
                    criterion = "first step in C, success, no warning, nothing written"
                else:
                    ok = (not r["native"] and r["status"] == SUCCESS and len(r["warnings"]) == 1
                          and "read-only" in r["warnings"][0] and not written)
                    criterion = "Python step, success, one warning, nothing raised or written"
                rows.append(RealTimeRow("read-only cache", label, f"nlink:13 p=5 ({readonly.method()}): "
                                        f"{'C step' if r['native'] else 'Python step'}, {len(r['warnings'])} warnings"
                                        f"{': ' + _gist(r['warnings'][0]) if r['warnings'] else ''}", r["wall"],
                                        r["status"], bool(ok), criterion))
        rows.append(_concurrent_row(tmp))
    return rows + [planted_entry_row()] + full_disk_rows(out)


def _gist(warning: str) -> str:
    """A cache warning without its paths (they name a temporary folder): its start and what runs instead."""
    import re

    return re.sub(r"\s*\(?/\S+\)?", "", warning.split(": prebuild")[0])[:70] + " …"


def _concurrent_row(tmp, scripts: int = 4) -> RealTimeRow:
    """``scripts`` processes wanting one C step at once on an empty cache: builds counted by a `make` wrapper."""
    import os
    import shutil
    import subprocess
    import time

    root, bin_dir, log = tmp / "concurrent", tmp / "bin", tmp / "make.log"
    bin_dir.mkdir()
    (bin_dir / "make").write_text(f'#!/bin/sh\necho build >> {log}\nexec {shutil.which("make")} "$@"\n')
    (bin_dir / "make").chmod(0o755)
    env = {**os.environ, "OCPKIT_CACHE_DIR": str(root), "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}
    t0 = time.perf_counter()
    procs = [subprocess.Popen(_cache_script(300), env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              cwd=tmp)
             for _ in range(scripts)]
    results = []
    for proc in procs:
        stdout, stderr = proc.communicate(timeout=900)
        results.append(_script_result(subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)))
    wall = time.perf_counter() - t0
    builds = log.read_text().count("build") if log.exists() else 0
    in_c = sum(bool(r.get("now_native")) for r in results)
    errors = sum("error" in r for r in results)
    return RealTimeRow("concurrent builds", f"{scripts} scripts, one entry", f"nlink:13 p=5: {builds} build(s), "
                       f"{in_c}/{scripts} scripts then in C, {errors} raised", wall,
                       _counts(r.get("status", "exception") for r in results), builds == 1 and in_c == scripts,
                       "one build machine-wide, every script then in C")


def planted_entry_row() -> RealTimeRow:
    """Another user's planted C step: nlink:13's default entry folder opened to everyone (mode 777), its libmpc.so
    and content hash replaced by a library whose constructor leaves a marker. A script's default LinearMPC must not
    load it (no marker) and refuse in one line (``UnsafeCacheError``)."""
    import os
    import shutil
    import subprocess
    import tempfile
    import time
    from pathlib import Path

    from ocpkit import problems
    from ocpkit.export import native
    from ocpkit.codegen.cache import write_entry
    from ocpkit.solvers.qp import LinearMPC

    with tempfile.TemporaryDirectory(prefix="ocpkit-bench-planted-") as tmp:
        tmp = Path(tmp)
        root, marker = tmp / "cache", tmp / "constructor-ran"
        env = {**os.environ, "OCPKIT_CACHE_DIR": str(root)}
        ocp = problems.make("nlink:13").ocp(knots=5)
        python = LinearMPC(ocp, native=False)  # the settings a default LinearMPC hands to ocpkit.export.native
        settings = (python._backend.tolerance, python.max_iter, python.linearization, 1, 0.0)
        root.mkdir(mode=0o700)
        scratch, key, _ = native._generate(ocp, settings, root / "native")  # the entry's key; nothing built
        shutil.rmtree(scratch)
        entry = root / "native" / key
        entry.mkdir(mode=0o777)
        entry.chmod(0o777)
        (tmp / "planted.c").write_text('#include <stdio.h>\n__attribute__((constructor)) static void planted(void) '
                                       f'{{ FILE *f = fopen("{marker}", "w"); if (f) fclose(f); }}\n')
        subprocess.run([os.environ.get("CC", "cc"), "-shared", "-fPIC", str(tmp / "planted.c"), "-o",
                        str(tmp / "planted.so")], check=True)
        write_entry(entry / f"lib{native.NAME}.so", (tmp / "planted.so").read_bytes())
        t0 = time.perf_counter()
        run = subprocess.run(_cache_script(0), env=env, capture_output=True, text=True, timeout=600, cwd=tmp)
        wall = time.perf_counter() - t0
        r = _script_result(run)
        refused = r.get("error", "").startswith("ocpkit.codegen.cache.UnsafeCacheError: ")
        planted_ran = marker.exists()
    return RealTimeRow("planted cache entry", "qp condensed daqp (default)",
                       f"nlink:13 p=5, entry folder 777: {'not loaded' if not planted_ran else 'LOADED'}, "
                       f"{_gist(r['error']) if refused else 'not refused'}", wall,
                       "refused" if refused else r.get("status", "exception"), refused and not planted_ran,
                       "the planted library never loaded; one-line refusal")


def full_disk_rows(out=print) -> list[RealTimeRow]:
    """A script's default LinearMPC of nlink:13 with its cache on a full file system (a filled tmpfs,
    :func:`ocpkit.benchmarks.readonly.run_full`; root with mount namespaces only): the Python step, success, one
    warning naming the folder as full, nothing raised."""
    import os
    import tempfile
    from pathlib import Path

    from ocpkit.benchmarks import readonly

    if readonly.method() != readonly.BIND_MOUNT:
        out("cache rows: the full-disk one skipped (a full file system needs root with mount namespaces)")
        return []
    with tempfile.TemporaryDirectory(prefix="ocpkit-bench-full-") as tmp:
        root = Path(tmp) / "cache"
        root.mkdir(mode=0o700)
        run = readonly.run_full(root, _cache_script(0), env={**os.environ, "OCPKIT_CACHE_DIR": str(root)},
                                capture_output=True, text=True, timeout=600, cwd=tmp)
    r = _script_result(run)
    if "error" in r:
        return [RealTimeRow("full disk", "qp condensed daqp (default)", f"raised: {r['error'][:100]}",
                            float("nan"), "exception", False, "nothing raised")]
    ok = (not r["native"] and r["status"] == SUCCESS and len(r["warnings"]) == 1
          and f"{root}/native is full" in r["warnings"][0])
    return [RealTimeRow("full disk", "qp condensed daqp (default)", f"nlink:13 p=5 (filled tmpfs): "
                        f"{'C step' if r['native'] else 'Python step'}, {len(r['warnings'])} warnings"
                        f"{': ' + _gist(r['warnings'][0]) if r['warnings'] else ''}", r["wall"], r["status"],
                        bool(ok), "Python step, success, one warning naming the folder as full, nothing raised")]


def not_dask_rows() -> list[RealTimeRow]:
    """`ocpkit study … --scheduler` at a server that is no Dask scheduler: a web server (``python -m http.server``)
    and a listener that never answers. Each must end in one line within the handshake timeout
    (:data:`ocpkit.runs.cluster.HANDSHAKE_S`) plus twice the command's cost against a closed port (its start, measured
    first), and leave no results store."""
    import os
    import socket
    import subprocess
    import sys
    import tempfile
    import time
    from pathlib import Path

    from ocpkit.runs.cluster import HANDSHAKE_S

    def study(address: str, tmp: Path) -> tuple[float, int, list[str], bool]:
        out_dir = tmp / "out"
        t0 = time.perf_counter()
        run = subprocess.run([sys.executable, "-m", "ocpkit.cli", "study", "robustness", "--problem", "pendulum",
                              "--scheduler", address, "--out", str(out_dir)], capture_output=True, text=True,
                             timeout=600, cwd=tmp)  # outside any checkout, which would shadow the installed ocpkit
        lines = [line for line in run.stderr.splitlines() if line.strip()]
        return time.perf_counter() - t0, run.returncode, lines, out_dir.exists()

    def free_port() -> int:
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            return probe.getsockname()[1]

    rows = []
    with tempfile.TemporaryDirectory(prefix="ocpkit-bench-not-dask-") as tmp:
        tmp = Path(tmp)
        baseline = study(f"tcp://127.0.0.1:{free_port()}", tmp)[0]  # refused at once: the command's own cost
        port = free_port()
        web = subprocess.Popen([sys.executable, "-m", "http.server", str(port), "--bind", "127.0.0.1"], cwd=tmp,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            deadline = time.monotonic() + 60
            while socket.socket().connect_ex(("127.0.0.1", port)) and time.monotonic() < deadline:
                time.sleep(0.05)
            cases = [("web server", f"tcp://127.0.0.1:{port}")]
            with socket.socket() as silent:
                silent.bind(("127.0.0.1", 0))
                silent.listen()
                cases.append(("silent listener", f"tcp://127.0.0.1:{silent.getsockname()[1]}"))
                for label, address in cases:
                    wall, code, lines, left = study(address, tmp)
                    ok = (code == 2 and len(lines) == 1 and "is not a Dask scheduler" in lines[0] and not left
                          and wall <= HANDSHAKE_S + 2 * baseline + 1)
                    rows.append(RealTimeRow("scheduler not Dask", f"cli study, {label}",
                                            f"exit {code}, {len(lines)} line(s): {lines[-1][15:95] if lines else '-'}"
                                            f"{', store LEFT' if left else ', no store'}", wall,
                                            "refused" if code == 2 else f"exit {code}", ok,
                                            f"one line ≤ {HANDSHAKE_S:g} s + 2 × {baseline:.1f} s start, no store"))
        finally:
            web.kill()
            web.wait()
    return rows


def sampling_budget_rows(steps=20, budget=1e-3) -> list[RealTimeRow]:
    """"EMPC 1 ms budget": EMPC, CEM and MPPI (population 1024, CPU) on nlink:13 after warm_up, ``steps`` replayed
    steps at ``budget``: the budget covers the whole call (issue 44: 88 ms-1.1 s a call, the linearization and the
    preconditioner running before it was checked); acceptable as the other step budgets, slowest ≤ 2 × budget + 2 ms."""
    problem = problems.make("nlink:13")
    ocp = problem.ocp()
    xs, goal = _replayed_states(problem, ocp, steps)
    rows = []
    for name in ("empc", "cem", "mppi"):
        for row in _budgeted(solvers.make(name, ocp, arch="cpu"), name, "nlink:13 T=50", xs, goal, (budget,)):
            row.case = "EMPC 1 ms budget"
            rows.append(row)
    return rows
