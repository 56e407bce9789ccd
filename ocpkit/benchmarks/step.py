"""`ocpkit bench step`: one whole MPC step (affine model + QP build + solve), ocpkit's condensed knots form
against the sparse traditional baselines (HPIPM, OSQP) and, when installed, the paper lab's affine_mpc and acados.

Every controller replays the same closed-loop state sequence (recorded once with ocpkit's condensed knots controller on
the OCP's discrete model) from a cold start, warm-starting from its own previous step as in a control loop. Each replay
runs one controller alone, as a real loop would (its data stay in cache); ``rounds`` rounds alternate the controllers in
rotated order, so all see the same machine load. affine_mpc gets the identical affine model (A_d, B_d, w_d) ocpkit
linearized at that state and is timed on its solve() alone. So is acados
(:class:`ocpkit.benchmarks.acados_peer.AcadosAffine`: SQP-RTI on that affine model, one iteration, i.e. its QP by
partial-condensing HPIPM), at p = T and on the coarse grid of the knots (N = p intervals of T/p steps, the input held
over each), timed on loading the model (its parameters at every stage), x and solving; it runs in a process of its
own (acados_install.isolated), its rounds after the others'.

The default row is LinearMPC as constructed without options, timed once its background builds have finished: for models
from nlink:5 up the whole step as compiled C (:mod:`ocpkit.export.native`), below it the Python step. The "Python step"
row keeps the Python step (``native=False``) with the default affine model (CasADi's VM until the background compile of
``ocpkit.codegen.compiled`` finishes, then compiled C); the "VM model" row the Python step on the VM throughout
(``compiled=False``). The floor estimate is build FLOPs / GEMM rate + the fastest QP solve + the compiled model.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager

import numpy as np

from ocpkit.benchmarks import acados_install
from ocpkit.problems import make
from ocpkit.solvers.qp import DEFAULT_QP, LinearMPC


BASE = "ocpkit condensed knots daqp (default)"  # the default QP of the condensed form, the default step
PYTHON = "ocpkit condensed knots daqp, Python step"
PROXQP = "ocpkit condensed knots proxqp"
VM = "ocpkit condensed knots daqp, VM model"
TRADITIONAL = "ocpkit sparse traditional hpipm"  # p = T: the OCP of acados' p = T row
# A step's parts (Solution.times) and the rest of its total: the Python around them (checks, ctypes, bookkeeping)
PARTS = ("model", "build", "solve", "rest")


def bench_step(
    links=(1, 2, 4, 7, 10, 13),
    horizons=(50, 100),
    knots=5,
    steps=20,
    rounds=5,
    seed=0,
    peers=True,
    busy=2,
    fresh=10.0,
    out=print,
) -> list[dict]:
    """Medians and spread (ms) of a whole step per configuration; ratios to ocpkit's condensed knots step.
    With ``busy`` > 0, then the nlink:13 T=100 step quiet and beside ``busy`` busy processes (:func:`bench_load`);
    with ``fresh`` > 0, the first ``fresh`` seconds of a closed loop after a fresh install (:func:`bench_fresh`)."""
    rows = []
    gemm = _gemm_rate()
    absent = acados_install.missing() if peers else None
    if absent:
        out(f"no acados rows: {absent}")
    for N in links:
        problem = make(f"nlink:{N}")
        for T in horizons:
            rows += _one(problem, T, knots, steps, seed, peers, rounds, acados=peers and absent is None)
    _print(rows, gemm, knots, out)
    if busy:
        bench_load(busy=busy, knots=knots, out=out)
    if fresh:
        bench_fresh(seconds=fresh, knots=knots, out=out)
    return rows


def bench_fresh(problem="nlink:13", horizon=100, knots=5, seconds=10.0, seed=0, out=print) -> dict:
    """The first ``seconds`` of a closed loop as after a fresh install (an empty cache: each run in its own process
    with its own new cache folder), on the default path (the Python step on the VM until the background compiles
    finish, then the C step) and on the VM path (``compiled=False``): step-time median and maximum per second."""
    runs = {}
    for label, compiled in (("default", None), ("VM (compiled=False)", False)):
        with tempfile.TemporaryDirectory(prefix="ocpkit-fresh-") as cache:
            code = (
                "import json, sys; from ocpkit.benchmarks.step import _closed_loop; "
                "print(json.dumps(_closed_loop(*json.loads(sys.argv[1]))))"
            )
            args = json.dumps([problem, horizon, knots, seconds, seed, compiled])
            proc = subprocess.run(
                [sys.executable, "-c", code, args],
                capture_output=True,
                text=True,
                env={**os.environ, "OCPKIT_CACHE_DIR": cache},
                check=True,
            )
            runs[label] = json.loads(proc.stdout.strip().splitlines()[-1])
    out(
        f"{problem} T={horizon} condensed knots({knots}), the first {seconds:g} s of a closed loop after a fresh "
        f"install (empty cache), step time median / max per second, ms:"
    )
    out(f"  {'second':>6}  " + "  ".join(f"{label:>24}" for label in runs) + "  default/VM (medians)")
    for k in range(int(np.ceil(seconds))):
        cells, medians = [], []
        for at, wall, path in (map(np.asarray, runs[label]) for label in runs):
            w = wall[(at >= k) & (at < k + 1)]
            medians.append(np.median(w) if w.size else np.nan)
            c_share = f" C {np.mean(path[(at >= k) & (at < k + 1)]):4.0%}" if w.size else ""
            cells.append(f"{1e3 * medians[-1]:7.3f} / {1e3 * w.max():7.3f}{c_share if path.any() else ''}")
        out(f"  {k:>6}  " + "  ".join(f"{c:>24}" for c in cells) + f"  {medians[0] / medians[1]:6.2f}")
    return runs


def _closed_loop(problem, horizon, knots, seconds, seed, compiled) -> tuple[list, list, list]:
    """(start of each step since the loop began (s), its wall time (s), whether it ran in C) over ``seconds`` of a
    closed loop of a newly constructed default LinearMPC on the OCP's discrete model."""
    prob = make(problem)
    ocp = prob.ocp(horizon=horizon, knots=knots, compiled=compiled)
    x, goal = prob.sample(seed)
    F = ocp.discrete()
    begin = time.perf_counter()
    ctrl = LinearMPC(ocp)
    at, wall, path = [], [], []
    while time.perf_counter() - begin < seconds:
        t0 = time.perf_counter()
        sol = ctrl.solve(x, goal)
        at.append(t0 - begin)
        wall.append(time.perf_counter() - t0)
        path.append(ctrl.native)
        x = np.asarray(F(x, sol.u)).ravel()
    return at, wall, path


@contextmanager
def busy_processes(count: int):
    """``count`` processes spinning on a CPU each for the duration of the block (a loaded machine)."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(count)]
    try:
        time.sleep(0.2)  # let them reach the CPU
        yield procs
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()


def load_medians(problem="nlink:13", horizon=100, knots=5, steps=30, busy=2, seed=0, seconds=2.0) -> dict:
    """Median whole-step time (s) of the condensed knots controller quiet and beside ``busy`` busy processes,
    with BLAS/OpenMP limited to 1 thread (the default) and unlimited (threads=None): {(threads, "quiet"|"loaded"): s}.

    The same replayed closed-loop states every time; each controller is calibrated by one untimed replay, then
    replays them for at least ``seconds`` per condition (a few replays last a fraction of a scheduler period,
    too short to see the load)."""
    prob = make(problem)
    ocp = prob.ocp(horizon=horizon, knots=knots)
    x, goal = prob.sample(seed)
    F, ref, xs = ocp.discrete(), LinearMPC(ocp), []
    for _ in range(steps):
        xs.append(x)
        x = np.asarray(F(x, ref.solve(x, goal).u)).ravel()
    ctrls = {1: LinearMPC(ocp), None: LinearMPC(ocp, threads=None)}
    for ctrl in ctrls.values():
        ctrl.wait_compiled()  # the default step once built (the C step from nlink:5 up)

    def replay(ctrl):
        ctrl.reset()
        return [ctrl.solve(x, goal).times["total"] for x in xs]

    for ctrl in ctrls.values():
        replay(ctrl)
    out = {}
    for label in ("quiet", "loaded"):
        with busy_processes(busy if label == "loaded" else 0):
            for threads, ctrl in ctrls.items():
                walls, end = [], time.perf_counter() + seconds
                while time.perf_counter() < end:
                    walls += replay(ctrl)
                out[(threads, label)] = float(np.median(walls))
    return out


def bench_load(problem="nlink:13", horizon=100, knots=5, steps=30, busy=2, out=print) -> dict:
    """Print the step's median quiet and under load (:func:`load_medians`) and the loaded/quiet ratio."""
    med = load_medians(problem, horizon, knots, steps, busy)
    out(
        f"{problem} T={horizon} condensed knots({knots}) {DEFAULT_QP['condensed']} (the default), median whole step, "
        f"quiet vs {busy} busy processes:"
    )
    for threads in (1, None):
        q, l = med[(threads, "quiet")], med[(threads, "loaded")]
        name = "BLAS threads 1 (default)" if threads == 1 else "BLAS threads unlimited"
        out(f"  {name:26} quiet {1e3 * q:8.3f} ms   loaded {1e3 * l:8.3f} ms   loaded/quiet {l / q:6.2f}")
    return med


def _acados(spec, T, p, xs, goal, models, rounds) -> dict:
    """{row name: (step times (s), statuses, QP iterations, u_0 of each replayed step)} of acados' QP
    (AcadosAffine) at p = T and on the coarse grid: ``rounds`` replays each, alternating (run in a process of its
    own)."""
    from ocpkit.benchmarks.acados_peer import AcadosAffine

    problem = make(spec)
    grids = {
        "acados p=T hpipm (SQP-RTI: its QP)": problem.ocp(horizon=T, knots=None),
        f"acados coarse grid N={p} hpipm (SQP-RTI)": problem.ocp(horizon=T, knots=p, parameterization="zoh"),
    }
    solvers = {name: AcadosAffine(ocp) for name, ocp in grids.items()}
    seen = {name: ([], set(), [], [None] * len(xs)) for name in solvers}
    for r in range(rounds):
        for name, qp in _rotated(solvers, r):
            times, status, iterations, u0 = seen[name]
            for k, (x, model) in enumerate(zip(xs, models)):
                t0 = time.perf_counter()
                u, code, its = qp.step(x, goal, model)
                times.append(time.perf_counter() - t0)
                status.add("success" if code == 0 else f"acados status {code}")
                iterations.append(its)
                u0[k] = u
    return seen


def _one(problem, T, p, steps, seed, peers, rounds, acados=False):
    ocp_k, ocp_t = problem.ocp(horizon=T, knots=p), problem.ocp(horizon=T)
    x, goal = problem.sample(seed)
    F = ocp_k.discrete()
    ref = LinearMPC(ocp_k)
    xs = []
    for _ in range(steps):  # the replayed closed loop
        xs.append(x)
        x = np.asarray(F(x, ref.solve(x, goal).u)).ravel()
    # What affine_mpc and acados are given at each step: copies (affine_model returns views of reused buffers, so
    # every step's w_d had been the last step's)
    models = [tuple(np.array(M) for M in ref.affine_model(x, goal, "goal")) for x in xs]
    ocp_vm = problem.ocp(horizon=T, knots=p, compiled=False)  # CasADi's SX virtual machine throughout
    ctrls = {
        BASE: LinearMPC(ocp_k),
        PYTHON: LinearMPC(ocp_k, native=False),
        PROXQP: LinearMPC(ocp_k, form="condensed", qp="proxqp"),
        VM: LinearMPC(ocp_vm, form="condensed", qp="daqp"),
        TRADITIONAL: LinearMPC(ocp_t, form="sparse", qp="hpipm"),
        "ocpkit sparse traditional osqp": LinearMPC(ocp_t, form="sparse", qp="osqp"),
    }
    for name in (BASE, PYTHON):  # the default step once built (cached: once per OCP); the Python step's model
        ctrls[name].wait_compiled()  # after its background compile (cached by hash: once per model)
    peer = _peers(ocp_k, goal, models[0]) if peers else {}
    times = {name: [] for name in [*ctrls, *peer]}
    parts = {name: {k: [] for k in PARTS} for name in ctrls if name.startswith("ocpkit condensed")}
    u0, u0_t = [None] * steps, [None] * steps  # the default's and the traditional (p = T) QP's first inputs
    agree, status = {name: 0.0 for name in peer}, {name: set() for name in times}
    iterations = {name: [] for name in peer}
    for r in range(rounds):
        for name, ctrl in _rotated(ctrls, r):
            ctrl.reset()
            for k, x in enumerate(xs):
                sol = ctrl.solve(x, goal)
                times[name].append(sol.times["total"])
                status[name].add(sol.status)
                if name == BASE:
                    u0[k] = sol.u
                elif name == TRADITIONAL:
                    u0_t[k] = sol.u
                t = sol.times
                for part, values in parts.get(name, {}).items():
                    values.append(t["total"] - t["model"] - t["build"] - t["solve"] if part == "rest" else t[part])
        for name, mpc in _rotated(peer, r):
            mpc.resetWarmStart()
            for k, (x, model) in enumerate(zip(xs, models)):
                A, B = np.asfortranarray(model[0]), np.asfortranarray(model[1])
                t0 = time.perf_counter()
                mpc.setModelDiscrete(A, B, model[2])
                st = mpc.solve(x)
                times[name].append(time.perf_counter() - t0)
                status[name].add(str(st).rsplit(".", 1)[-1])
                iterations[name].append(mpc.getSolveInfo().iterations)
                agree[name] = max(agree[name], float(np.abs(mpc.getNextInput() - u0[k]).max()))
                if not mpc.isWithinSparsityPattern():  # outside the timing: it scans every entry
                    status[name].add("model entries dropped")
    if acados:
        found = acados_install.isolated(_acados, problem.name, T, p, xs, goal, models, rounds)
        for name, (t, st, its, u) in found.items():  # u0 against the same OCP's at p = T, else the default's
            times[name], status[name], iterations[name] = t, st, its
            ours = u0_t if "p=T" in name else u0
            agree[name] = max(float(np.abs(a - b).max()) for a, b in zip(u, ours))
    flops = ctrls[BASE].transcription.build_flops()
    base = float(np.median(times[BASE]))
    out = []
    for name, t in times.items():
        t = np.asarray(t)
        row = {
            "problem": problem.name,
            "horizon": T,
            "solver": name,
            "median": float(np.median(t)),
            "p25": float(np.percentile(t, 25)),
            "p75": float(np.percentile(t, 75)),
            "ratio": float(np.median(t)) / base,
            "status": ",".join(sorted(status[name])),
            "u0_diff": agree.get(name),
            "iterations": float(np.median(iterations[name])) if name in iterations else None,
        }
        if name in parts:
            row.update(
                {part: float(np.median(v)) for part, v in parts[name].items()},
                flops=flops,
                step="C" if ctrls[name].native else "Python",
            )
        out.append(row)
    return out


def _rotated(items: dict, r: int) -> list:
    """The (name, item) pairs starting at the r-th: each round times the controllers in another order."""
    pairs = list(items.items())
    return pairs[r % len(pairs) :] + pairs[: r % len(pairs)] if pairs else []


def _peers(ocp, goal, model) -> dict:
    """affine_mpc CondensedMPC and SparseMPC on the same OCP (diagonal weights, knot bounds), if installed.

    affine_mpc fixes its QP sparsity at initializeSolver and silently drops later model entries outside that
    pattern (an identity/zero set-up model loses all of B; the rest state's A_d at nlink:7 has 91 exact zeros that
    later states fill, which left SparseMPC's u0 3.0 off). So it is set up with a real affine model whose exact
    zeros are made tiny (1e-12): every entry is in the pattern; the replay then checks isWithinSparsityPattern.
    """
    try:
        import affine_mpc as ampc
    except ImportError:
        return {}
    n, m, T, p = ocp.nx, ocp.nu, ocp.horizon, ocp.knots
    mpcs = {}
    for form, cls in (("CondensedMPC", ampc.CondensedMPC), ("SparseMPC", ampc.SparseMPC)):
        for accuracy in ("its defaults", "eps 1e-9"):
            mpc = cls(n, m, ampc.Parameterization.linearInterp(T, p), ampc.Options(use_input_cost=True))
            full = [np.asfortranarray(np.where(M == 0.0, 1e-12, M)) for M in model[:2]]
            mpc.setModelDiscrete(*full, model[2])
            mpc.setInputLimits(ocp.u_min, ocp.u_max)
            mpc.setWeights(np.diag(ocp.Q).copy(), np.diag(ocp.Q_terminal).copy(), np.diag(ocp.R).copy())
            mpc.setReferenceState(goal)
            mpc.setReferenceInput(ocp.input_goal(goal))
            # Its recommended OSQP settings (eps 1e-6, 4000 iterations), and ocpkit's accuracy (1e-9). affine_mpc
            # weighs R on the control points, ocpkit on every step's input: with knots u0 differs slightly (0.05 at
            # nlink:7, T=100, p=5, over the replayed loop); traditional MPC agrees to 3e-8 (measured).
            settings = ampc.OSQPSettings()
            if accuracy != "its defaults":
                settings.eps_abs = settings.eps_rel = 1e-9
                settings.max_iter = 100_000
            if mpc.initializeSolver(settings):
                mpcs[f"affine_mpc {form} (OSQP, {accuracy})"] = mpc
    return mpcs


def _gemm_rate(size=1000, repeats=5) -> float:
    """Dense GEMM rate of one core (GFLOP/s, numpy's BLAS on 1 thread as in a step, best of ``repeats``)."""
    from threadpoolctl import threadpool_limits

    a, b = np.random.default_rng(0).normal(size=(2, size, size))
    with threadpool_limits(1):
        best = min(_timed(lambda: a @ b) for _ in range(repeats))
    return 2 * size**3 / best / 1e9


def _timed(f) -> float:
    t0 = time.perf_counter()
    f()
    return time.perf_counter() - t0


def _print(rows, gemm, knots, out):
    out(
        f"Whole MPC step (affine model + build + solve), ms: median [p25, p75]; ratio = median / ocpkit condensed "
        f"knots({knots}); u0 = max |u0 − ocpkit's u0| over the replayed steps (acados p=T: − ocpkit's sparse "
        f"traditional u0, the same OCP); it = median QP iterations. affine_mpc and acados rows time setting the model "
        f"and solving, given ocpkit's affine model (its linearization is not counted)."
    )
    out(f"Dense GEMM (1000³, numpy BLAS) in this run: {gemm:.1f} GFLOP/s")
    out(
        f"{'problem':10} {'T':>4} {'solver':46} {'median':>9} {'p25':>9} {'p75':>9} {'ratio':>8} {'u0':>9} "
        f"{'it':>6}  status"
    )
    for r in rows:
        u0 = "" if r["u0_diff"] is None else f"{r['u0_diff']:9.1e}"
        it = "" if r["iterations"] is None else f"{r['iterations']:6.0f}"
        out(
            f"{r['problem']:10} {r['horizon']:>4} {r['solver']:46} {1e3 * r['median']:9.3f} {1e3 * r['p25']:9.3f} "
            f"{1e3 * r['p75']:9.3f} {r['ratio']:8.2f} {u0:>9} {it:>6}  {r['status']}"
        )
    out(
        "ocpkit condensed knots, medians (ms) of the parts and the build's rate (C: the compiled C step, timed in C; "
        "Python: the Python step, its model compiled after its background compile; vm: compiled=False; rest: the "
        "whole step less the three, the Python around them):"
    )
    parts = {(r["problem"], r["horizon"], r["solver"]): r for r in rows if "flops" in r}
    for (name, T, solver), r in parts.items():
        gf = r["flops"] / r["build"] / 1e9
        shortest = min(t for (nm, t, sv) in parts if nm == name and sv == solver)
        ratio = (
            ""
            if T == shortest
            else f"  solve(T={T})/solve(T={shortest}) = {r['solve'] / parts[(name, shortest, solver)]['solve']:.2f}"
        )
        tag = (
            solver.removeprefix("ocpkit condensed knots ")
            .replace(", VM model", " vm")
            .replace(", Python step", "")
            .replace(" (default)", "")
        ) + f" {r['step']}"
        rate = (
            "by doubling, fewer FLOPs"
            if r["step"] == "C"
            else f"{r['flops'] / 1e6:.2f} MFLOP, {gf:.1f} GFLOP/s = {100 * gf / gemm:.0f}% of GEMM"
        )
        out(
            f"  {name:10} T={T:<4} {tag:13} model {1e3 * r['model']:.3f}  build {1e3 * r['build']:.3f} ({rate})  "
            f"solve {1e3 * r['solve']:.3f}  rest {1e3 * r['rest']:.3f}{ratio}"
        )
    out("Floor estimate = build FLOPs / GEMM rate + fastest QP solve + compiled model; fraction = floor / best step:")
    for name, T in dict.fromkeys((nm, t) for nm, t, _ in parts):
        mine = [r for (nm, t, _), r in parts.items() if (nm, t) == (name, T)]
        compiled = [r for r in mine if r["solver"] != VM] or mine
        build, solve, model = (
            mine[0]["flops"] / (gemm * 1e9),
            min(r["solve"] for r in mine),
            min(r["model"] for r in compiled),
        )
        floor = build + solve + model
        best = min(mine, key=lambda r: r["median"])
        out(
            f"  {name:10} T={T:<4} floor {1e3 * floor:.3f} ms (build {1e3 * build:.3f} + QP {1e3 * solve:.3f} + "
            f"model {1e3 * model:.3f}); best step {1e3 * best['median']:.3f} ms "
            f"({best['solver'].removeprefix('ocpkit condensed knots ')}): floor = {100 * floor / best['median']:.0f}%"
        )
