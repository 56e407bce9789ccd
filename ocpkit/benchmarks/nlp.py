"""Nonlinear MPC side by side: IPOPT, fatrop, real-time iteration (1 and 3 SQP steps) and LinearMPC (LTI, LTV),
the controllers of :data:`ocpkit.solvers.CONTROLLERS` by name ("ipopt", "fatrop", "rti", "rti3", "qp", "ltv").

For each problem and seeded start/goal every controller runs its own closed loop on the plant (the same
starts, goals and duration); the table gives each one's time to its steady state (construction plus the
background builds it waits for: C steps, compiled models), its median step time (model + build + solve, ms) and
that median's split into the model's sensitivities, the QP's build (condensing) and the QP solve, its
closed-loop actual cost (ocpkit.sim.metrics.actual_cost) as a ratio to IPOPT's (converged to its default tol
1e-8), its fallbacks and its final error max |x_T − x_goal|. All controllers use the same OCP (knots,
horizon); IPOPT is the reference solution of the nonlinear problem, so a ratio below 1 is luck of the
closed loop, not a better optimizer.

The tutorial's cart-pole (examples/cartpole.py, "Declare your own problem": x = [p, θ, ṗ, θ̇], θ = 0 upright; the
spec :func:`example_cartpole`, a default problem when the package runs from its source tree) is run as a swing-up:
from hanging, θ = π, to the sampled goal. It is told by its spec, not its name: the shipped problem "cartpole" (θ = 0
hanging) runs as any other problem.

The peer "crocoddyl" (Crocoddyl's FDDP, :mod:`ocpkit.benchmarks.crocoddyl_peer`; ``pip install "ocpkit[peers]"``)
is a controller column when asked for. It solves traditional MPC (p = T) on the same horizon, and its dynamics
have no joint damping or friction, so with it every problem of the run, for every controller and the plant, is
made without them; problems it cannot model (no pinocchio model, servo inputs) run without its row. After the
closed-loop table it prints its per-solve comparison (:func:`ocpkit.benchmarks.crocoddyl_compare.compare`).
Both peers side by side on the same OCPs, one iteration a step and converged, p = T and knots in tables of their own
(issue 48's must-show): ``ocpkit bench peers`` (:mod:`ocpkit.benchmarks.peers`).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ocpkit import problems as registry
from ocpkit import solvers
from ocpkit._checks import integer
from ocpkit.benchmarks import acados_compare, acados_install, crocoddyl_compare, crocoddyl_peer
from ocpkit.benchmarks.closed_loop import closed_loop
from ocpkit.benchmarks.closed_loop import load as _load  # startup.py reads it here
from ocpkit.solvers.methods import KNOTS

ROBOTS = ("nlink:3", "nlink:7", "puma560", "baxter")
CONTROLLERS = solvers.BENCHMARKED["nlp"]  # the default columns, names of solvers.CONTROLLERS
PEERS = ("crocoddyl", "acados")  # other libraries' controllers, run only when asked for
# Warm steps of the peers' per-solve comparison at most (IPOPT at p = T takes a second a solve on the Puma).
PER_SOLVE_STEPS = 10


def example_cartpole() -> str | None:
    """The tutorial's cart-pole, examples/cartpole.py, as a problem spec, or None outside the source tree."""
    path = Path(__file__).resolve().parents[2] / "examples" / "cartpole.py"
    return f"{path}:CartPole" if path.exists() else None


def is_example_cartpole(spec: str) -> bool:
    """Whether the problem spec ``spec`` is the tutorial's cart-pole (:func:`example_cartpole`), run as a swing-up."""
    example = example_cartpole()
    return example is not None and spec == example


def with_example_cartpole(names) -> list[str]:
    """``names`` and, from the source tree, the tutorial's cart-pole (:func:`example_cartpole`) after them."""
    cartpole = example_cartpole()
    return list(names) + ([cartpole] if cartpole else [])


def default_problems() -> list[str]:
    known = set(registry.names())
    return with_example_cartpole(name for name in ROBOTS if name.partition(":")[0] in known)


def controller(kind: str, ocp, problem=None):
    """A controller of :data:`ocpkit.solvers.CONTROLLERS` or PEERS for ``ocp`` (the peer "crocoddyl" and a
    controller for traditional MPC only, such as "rti-hpipm": on ``problem``'s p = T OCP of that horizon)."""
    traditional = kind == "crocoddyl" or getattr(solvers.CONTROLLERS.get(kind), "knots", None) == "horizon"
    if traditional and problem is not None and ocp.knots != ocp.horizon:
        ocp = problem.ocp(knots=None, horizon=ocp.horizon, integrator=ocp.integrator)
    if kind == "crocoddyl":
        return crocoddyl_peer.CrocoddylMPC(problem, ocp)
    return solvers.controller(kind, ocp)


def bench_nlp(
    problems=None,
    knots: int | None = KNOTS,
    horizon: int | None = 50,
    samples: int = 3,
    steps: int = 50,
    *,
    controllers=CONTROLLERS,
    compiled: bool = False,
    integrator: str | None = None,
    first_seed: int = 0,
    echo: bool = True,
) -> list[dict]:
    """Median step time (ms), closed-loop actual-cost ratio to IPOPT, fallbacks and final error of every
    controller in ``controllers`` (names of :data:`ocpkit.solvers.CONTROLLERS`; default CONTROLLERS), one row per
    problem × controller.

    ``knots`` None is traditional MPC (p = T); ``horizon`` None is the problem's own. The cart-pole swing-up
    keeps its own horizon (1 s, 100 steps: half of it cannot see the pole come up) with 10 knots, and runs
    for the problem's duration plus one second. ``samples`` seeded start/goal pairs (seeds ``first_seed``, …) run
    ``steps`` control steps. ``integrator`` is every controller's prediction
    (:data:`ocpkit.model.dynamics.INTEGRATORS`, None: "rk4"); the plant is RK4 whatever it is, so the costs of two
    runs compare across integrators.

    ``compiled`` evaluates the affine model as compiled C (RTI's and LTV's T per-stage models, LinearMPC's one):
    the one-off compile (cached) is done before any controller runs and printed, never counted in a step.
    Without "ipopt" in ``controllers`` (to time the others alone) the cost ratio is NaN.
    "crocoddyl" (PEERS) adds Crocoddyl's FDDP, p = T, on the problems without damping and friction (see the module
    docstring), then its per-solve table over ``samples`` seeds and min(``steps``, PER_SOLVE_STEPS) MPC steps;
    the rows returned are the closed-loop table's.
    "acados" (PEERS) runs the other controllers' table (if any), then the like-for-like tables of
    :func:`ocpkit.benchmarks.acados_compare.compare` (p = T and knots, acados' SQP-RTI beside ocpkit's RTI C step
    and IPOPT) on ``problems`` (None: its Puma 560, Panda and nlink:13) with ``knots`` (None: KNOTS) and
    ``integrator`` (None: RK4 and Euler), and returns both tables' rows.
    """
    if isinstance(problems, str):
        raise TypeError(f"problems must be a list of problem names, got the string {problems!r}")
    names = default_problems() if problems is None else list(problems)
    samples, steps = integer(samples, "samples", 1), integer(steps, "steps", 1)
    first_seed = integer(first_seed, "first_seed", 0)
    controllers = tuple(controllers)
    known = tuple(solvers.CONTROLLERS) + PEERS
    unknown = [c for c in controllers if c not in known]
    if unknown or not controllers:
        raise ValueError(f"controllers must be among {known}, got {controllers}")
    if "acados" in controllers:
        reason = acados_install.missing()
        if reason:
            raise ImportError(reason)
        others = tuple(c for c in controllers if c != "acados")
        options = {"horizon": horizon, "samples": samples, "steps": steps, "first_seed": first_seed, "echo": echo}
        rows = []
        if others:
            rows = bench_nlp(problems, knots, controllers=others, compiled=compiled, integrator=integrator, **options)
        return rows + acados_install.isolated(  # acados in a process of its own (acados_install's docstring)
            acados_compare.compare,
            acados_compare.PROBLEMS if problems is None else problems,
            knots=KNOTS if knots is None else knots,
            integrators=acados_compare.INTEGRATORS if integrator is None else (integrator,),
            **options,
        )
    integrator = integrator or "rk4"
    peer = "crocoddyl" in controllers
    if peer:
        crocoddyl_peer.require()
        if echo:
            print(
                "crocoddyl: every problem runs without joint damping and friction (Crocoddyl's free dynamics have "
                "none); its rows are traditional MPC (knots T)",
                flush=True,
            )
    rows, compared = [], []
    if echo:
        print(f"integrator {integrator}; {samples} seeds from {first_seed}; machine load {_load()}", flush=True)
        print(
            f"{'problem':<22}{'knots':>6}{'T':>5} {'controller':<10}{'ready s':>8}{'step ms':>9}{'p90 ms':>8}"
            f"{'model':>8}{'build':>8}{'QP':>9}{'cost/ipopt':>11}{'fallbk':>7}{'final err':>10}",
            flush=True,
        )
    for name in names:
        prob = crocoddyl_peer.undamped(name) if peer else registry.make(name)
        swing = is_example_cartpole(name)
        p, T = (10, None) if swing else (knots, horizon)
        ocp = prob.ocp(knots=p, horizon=T, integrator=integrator, **({"compiled": True} if compiled else {}))
        if compiled:
            t0 = time.perf_counter()
            ocp.affine()  # compiled (or loaded from the cache) once, outside every timed step
            if echo:
                print(f"{name}: compiled affine model ready in {time.perf_counter() - t0:.1f} s", flush=True)
        duration = (prob.duration + 1.0) if swing else steps * ocp.dt
        cases = []
        for seed in range(first_seed, first_seed + samples):
            x0, goal = prob.sample(seed)
            if swing:
                x0 = np.r_[x0[0], np.pi + x0[1], x0[2:]]
            cases.append((x0, goal))
        results = {}
        for kind in controllers:
            t0 = time.perf_counter()
            try:
                ctrl = controller(kind, ocp, prob)
            except ValueError as exc:
                if kind not in PEERS:
                    raise
                if echo:
                    print(f"{name}: no {kind} row: {exc}", flush=True)
                continue
            if hasattr(ctrl, "wait_compiled"):  # the steady state: C step or compiled model loaded
                ctrl.wait_compiled()
            build = time.perf_counter() - t0
            own = ctrl.ocp
            results[kind] = {
                "problem": prob.name if swing else name,
                "knots": "T" if own.knots == own.horizon else own.knots,
                "horizon": own.horizon,
                "controller": kind,
                "build_s": build,
                "swing_up": swing,
                "integrator": own.integrator,
                **closed_loop(prob, ctrl, ocp, cases, duration),
            }
        if peer and "crocoddyl" in results:
            compared.append(name)
        for kind in results:
            row = results[kind]
            row["cost_ratio"] = row["cost"] / results["ipopt"]["cost"] if "ipopt" in results else float("nan")
            rows.append(row)
            if echo:
                label = "cartpole swing-up" if swing else name
                print(
                    f"{label:<22}{row['knots']!s:>6}{row['horizon']:>5} {kind:<10}{row['build_s']:>8.2f}"
                    f"{row['step_ms']:>9.3f}{row['p90_ms']:>8.3f}{row['model_ms']:>8.3f}{row['build_ms']:>8.3f}"
                    f"{row['solve_ms']:>9.3f}{row['cost_ratio']:>11.4f}{row['fallbacks']:>7d}"
                    f"{row['final_error']:>10.4f}",
                    flush=True,
                )
    if echo:
        print(f"machine load {_load()}", flush=True)
    if compared and echo:  # a printed table: without echo nobody would see it
        crocoddyl_compare.compare(
            compared, horizon=horizon, knots=knots, seeds=samples, steps=max(2, min(steps, PER_SOLVE_STEPS)), echo=echo
        )
    return rows
