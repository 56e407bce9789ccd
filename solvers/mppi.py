"""MPPI: model predictive path integral control (Williams et al., cited in the paper) over the knots.

Each generation perturbs the nominal knots with Gaussian noise (clipped to the input bounds), rolls
the population out and moves the nominal to the exponentially weighted average Σ_i w_i U_i with
w_i ∝ exp(−(J_i − min J)/λ). The preconditioned variant (default) draws the noise with covariance
σ²P⁻¹ from the knot QP's Hessian and evaluates the seeds in every population
(:mod:`ocpkit.solvers.sampling`); "paper" uses N(0, σ²) per parameter. The nominal carries over to the
next control step shifted one step in time (preconditioned: unless a seed rolls out better, which then
starts the step); u is its input at t = 0.

Constraint domination, in both variants: where some candidates are feasible (clear of the obstacles, within the
state bounds; :func:`ocpkit.solvers.sampling.excess`), only they are weighted, min J taken over them; otherwise all
are, by their penalized cost. The plan returned is the nominal unless the best candidate
(:func:`ocpkit.solvers.sampling.best_first`) dominates it (:meth:`GaussianSampling._final`): an average of plans
that pass a ball on either side can hit it.
"""

# No "from __future__ import annotations": Taichi reads kernel annotations as types.
import numpy as np
import taichi as ti

from ocpkit._checks import positive
from ocpkit.codegen.kernels import runtime
from ocpkit.solvers.methods import MPPI
from ocpkit.solvers.gaussian import GaussianSampling
from ocpkit.solvers.sampling import excess


class MPPI(GaussianSampling):
    """MPPI with ``population`` samples, noise ``sigma`` (see :class:`GaussianSampling`) and temperature
    ``temperature`` λ (in the cost's units)."""

    def __init__(
        self,
        ocp,
        *,
        population: int = MPPI["population"].default,
        sigma=None,
        temperature: float = MPPI["temperature"].default,
        generations: int = MPPI["generations"].default,
        **options,
    ):
        super().__init__(ocp, population=population, generations=generations, sigma=sigma, **options)
        self.temperature = positive(temperature, "temperature")
        eng = self.engine
        self._weighted_average = runtime.shared(
            ("weighted average", eng.ftype, eng.num_knots, eng.nu, eng.arch),
            lambda: _weighted_average(eng.ftype, eng.num_knots, eng.nu, runtime.serial_transfers()),
        )

    def _start(self, x, goal, cold):
        self.nominal = self._start_distribution(getattr(self, "nominal", None), cold)

    def _generation(self, cold):
        self._sample(self.nominal)
        cost = np.nan_to_num(self._results[:, 0].astype(np.float64), nan=np.inf)
        feasible = excess(self._results) == 0
        if feasible.any():
            cost = np.where(feasible, cost, np.inf)
        self._best_index = int(self._ranked(1)[0])
        low = cost.min()
        if np.isfinite(low):
            w = np.exp(-(cost - low) / self.temperature)
            self.nominal = np.empty((self.ocp.knots, self.ocp.nu))
            self._launch(self._weighted_average, w / w.sum(), self.engine.knots, self.nominal)
        return self._outcome(self._best_index)

    def _result(self, best):
        self.nominal, best = self._final(self.nominal, best, self._best_index)
        return self.nominal, best


def _weighted_average(F, p, m, serial):
    """Σ_i w_i U_i over the population's knots."""

    @ti.kernel
    def weighted_average(weights: ti.types.ndarray(), knots: ti.types.ndarray(), out: ti.types.ndarray()):
        ti.loop_config(serialize=serial)
        for j, a in ti.ndrange(p, m):
            s = ti.cast(0.0, F)
            for i in range(knots.shape[0]):
                s += ti.cast(weights[i], F) * knots[i, j, a]
            out[j, a] = s

    return weighted_average


SOLVERS = {"mppi": MPPI}
