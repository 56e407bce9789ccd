"""`ocpkit build`: what a controller of a problem loads from the cache (its C step, compiled models, Taichi
kernels) built into the cache ahead of its first run."""

from __future__ import annotations

import time
from pathlib import Path

from ocpkit import problems
from ocpkit.cli.commands import make_controller
from ocpkit.cli.options import make_ocp, solver_options


def build_command(args):
    """`ocpkit build`: what the default LinearMPC of the problem's OCP loads from the cache — its C step and the
    compiled affine model of its Python step — built into the cache unless there (and loading), paths printed; with
    another solver or options, :func:`_prebuild_controller`."""
    from ocpkit.codegen import compiled
    from ocpkit.export import native
    from ocpkit.codegen.cache import cache_root
    from ocpkit.model.ocp import BACKGROUND_MIN_INSTRUCTIONS
    from ocpkit.solvers.qp import LinearMPC

    print(f"cache: {cache_root()} (set OCPKIT_CACHE_DIR to fill another)")
    if args.solver != "qp" or solver_options(args):
        return _prebuild_controller(args)
    problem = problems.make(args.problem)
    ocp = make_ocp(problem, args, error=args.error, compiled=args.compiled)
    size = ocp.model.jacobian.n_instructions()
    start = time.time()
    if native.wanted(ocp):
        LinearMPC(ocp, native=True)  # builds the C step here and now (or finds it), and loads it
        for folder in native.built(ocp):
            library = folder / f"lib{native.NAME}.so"
            print(f"C step (LinearMPC: condensed, daqp, linearization goal): {library} ({_how(library, start)})")
    else:
        pairs = ocp.task_functions.pairs if ocp.task_functions is not None else 0
        why = (
            "a linear model"
            if ocp.model.linear
            else f"a model of {size} VM instructions, below {BACKGROUND_MIN_INSTRUCTIONS}"
            if size < BACKGROUND_MIN_INSTRUCTIONS
            else "obstacles, constants of the generated C (a build per placement: --compiled builds it)"
            if pairs
            else f"a knot QP of {ocp.knots * ocp.nu} variables, over ocpkit.export.native.MAX_VARIABLES = "
            f"{native.MAX_VARIABLES}"
        )
        print(f"C step: none (the default LinearMPC keeps its Python step here: {why})")
    if size >= BACKGROUND_MIN_INSTRUCTIONS:
        start = time.time()
        library = compiled.prebuild(ocp.model.affine(ocp.dt, ocp.substeps, ocp.integrator))
        print(f"compiled affine model (the Python step's): {library} ({_how(library, start)})")
    else:
        print(
            f"compiled affine model: none (a model of {size} VM instructions, below {BACKGROUND_MIN_INSTRUCTIONS}, "
            f"stays on CasADi's VM)"
        )
    return 0


def _prebuild_controller(args):
    """`ocpkit build --solver …`: the controller as `simulate` constructs it, one step from the seeded start (a
    Taichi kernel compiles at its first launch, into the cache) and its background builds waited for."""
    start = time.perf_counter()
    problem, ocp, ctrl = make_controller(args)
    x0, goal = problem.sample(args.seed)
    sol = ctrl.solve(x0, goal)
    ctrl.wait_compiled()
    print(
        f"{ctrl!r}: first step {sol.status} by {sol.path}; ready in {time.perf_counter() - start:.1f} s, now "
        f"answering by {ctrl.path}"
    )
    return 0


def _how(library: Path, start: float) -> str:
    return "built now" if library.stat().st_mtime >= start - 0.05 else "already in the cache"
