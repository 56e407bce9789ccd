"""`ocpkit bench empc`: EMPC's control step by part, generation time and rollouts per second versus links,
population, horizon and variant (the paper's Section "Comparing Evolutionary, Parameterized Convex
Solver, and Traditional MPC", solve-time figures)."""

from __future__ import annotations

import time

import numpy as np

from ocpkit import problems
from ocpkit.codegen.kernels import runtime
from ocpkit.solvers.sampling import VARIANTS

LINKS = (1, 2, 4, 7, 10, 13)
POPULATIONS = (256, 1024, 4096, 16384)
HORIZONS = (50, 100)
PARTS = ("model", "build", "factor", "seed", "copies", "generations")


def bench_empc(
    links=LINKS,
    populations=POPULATIONS,
    horizons=HORIZONS,
    *,
    variants=VARIANTS,
    generations: int = 1,
    knots: int = 3,
    steps: int = 20,
    arch: str = "auto",
    precision: str = "float64",
    seed: int = 0,
    out=print,
) -> list[dict]:
    """Time EvolutionaryMPC on nlink:L for every (links, horizon, population, variant); returns the rows.

    Each configuration is compiled and warmed up by one solve, then solved ``steps`` times from
    one sampled state (warm-started, as in closed loop). Reported medians: the step's parts
    (``model`` linearization, the preconditioner's ``build``, ``factor`` and ``seed`` (Newton and
    holding candidates), host↔device ``copies``, the ``generations``' kernel launches), ``generation`` =
    generations time / generations, ``rollouts/s``, ``step`` (the whole control step) and ``step_cpu``, the
    process's CPU time in it (all threads: with ``OCPKIT_CPU_THREADS=1`` the step an idle machine would take
    where other processes share the cores).
    """
    from ocpkit.solvers.empc import EvolutionaryMPC

    device = runtime.init(arch)
    rows = []
    out(_header(device, precision))
    for L in links:
        problem = problems.make(f"nlink:{L}")
        x0, goal = problem.sample(seed)
        for T in horizons:
            ocp = problem.ocp(knots=knots, horizon=T)
            for N in populations:
                for variant in variants:
                    ctrl = EvolutionaryMPC(
                        ocp,
                        population=N,
                        num_parents=min(16, N // 2),
                        variant=variant,
                        generations=generations,
                        precision=precision,
                        arch=arch,
                        seed=seed,
                    )
                    ctrl.solve(x0, goal)  # compile and cold start
                    sols, cpu = [], []
                    for _ in range(steps):
                        start = time.process_time()
                        sols.append(ctrl.solve(x0, goal))
                        cpu.append(time.process_time() - start)
                    row = {part: float(np.median([s.times[part] for s in sols])) for part in PARTS}
                    row.update(
                        links=L,
                        horizon=T,
                        population=N,
                        variant=variant,
                        num_generations=generations,
                        generation=row["generations"] / generations,
                        rollouts_per_s=N * generations / row["generations"],
                        step=float(np.median([s.times["total"] for s in sols])),
                        step_cpu=float(np.median(cpu)),
                        arch=device,
                        precision=precision,
                    )
                    rows.append(row)
                    out(_row(row))
    return rows


def _header(device, precision):
    return (
        f"EMPC on nlink:L, arch {device}, {precision}; medians, times in ms\n"
        f"{'links':>5} {'T':>4} {'population':>10} {'variant':>14} "
        + " ".join(f"{p:>11}" for p in PARTS)
        + f" {'generation':>10} {'rollouts/s':>10} {'step':>8} {'step cpu':>8}"
    )


def _row(r):
    return (
        f"{r['links']:>5} {r['horizon']:>4} {r['population']:>10} {r['variant']:>14} "
        + " ".join(f"{1e3 * r[p]:>11.3f}" for p in PARTS)
        + f" {1e3 * r['generation']:>10.3f} {r['rollouts_per_s']:>10.3g}"
        + f" {1e3 * r['step']:>8.3f} {1e3 * r['step_cpu']:>8.3f}"
    )
