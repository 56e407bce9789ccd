"""`ocpkit bench empc`: EMPC generation time, rollouts per second and control-step time versus
links, population and horizon (the paper's Section "Comparing Evolutionary, Parameterized Convex
Solver, and Traditional MPC", solve-time figures)."""
from __future__ import annotations

import numpy as np

from ocpkit import problems
from ocpkit.kernels import runtime

LINKS = (1, 2, 4, 7, 10, 13)
POPULATIONS = (256, 1024, 4096, 16384)
HORIZONS = (50, 100)


def bench_empc(links=LINKS, populations=POPULATIONS, horizons=HORIZONS, *, generations: int = 1,
               knots: int = 3, steps: int = 20, arch: str = "auto", precision: str = "float64",
               seed: int = 0, out=print) -> list[dict]:
    """Time EvolutionaryMPC on nlink:L for every (links, horizon, population); returns the rows.

    Each configuration is compiled and warmed up by one solve, then solved ``steps`` times from
    one sampled state (warm-started, as in closed loop). Reported medians: ``generation`` =
    solve time / generations (kernel launches and host↔device copies included), ``rollouts/s``,
    ``solve`` (the optimizer, copies included) and ``step`` (solve plus the host linearization).
    """
    from ocpkit.solvers.empc import EvolutionaryMPC

    device = runtime.init(arch)
    rows = []
    for L in links:
        problem = problems.make(f"nlink:{L}")
        x0, goal = problem.sample(seed)
        for T in horizons:
            ocp = problem.ocp(knots=knots, horizon=T)
            for N in populations:
                ctrl = EvolutionaryMPC(ocp, population=N, num_parents=min(16, N // 2),
                                       generations=generations, precision=precision, arch=arch,
                                       seed=seed)
                ctrl.solve(x0, goal)  # compile and cold start
                sols = [ctrl.solve(x0, goal) for _ in range(steps)]
                solve = float(np.median([s.times["solve"] for s in sols]))
                rows.append({"links": L, "horizon": T, "population": N, "generations": generations,
                             "generation": solve / generations, "rollouts_per_s": N * generations / solve,
                             "solve": solve, "step": float(np.median([s.times["total"] for s in sols])),
                             "arch": device, "precision": precision})
                out(_row(rows[-1]) if len(rows) > 1 else _header(device, precision) + "\n" + _row(rows[-1]))
    return rows


def _header(device, precision):
    return (f"EMPC on nlink:L, arch {device}, {precision}; medians, times in ms\n"
            f"{'links':>5} {'T':>4} {'population':>10} {'generation':>10} {'rollouts/s':>12} "
            f"{'solve':>8} {'step':>8}")


def _row(r):
    return (f"{r['links']:>5} {r['horizon']:>4} {r['population']:>10} {1e3 * r['generation']:>10.3f} "
            f"{r['rollouts_per_s']:>12.3g} {1e3 * r['solve']:>8.3f} {1e3 * r['step']:>8.3f}")
