"""`ocpkit export`: generate and build the C MPC step, then check it against the same step in Python on a closed
loop (the round trip)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from ocpkit import problems
from ocpkit.cli.commands import said_if_slow, seeded_start
from ocpkit.cli.options import make_ocp
from ocpkit.cli.task import reach_ocp, reach_task

EXAMPLE_STEPS = 100  # the example's closed loop (export's steps)


def export_command(args):
    from ocpkit.export import BuildError, build, check_tools, export

    try:
        check_tools()  # before any work: a missing cc or make is one line
        task = reach_task(args)
        problem = problems.make(args.problem)
        ocp = make_ocp(problem, args) if task is None else reach_ocp(problem, args, task)
        x0, goal = seeded_start(problem, ocp, args.seed, task)
        reference = _reference(ocp, args.reference_window)
        with said_if_slow(f"generating the C step of {args.problem} (CasADi code generation)"):
            exported = export(
                ocp,
                args.out,
                form=args.form,
                qp=args.qp,
                linearization=args.linearization,
                x0=x0,
                force=args.force,
                iterations=args.iterations,
                goal=None if reference is not None else goal,
                reference=reference,
                steps=EXAMPLE_STEPS,
            )
        with said_if_slow(f"building the C step in {args.out} (make: {_build_estimate(exported.out_dir)})"):
            build(args.out)
    except BuildError as exc:
        print(f"ocpkit: error: {exc}", file=sys.stderr)
        return 2
    with said_if_slow("round trip: the compiled step and the Python step on the same closed loop"):
        du, steps, failures, along = _round_trip(problem, ocp, args, exported, (x0, goal), reference)
    ok = failures == 0 and du <= 1e-6
    print(
        f"exported and built {args.problem} ({args.form}, {ocp.parameterization.kind} with {ocp.knots} knots over "
        f"T = {ocp.horizon}, {args.qp}, linearization {args.linearization}) in {exported.out_dir}; "
        f"see {Path(args.out) / 'README.md'}\nround trip: the compiled step vs the same step in Python over {steps} "
        f"closed-loop steps from seed {args.seed}{along}: max |du| = {du:.2e}, {failures} non-successes — "
        f"{'agree' if ok else 'DISAGREE'}"
    )
    return 0 if ok else 1


def _build_estimate(folder) -> str:
    """How long ``make`` may take on the generated C in ``folder``: about 1 s per 150 kB on one core (measured on
    nlink:7's 225 kB: 1.3 s with two jobs, the folder's default)."""
    size = sum(path.stat().st_size for path in Path(folder).glob("*.c"))
    return f"{size / 1e3:.0f} kB of C, about {max(1, round(size / 150e3))} s the first time"


def _reference(ocp, path):
    """The goal rows of the example's steps and their windows, (steps + T + 1, ng), of the reference file ``path``
    (``--reference-window``: a CSV or NPZ file as :meth:`ocpkit.model.reference.Reference.load` reads it); None
    without one."""
    if path is None:
        return None
    from ocpkit.model.reference import Reference

    return Reference.load(path, ocp).window(0.0, ocp.dt, EXAMPLE_STEPS + ocp.horizon)


def _round_trip(problem, ocp, args, exported, start, reference=None, steps: int = 20):
    """The compiled step (through ctypes) and LinearMPC in Python on the same closed loop from ``start`` (x0, goal;
    the discrete model, driven by LinearMPC's input): their largest first-input difference, the steps where either
    failed, and the words for what the loop followed. With ``reference`` (its rows) each step's goal is its window
    where LinearMPC takes one, else its row: the C step's window step or its held step."""
    from ocpkit.export import ExportedMPC
    from ocpkit.model.problem import check_dynamics
    from ocpkit.solvers.rti import RealTimeIteration
    from ocpkit.solvers.qp import LinearMPC

    c = ExportedMPC(ocp, exported.out_dir, name=exported.name)
    if exported.linearization == "trajectory":
        py = RealTimeIteration(ocp, iterations=args.iterations, eps=1e-10, native=False)
    else:
        py = LinearMPC(ocp, form="condensed", eps=1e-10, linearization=exported.linearization, native=False)
    F = ocp.discrete()
    x, goal = start
    du, failures = 0.0, 0
    preview = reference is not None and "goal window" in type(py).TAKES
    for k in range(steps):
        if reference is not None:
            goal = reference[k : k + ocp.horizon + 1] if preview else reference[k]
        a, b = py.solve(x, goal), c.solve(x, goal)
        failures += (not a.ok) + (not b.ok)
        du = max(du, float(np.abs(a.u - b.u).max()))
        x_next = np.asarray(F(x, a.u)).ravel()
        if not np.isfinite(x_next).all():  # NaN dynamics are named as such (DynamicsError), else the step diverged
            check_dynamics(
                ocp.model,
                x,
                a.u,
                dt=ocp.dt,
                substeps=ocp.substeps,
                context=f"the round trip's closed loop, step {k + 1}",
            )
            raise ValueError(
                f"the round trip's closed loop diverged at step {k + 1}: the discrete model "
                f"from x = {x.tolist()}, u = {a.u.tolist()} is not finite"
            )
        x = x_next
    along = "" if reference is None else f" along {args.reference_window}"
    if reference is not None and not preview:
        along += f" (its present value each step: {type(py).__name__} takes no goal window yet)"
    return du, steps, failures, along
