"""`ocpkit bench startup`: the time from "new controller" to its first good step, for every solver.

Each run is a fresh Python process (:func:`_worker`) that imports ocpkit, builds the problem's OCP (the command line's
knots, :data:`ocpkit.solvers.methods.KNOTS`, the problem's horizon), constructs one controller and steps it in closed
loop on the OCP's discrete model from a seeded start. It reports, in seconds from the constructor call: the first
returned solution, the first verified ``success`` (and the step and path that gave it), and the steady state
(``wait_compiled``: the C step or compiled model loaded, the Taichi kernel compiled), then the median step there.
Each configuration runs twice in a new cache folder of its own (``OCPKIT_CACHE_DIR``, Taichi's kernels included):
empty, then warm (what the first run left).

The split says where the start-up went, each part timed around the library call that does it: ``import``
(ocpkit, its problems and solvers), ``symbolic`` (the problem and its OCP in CasADi), ``setup`` (the constructor,
less the parts below), ``codegen`` (C code generation of the C step), ``translate`` (CasADi → Taichi functions),
``taichi`` (Taichi's AST transform and compile of each kernel, at its first launch), ``C build`` (a C compile the
loop waited for), and ``first step`` (the rest of the steps before the first success). Background builds (the C
step, the compiled model) do not hold the loop up: they show in the steady-state column.
"""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from ocpkit.solvers import BENCHMARKED
from ocpkit.solvers.methods import KNOTS

PROBLEMS = ("nlink:13", "puma560", "panda")  # panda: a 7-DoF arm read from its URDF
CONTROLLERS = BENCHMARKED["startup"]  # the default rows: names of ocpkit.solvers.CONTROLLERS, and "exported"
PARTS = ("import", "symbolic", "setup", "codegen", "translate", "taichi", "C build", "first step")
INNER = ("codegen", "translate", "taichi", "C build")  # timed inside the constructor or the first steps
MAX_STEPS = 200  # steps tried for a first success
STEADY_STEPS = 20


def bench_startup(
    problems=PROBLEMS, controllers=CONTROLLERS, timeout: float = 900.0, seed: int = 0, out=print
) -> list[dict]:
    """Every controller on every problem, empty cache then warm, each in a fresh process; prints a table per
    problem and returns its rows."""
    from ocpkit import solvers
    from ocpkit.benchmarks.nlp import _load

    known = (*solvers.CONTROLLERS, "exported")
    unknown = [c for c in controllers if c not in known]
    if unknown:
        raise ValueError(f"controllers must be among {', '.join(known)}, got {', '.join(unknown)}")
    out(f"start-up, fresh process per run, {KNOTS} knots; machine load {_load()}", flush=True)
    rows = []
    for problem in problems:
        out(f"\n{problem}: seconds from the constructor call (import before it); steady step in ms", flush=True)
        out(
            f"  {'controller':14} {'cache':5} {'import':>6} {'first':>7} {'success':>7} {'at step':>7} "
            f"{'steady':>7} {'step ms':>8}  {'path at first success':28} split (s)",
            flush=True,
        )
        for name in controllers:
            with tempfile.TemporaryDirectory(prefix="ocpkit-startup-") as cache:
                for state in ("empty", "warm"):
                    row = {
                        "problem": problem,
                        "controller": name,
                        "cache": state,
                        **_run(problem, name, cache, timeout, seed),
                    }
                    rows.append(row)
                    out(_format(row), flush=True)
    out(f"\nmachine load {_load()}")
    return rows


def _run(problem: str, controller: str, cache: str, timeout: float, seed: int) -> dict:
    """One fresh process: its measurements, or what stopped it."""
    env = {k: v for k, v in os.environ.items() if k != "TI_OFFLINE_CACHE_FILE_PATH"}
    env["OCPKIT_CACHE_DIR"] = cache
    code = (
        "import time; t = time.perf_counter(); import ocpkit; from ocpkit.benchmarks.startup import _worker; "
        "import sys; _worker(t, *sys.argv[1:])"
    )
    try:
        # cwd away from any checkout: `python -c` puts the cwd first on sys.path, and a checkout's ocpkit/ has no
        # problems/ (that only exists as ocpkit.problems once installed).
        proc = subprocess.run(
            [sys.executable, "-c", code, problem, controller, str(seed)],
            env=env,
            cwd=cache,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
    except subprocess.TimeoutExpired:
        return {"error": f"no first success within {timeout:g} s"}
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode or not lines:
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return {"error": f"exit {proc.returncode}: {tail}"}
    return json.loads(lines[-1])


def _format(row: dict) -> str:
    head = f"  {row['controller']:14} {row['cache']:5}"
    if "error" in row:
        return f"{head} {row['error']}"
    split = " ".join(f"{k} {v:.2f}" for k, v in row["split"].items() if v >= 0.005)
    success = row["success"]
    return (
        f"{head} {row['import']:6.2f} {row['first']:7.2f} {_s(success):>7} {row['success_step']!s:>7} "
        f"{_s(row['steady']):>7} {_ms(row['step']):>8}  {row['path']:28} {split}"
    )


def _s(value) -> str:
    return "-" if value is None else f"{value:.2f}"


def _ms(value) -> str:
    return "-" if value is None else f"{1e3 * value:.3f}"


def _make(name: str, ocp):
    """The controller ``name`` (of :data:`ocpkit.solvers.CONTROLLERS`, or "exported") on ``ocp``, as a user constructs
    it."""
    from ocpkit import solvers

    if name == "exported":
        from ocpkit.export import ExportedMPC, build, export

        folder = tempfile.mkdtemp(prefix="ocpkit-startup-export-")
        export(ocp, folder)
        build(folder)
        return ExportedMPC(ocp, folder)
    return solvers.controller(name, ocp)


def _timed(split: dict, part: str, owner, attribute: str, first_only: bool = False) -> None:
    """Wrap ``owner.attribute`` so that its wall time adds to ``split[part]`` (``first_only``: per instance, its first
    call only — a Taichi kernel compiles at its first launch)."""
    original = getattr(owner, attribute)
    seen = set()

    @functools.wraps(original)
    def wrapper(*args, **kwargs):
        if first_only:
            if id(args[0]) in seen:
                return original(*args, **kwargs)
            seen.add(id(args[0]))
        start = time.perf_counter()
        try:
            return original(*args, **kwargs)
        finally:
            split[part] += time.perf_counter() - start

    setattr(owner, attribute, wrapper)


def _instrument(split: dict) -> None:
    """Time the start-up's parts where the library does them (see the module docstring)."""
    from taichi.lang import kernel_impl

    from ocpkit import export
    from ocpkit.codegen import compiled
    from ocpkit.export import native
    from ocpkit.codegen.kernels import rollout, translate

    _timed(split, "codegen", native, "export")
    _timed(split, "codegen", export, "export")
    _timed(split, "C build", export, "build")
    _timed(split, "C build", compiled, "compile_function")
    _timed(split, "translate", rollout, "translate")
    _timed(split, "translate", translate, "translate")
    _timed(split, "taichi", kernel_impl.Kernel, "__call__", first_only=True)


def _worker(t_import: float, problem: str, controller: str, seed: str) -> None:
    """The measurements of one fresh process as one JSON line (see :func:`bench_startup`)."""
    from ocpkit import problems, solvers  # noqa: F401 - part of what a user imports

    split = dict.fromkeys(PARTS, 0.0)
    split["import"] = time.perf_counter() - t_import
    _instrument(split)

    def inner() -> float:
        return sum(split[k] for k in INNER)

    t0 = time.perf_counter()
    prob = problems.make(problem)
    ocp = prob.ocp(knots=KNOTS)
    F = ocp.discrete()
    split["symbolic"] = time.perf_counter() - t0
    t0, before = time.perf_counter(), inner()
    ctrl = _make(controller, ocp)
    split["setup"] = time.perf_counter() - t0 - (inner() - before)
    x, goal = prob.sample(int(seed))
    first = success = step = None
    path = ""
    loop_start, before = time.perf_counter(), inner()
    for k in range(MAX_STEPS):
        sol = ctrl.solve(x, goal)
        now = time.perf_counter() - t0
        first = now if first is None else first
        if sol.ok:
            success, step, path = now, k, sol.path
            break
        x = np.asarray(F(x, sol.u), dtype=float).ravel()
    split["first step"] = time.perf_counter() - loop_start - (inner() - before)
    ctrl.wait_compiled()
    steady = time.perf_counter() - t0
    times = []
    for _ in range(STEADY_STEPS):
        sol = ctrl.solve(x, goal)
        times.append(sol.times["total"])
        x = np.asarray(F(x, sol.u), dtype=float).ravel()
    print(
        json.dumps(
            {
                "import": split.pop("import"),
                "first": first,
                "success": success,
                "success_step": step,
                "path": path or "none",
                "steady": steady,
                "steady_path": sol.path,
                "step": float(np.median(times)),
                "split": split,
            }
        ),
        flush=True,
    )
