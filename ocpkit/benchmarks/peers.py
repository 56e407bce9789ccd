"""The peers' like-for-like tables (issue 48's must-show): ocpkit's RTI C step, IPOPT, acados and Crocoddyl on the
very same OCPs, in closed loop on the same plant: ``ocpkit bench peers``.

For each integrator (RK4, semi-implicit Euler) and problem (Puma 560, Panda, nlink:13; T = 50), every controller runs
its own closed loop from each seeded start and goal (seeds from :data:`FIRST_SEED`, never used to tune anything) on
the problem's RK4 plant. The problems are made without joint damping and friction
(:func:`~ocpkit.benchmarks.crocoddyl_peer.undamped`: Crocoddyl's free dynamics have none), so that every row, with or
without Crocoddyl, solves the same OCP and shares one reference: IPOPT's closed loop at p = T.

Two tables, never mixed:

* p = T (a node every step), one iteration a step: ocpkit's RTI (one Gauss–Newton step, the condensed QP's C step;
  and "rti hpipm", the controller "rti-hpipm": the sparse QP by HPIPM's Riccati interior point through CasADi),
  acados' SQP-RTI (one SQP iteration, partial-condensing HPIPM; RK4 as acados' ERK, Euler as DISCRETE dynamics of
  ocpkit's step), Crocoddyl's FDDP with one iteration a step warm-started from the last plan (its RTI analogue);
  and converged every step: IPOPT (tol 1e-8 on its scaled NLP error, the reference; and "ipopt 1e-6" with that and
  its unscaled dual and primal infeasibility and complementarity ≤ 1e-6: :data:`IPOPT_KKT`), acados' SQP (every KKT
  residual, ∞-norm, ≤ 1e-6: tol_stat, tol_eq, tol_ineq, tol_comp), FDDP (th_stop 1e-12 on its expected decrease
  ½ Σ Q_uᵀQ_uu⁻¹Q_u, which leaves ‖Q_u‖∞ ≤ 1e-6: :data:`~ocpkit.benchmarks.crocoddyl_peer.TH_STOP_KKT`).
* knots (the same freedom: p inputs over the horizon): ocpkit's RTI C step on its p-knot piecewise-linear OCP and on
  the zero-order hold of p blocks, and acados' SQP-RTI on the coarse grid (N = p intervals of T/p steps, the input
  held over each), the nearest analogue acados has. Crocoddyl has no coarse grid.

Columns: "it" the median iterations a step; "step ms" the median over seeds of each seed's median step time
(``Solution.times["total"]``, what the control loop waits for) and, in brackets, the worst seed's; "max ms" the
slowest step of all (the first steps are cold); "ms/it" the median step over its iterations (per iteration);
"model/build/QP" the medians of the step's parts (ocpkit: sensitivities, condensing, QP; the peers time their
whole solve as QP, acados' set-up from Python as build); "cost/ipopt" each seed's closed-loop actual cost over IPOPT's,
median [worst]; "fallbk" the fallbacks; "path" what
answered most steps (ocpkit's C step, a fallback, the peer). The default size, 5 seeds x 50 steps (n = 250 steps a
row), takes 5-10 minutes on 2 idle cores once every solver is built (2 x 10 took 50 s at load 5); the first run
compiles acados' 18 solvers (10-80 s each) and ocpkit's C steps into the cache. acados runs
in a process of its own (:func:`ocpkit.benchmarks.acados_install.isolated`), Crocoddyl where importable (the extra
``peers``: it needs pin < 4.1); an absent peer is skipped with one line saying why.
"""

from __future__ import annotations

import time

import numpy as np

from ocpkit import solvers
from ocpkit._checks import integer
from ocpkit.benchmarks import acados_install, crocoddyl_peer
from ocpkit.benchmarks.closed_loop import closed_loop, load
from ocpkit.solvers.methods import KNOTS

PROBLEMS = ("puma560", "panda", "nlink:13")
INTEGRATORS = ("rk4", "euler")
# The first seed: the tuned and documented runs used seeds 0-9.
FIRST_SEED = 100
# Every converged row's tolerance (acados' KKT residuals; FDDP: crocoddyl_peer.TH_STOP_KKT).
KKT_TOL = 1e-6
TABLES = ("p = T", "knots")
# IPOPT at the peers' tolerance: its scaled NLP error and each unscaled residual (dual and primal infeasibility,
# complementarity) ≤ KKT_TOL; the reference row keeps its default tol 1e-8.
IPOPT_KKT = {"tol": KKT_TOL, "dual_inf_tol": KKT_TOL, "constr_viol_tol": KKT_TOL, "compl_inf_tol": KKT_TOL}


def bench_peers(
    problems=PROBLEMS,
    integrators=INTEGRATORS,
    horizon: int = 50,
    knots: int = KNOTS,
    samples: int = 5,
    steps: int = 50,
    first_seed: int = FIRST_SEED,
    echo: bool = True,
) -> list[dict]:
    """The rows of both tables (see the module docstring) for every integrator × problem: ``samples`` seeded starts
    and goals from ``first_seed``, ``steps`` control steps each, horizon ``horizon``, ``knots`` knots (they divide
    the horizon: acados' coarse grid has equal intervals). Each row: problem, integrator, table, controller, grid,
    ready_s, and over the seeds step_ms, worst_ms (the worst seed's median), max_ms, iterations, cost_ratio and
    worst_ratio, fallbacks, path."""
    if isinstance(problems, str):
        raise TypeError(f"problems must be a list of problem specs, got the string {problems!r}")
    samples, steps = integer(samples, "samples", 1), integer(steps, "steps", 1)
    horizon, knots = integer(horizon, "horizon", 2), integer(knots, "knots", 2)
    first_seed = integer(first_seed, "first_seed", 0)
    if horizon % knots:
        raise ValueError(f"knots must divide the horizon for acados' coarse grid: {knots} does not divide {horizon}")
    problems, integrators = list(problems), tuple(integrators)
    args = (problems, integrators, horizon, knots, samples, steps, first_seed)
    skipped = {peer: why for peer, why in (("acados", acados_install.missing()), ("crocoddyl", _crocoddyl_missing()))}
    if echo:
        print(
            f"peers, like for like: {', '.join(problems)}; {'/'.join(integrators)}; T = {horizon}, {knots} knots; "
            f"{samples} seed{'s' if samples > 1 else ''} from {first_seed} x {steps} steps (n = {samples * steps} "
            f"steps a row); without joint damping and friction; load {load()}",
            flush=True,
        )
        for peer, why in skipped.items():
            if why:
                print(f"no {peer} rows: {why}", flush=True)
    t0 = time.perf_counter()
    runs = _runs(*args, peer=not skipped["crocoddyl"], echo=echo)
    if not skipped["acados"]:
        runs.update(acados_install.isolated(_acados_runs, *args, echo=echo))  # a process of its own (acados_install)
    rows = [_row(key, seen, runs[(key[0], key[1], "p = T", "ipopt")]) for key, seen in runs.items()]
    rows.sort(
        key=lambda r: (TABLES.index(r["table"]), integrators.index(r["integrator"]), problems.index(r["problem"]))
    )
    if echo:
        _print(rows, samples, steps)
        print(f"{time.perf_counter() - t0:.0f} s; load {load()}", flush=True)
    return rows


def _crocoddyl_missing() -> str | None:
    try:
        crocoddyl_peer.require()
    except ImportError as exc:
        return str(exc)
    return None


def _cases(prob, samples, first_seed):
    return [prob.sample(seed) for seed in range(first_seed, first_seed + samples)]


def _seeds(prob, ctrl, ocp, cases, steps, parts=("model", "build", "solve")) -> list[dict]:
    """One closed loop a seed: :func:`~ocpkit.benchmarks.closed_loop.closed_loop` of each case (RTI's iterations:
    its Gauss–Newton steps a control step; its Solution counts the QP's)."""
    from ocpkit.solvers.rti import RealTimeIteration

    seeds = [closed_loop(prob, ctrl, ocp, [case], steps * ocp.dt, parts) for case in cases]
    if isinstance(ctrl, RealTimeIteration):
        for seed in seeds:
            seed["iterations"] = float(ctrl.iterations)
    return seeds


def _ready(make, ocp, case):
    """(controller, seconds to construct it and wait for its C builds), then one untimed solve at ``case`` (a new
    controller's first step pays one-offs that are no solver's work: the thread limiter's scan of the loaded
    libraries, first calls into a library)."""
    t0 = time.perf_counter()
    ctrl = make(ocp)
    if hasattr(ctrl, "wait_compiled"):
        ctrl.wait_compiled()
    ready = time.perf_counter() - t0
    ctrl.solve(*case)
    ctrl.reset()
    return ctrl, ready


def _own(prob, knots, kind, ocp):
    """ocpkit's OCP for its RTI C step (compiled=True: also at p = T) beside ``ocp``: ``knots`` None is p = T."""
    return prob.ocp(knots=knots, horizon=ocp.horizon, integrator=ocp.integrator, parameterization=kind, compiled=True)


def _runs(problems, integrators, horizon, knots, samples, steps, first_seed, *, peer: bool, echo: bool) -> dict:
    """{(problem, integrator, table, controller): (grid, ready s, per-seed closed loops)} of IPOPT, ocpkit's RTI C
    step and, with ``peer``, Crocoddyl's FDDP (one iteration a step, and converged)."""
    rti = lambda ocp: solvers.controller("rti", ocp)  # noqa: E731
    runs = {}
    for integrator in integrators:
        for spec in problems:
            prob = crocoddyl_peer.undamped(spec)
            ocp = prob.ocp(knots=None, horizon=horizon, integrator=integrator)
            # (table, controller, grid, its OCP, its maker)
            rows = [
                ("p = T", "ipopt", f"N={horizon}", ocp, lambda o: solvers.controller("ipopt", o)),
                ("p = T", "ipopt 1e-6", f"N={horizon}", ocp, lambda o: solvers.make("ipopt", o, options=IPOPT_KKT)),
                ("p = T", "rti", f"N={horizon}", _own(prob, None, "linear", ocp), rti),
                ("p = T", "rti hpipm", f"N={horizon}", ocp, lambda o: solvers.controller("rti-hpipm", o)),
                ("knots", f"rti {knots} knots", f"p={knots}", _own(prob, knots, "linear", ocp), rti),
                ("knots", f"rti {knots} blocks", f"p={knots}", _own(prob, knots, "zoh", ocp), rti),
            ]
            if peer:
                fddp = crocoddyl_peer.CrocoddylMPC
                rows += [
                    ("p = T", "fddp 1 it", f"N={horizon}", ocp, lambda o: fddp(prob, o, max_iter=1, converge=False)),
                    ("p = T", "fddp", f"N={horizon}", ocp, lambda o: fddp(prob, o, th_stop=crocoddyl_peer.TH_STOP_KKT)),
                ]
            _progress(runs, rows, prob, ocp, samples, first_seed, steps, (spec, integrator), echo)
    return runs


def _progress(runs, rows, prob, ocp, samples, first_seed, steps, key, echo) -> None:
    """Run ``rows`` ((table, controller, grid, OCP, maker)) into ``runs`` and say how long they took."""
    t0 = time.perf_counter()
    cases = _cases(prob, samples, first_seed)
    for table, label, grid, own, make in rows:
        ctrl, ready = _ready(make, own, cases[0])
        runs[(*key, table, label)] = (grid, ready, _seeds(prob, ctrl, ocp, cases, steps))
    if echo:
        print(f"  {' '.join(key)}: {', '.join(r[1] for r in rows)} in {time.perf_counter() - t0:.0f} s", flush=True)


def _acados_runs(problems, integrators, horizon, knots, samples, steps, first_seed, *, echo: bool) -> dict:
    """:func:`_runs`' entries of acados: SQP-RTI at p = T and on the coarse grid, SQP converged at p = T (run in a
    process of its own)."""
    from ocpkit.benchmarks.acados_peer import AcadosMPC

    runs = {}
    for integrator in integrators:
        dynamics = "erk" if integrator == "rk4" else "discrete"
        for spec in problems:
            prob = crocoddyl_peer.undamped(spec)
            ocp = prob.ocp(knots=None, horizon=horizon, integrator=integrator)
            coarse = prob.ocp(knots=knots, horizon=horizon, integrator=integrator, parameterization="zoh")
            rti = lambda o: AcadosMPC(o, dynamics=dynamics)  # noqa: E731
            sqp = lambda o: AcadosMPC(o, dynamics=dynamics, nlp="sqp", tol=KKT_TOL)  # noqa: E731
            rows = [
                ("p = T", f"acados rti {dynamics}", f"N={horizon}", ocp, rti),
                ("p = T", "acados sqp", f"N={horizon}", ocp, sqp),
                ("knots", f"acados rti {dynamics}", f"N={knots}", coarse, rti),
            ]
            _progress(runs, rows, prob, ocp, samples, first_seed, steps, (spec, integrator), echo)
    return runs


def _row(key, run, reference) -> dict:
    """One table row of a controller's per-seed closed loops, its costs over the reference's (IPOPT's) seed by
    seed."""
    (spec, integrator, table, label), (grid, ready, seeds) = key, run
    medians = [s["step_ms"] for s in seeds]
    ratios = [s["cost"] / r["cost"] for s, r in zip(seeds, reference[2])]
    iterations = float(np.median([s["iterations"] for s in seeds]))
    return {
        "problem": spec,
        "integrator": integrator,
        "table": table,
        "controller": label,
        "grid": grid,
        "ready_s": ready,
        "step_ms": float(np.median(medians)),
        "worst_ms": float(max(medians)),
        "max_ms": float(max(s["max_ms"] for s in seeds)),
        "iterations": iterations,
        "iteration_ms": float(np.median(medians)) / max(iterations, 1.0),
        "cost_ratio": float(np.median(ratios)),
        "worst_ratio": float(max(ratios)),
        "fallbacks": sum(s["fallbacks"] for s in seeds),
        **{f"{part}_ms": float(np.median([s[f"{part}_ms"] for s in seeds])) for part in ("model", "build", "solve")},
        "path": seeds[0]["path"],
        "steps": sum(s["steps"] for s in seeds),
    }


def _print(rows, samples, steps) -> None:
    for table in TABLES:
        print(
            f"\n{table}: {samples} seed{'s' if samples > 1 else ''} x {steps} steps; step ms: median over seeds "
            f"[worst seed]; cost / IPOPT's (p = T) closed loop, median [worst]; load {load()}",
            flush=True,
        )
        print(
            f"{'problem':<10}{'integ':>6} {'controller':<20}{'grid':>5}{'ready s':>8}{'it':>4}{'step ms':>20}"
            f"{'max ms':>9}{'ms/it':>8}{'model/build/QP':>21}{'cost/ipopt':>22}{'fallbk':>7}  path"
        )
        for r in rows:
            if r["table"] != table:
                continue
            step = f"{r['step_ms']:.3f} [{r['worst_ms']:.3f}]"
            cost = f"{r['cost_ratio']:.4f} [{r['worst_ratio']:.4f}]"
            split = f"{r['model_ms']:.2f}/{r['build_ms']:.2f}/{r['solve_ms']:.2f}"
            print(
                f"{r['problem']:<10}{r['integrator']:>6} {r['controller']:<20}{r['grid']:>5}{r['ready_s']:>8.1f}"
                f"{r['iterations']:>4.0f}{step:>20}{r['max_ms']:>9.2f}{r['iteration_ms']:>8.3f}{split:>21}{cost:>22}"
                f"{r['fallbacks']:>7d}  {r['path']}",
                flush=True,
            )
