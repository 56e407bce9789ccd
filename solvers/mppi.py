"""MPPI: model predictive path integral control (Williams et al., cited in the paper) over the knots.

Each generation perturbs the nominal knots with N(0, σ²) noise (clipped to the input bounds),
rolls the population out and moves the nominal to the exponentially weighted average
Σ_i w_i U_i with w_i ∝ exp(−(J_i − min J)/λ). The nominal carries over to the next control step
shifted one step in time; u is its input at t = 0.
"""
# No "from __future__ import annotations": Taichi reads kernel annotations as types.
import numpy as np
import taichi as ti

from ocpkit._checks import positive
from ocpkit.solvers.sampling import GaussianSampling


class MPPI(GaussianSampling):
    """MPPI with ``population`` samples, noise ``sigma`` (scalar or per input; default 10% of each
    input's range) and temperature ``temperature`` λ (in the cost's units)."""

    def __init__(self, ocp, *, population: int = 1024, sigma=None, temperature: float = 1.0,
                 generations: int = 1, **options):
        super().__init__(ocp, population=population, generations=generations, sigma=sigma,
                         **options)
        self.temperature = positive(temperature, "temperature")
        eng = self.engine
        N, p, m = eng.num_sims, eng.num_knots, eng.nu
        knots = eng.knots
        weights = self._weights = ti.field(eng.ftype, shape=N)
        average = self._average = ti.field(eng.ftype, shape=(p, m))

        @ti.kernel
        def weighted_average():
            for j, a in ti.ndrange(p, m):
                s = ti.cast(0.0, eng.ftype)
                for i in range(N):
                    s += weights[i] * knots[i, j, a]
                average[j, a] = s

        self._weighted_average = weighted_average

    def _start(self, x, goal, cold):
        ocp = self.ocp
        if cold:
            self.nominal = np.tile(np.clip(ocp.input_goal(goal), ocp.u_min, ocp.u_max), (ocp.knots, 1))
        else:
            self.nominal = self._shifted(self.nominal)
        self.std = np.tile(self.sigma, (ocp.knots, 1))

    def _generation(self, cold):
        self._sample(self.nominal, self.std)
        cost = np.nan_to_num(self.engine.cost.to_numpy().astype(np.float64), nan=np.inf)
        best = cost.min()
        if not np.isfinite(best):
            return best
        w = np.exp(-(cost - best) / self.temperature)
        self._weights.from_numpy((w / w.sum()).astype(self.engine.ntype))
        self._weighted_average()
        self.nominal = self._average.to_numpy().astype(np.float64)
        return float(best)

    def _result(self):
        return self.nominal


SOLVERS = {"mppi": MPPI}
