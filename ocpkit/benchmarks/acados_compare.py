"""acados' SQP-RTI beside ocpkit's RTI and IPOPT in closed loop, like for like (the peer:
:mod:`ocpkit.benchmarks.acados_peer`): the tables ``ocpkit bench nlp --controller acados`` prints.

Two tables a problem and integrator, never mixed:

* p = T (traditional MPC, a node every step): IPOPT (the reference: NonlinearMPC converged), ocpkit's RTI (one
  Gauss–Newton step a control step: its default, the condensed QP's C step, and the sparse QP by ProxQP beside
  it), acados' SQP-RTI (N = T, partial-condensing
  HPIPM; RK4 as acados' ERK, semi-implicit Euler as DISCRETE dynamics of ocpkit's step) and acados' SQP converged
  to SQP_TOL (a converged solve each step, as IPOPT's).
* knots (the same freedom, p inputs over the horizon): ocpkit's RTI on its ``knots``-knot piecewise-linear OCP and on
  the zero-order hold of p blocks, and acados on the coarse grid (N = p intervals of T/p integrator steps, the
  input held over each), the nearest analogue acados has.

Every row runs its own closed loops on the plant (RK4, the same seeded starts and goals, as ``ocpkit bench nlp``);
its cost is the closed-loop actual cost over IPOPT's at p = T with the same integrator. Times: the median step
(``Solution.times["total"]``, what the control loop waits for, ms), its 90th percentile, the medians of its parts
(model: the sensitivities, build: the QP's, or acados' set-up from Python, solve: the QP, or acados' call and
reading its plan) and for acados its own ``time_tot`` (sensitivities and QP together). "ready s" is the
construction (acados: generation and compilation, cached after the first time) and C builds waited for.

No row solves with ``qp="hpipm"``: CasADi's HPIPM plugin crashes (segmentation fault, whichever is loaded first)
in a process that has loaded acados' own HPIPM and BLASFEO libraries.
"""

from __future__ import annotations

import time


from ocpkit import problems as registry
from ocpkit import solvers
from ocpkit._checks import integer
from ocpkit.benchmarks.acados_install import require
from ocpkit.benchmarks.acados_peer import AcadosMPC
from ocpkit.benchmarks.closed_loop import closed_loop, load

PROBLEMS = ("puma560", "panda", "nlink:13")
INTEGRATORS = ("rk4", "euler")
# The converged rows' tolerance: every KKT residual of acados' SQP (IPOPT: its default tol 1e-8).
SQP_TOL = 1e-6


def compare(
    problems=PROBLEMS,
    horizon: int | None = 50,
    knots: int = 5,
    samples: int = 3,
    steps: int = 50,
    integrators=INTEGRATORS,
    first_seed: int = 0,
    echo: bool = True,
) -> list[dict]:
    """The rows of the two tables (see the module docstring) for every problem × integrator: ``samples`` seeded
    starts and goals from ``first_seed``, ``steps`` control steps each, horizon T = ``horizon`` (None: the
    problem's own), ``knots`` knots (they must divide T: acados' coarse grid has equal intervals)."""
    require()
    samples, steps, knots = integer(samples, "samples", 1), integer(steps, "steps", 1), integer(knots, "knots", 2)
    if isinstance(problems, str):
        raise TypeError(f"problems must be a list of problem specs, got the string {problems!r}")
    rows = []
    for integrator in integrators:
        for spec in problems:
            rows += _problem(spec, integrator, horizon, knots, samples, steps, first_seed, echo)
    if echo:
        print(f"machine load {load()}", flush=True)
    return rows


def _problem(spec, integrator, horizon, knots, samples, steps, first_seed, echo) -> list[dict]:
    prob = registry.make(spec)
    horizon = prob.horizon if horizon is None else integer(horizon, "horizon", 2)
    if horizon % knots:
        raise ValueError(f"knots must divide the horizon for acados' coarse grid: {knots} does not divide {horizon}")
    ocps = {
        "T": prob.ocp(knots=None, horizon=horizon, integrator=integrator),
        "blocks": prob.ocp(knots=knots, horizon=horizon, integrator=integrator, parameterization="zoh"),
    }
    for name, p, kind in (("rti T", None, "linear"), ("rti linear", knots, "linear"), ("rti zoh", knots, "zoh")):
        # ocpkit's RTI as its C step (compiled=True: also at p = T, beyond the knot QPs the default compiles)
        ocps[name] = prob.ocp(knots=p, horizon=horizon, integrator=integrator, parameterization=kind, compiled=True)
    dynamics = "erk" if integrator == "rk4" else "discrete"
    # (table, row label, OCP, controller maker)
    runs = [
        ("p = T", "ipopt", "T", lambda ocp: solvers.controller("ipopt", ocp)),
        ("p = T", "rti", "rti T", lambda ocp: solvers.controller("rti", ocp)),
        ("p = T", "rti sparse", "rti T", lambda ocp: solvers.make("rti", ocp, form="sparse")),
        ("p = T", f"acados {dynamics}", "T", lambda ocp: AcadosMPC(ocp, dynamics=dynamics)),
        ("p = T", "acados sqp", "T", lambda ocp: AcadosMPC(ocp, dynamics=dynamics, nlp="sqp", tol=SQP_TOL)),
        ("knots", "rti linear", "rti linear", lambda ocp: solvers.controller("rti", ocp)),
        ("knots", "rti zoh", "rti zoh", lambda ocp: solvers.controller("rti", ocp)),
        ("knots", f"acados {dynamics}", "blocks", lambda ocp: AcadosMPC(ocp, dynamics=dynamics)),
    ]
    cases = [prob.sample(seed) for seed in range(first_seed, first_seed + samples)]
    rows = []
    for table, label, which, make in runs:
        ocp = ocps[which]
        t0 = time.perf_counter()
        ctrl = make(ocp)
        if hasattr(ctrl, "wait_compiled"):  # the steady state: C step or compiled model loaded
            ctrl.wait_compiled()
        ready = time.perf_counter() - t0
        parts = ("model", "build", "solve") + (("acados",) if isinstance(ctrl, AcadosMPC) else ())
        run = closed_loop(prob, ctrl, ocps["T"], cases, steps * ocp.dt, parts)
        grid = f"N={ctrl.intervals}" if isinstance(ctrl, AcadosMPC) else f"p={ocp.knots}"
        rows.append(
            {
                "problem": spec,
                "integrator": integrator,
                "table": table,
                "controller": label,
                "grid": grid,
                "horizon": horizon,
                "ready_s": ready,
                **run,
            }
        )
    reference = rows[0]["cost"]
    for row in rows:
        row["cost_ratio"] = row["cost"] / reference
    if echo:
        _print(spec, integrator, rows, samples, steps)
    return rows


def _print(spec, integrator, rows, samples, steps) -> None:
    for table in ("p = T", "knots"):
        print(
            f"\n{spec}, {integrator}, {table}: T = {rows[0]['horizon']}; {samples} seed{'s' if samples > 1 else ''} "
            f"x {steps} steps; cost / IPOPT's (p = T) closed loop; load {load()}",
            flush=True,
        )
        print(
            f"{'controller':<16}{'grid':>6}{'ready s':>9}{'step ms':>9}{'p90 ms':>8}{'model':>8}{'build':>8}"
            f"{'solve':>8}{'acados ms':>10}{'cost/ipopt':>11}{'fallbk':>7}  path"
        )
        for row in rows:
            if row["table"] != table:
                continue
            own = f"{row['acados_ms']:.3f}" if "acados_ms" in row else "-"
            print(
                f"{row['controller']:<16}{row['grid']:>6}{row['ready_s']:>9.1f}{row['step_ms']:>9.3f}"
                f"{row['p90_ms']:>8.3f}{row['model_ms']:>8.3f}{row['build_ms']:>8.3f}{row['solve_ms']:>8.3f}{own:>10}"
                f"{row['cost_ratio']:>11.4f}{row['fallbacks']:>7d}  {row['path']}",
                flush=True,
            )
