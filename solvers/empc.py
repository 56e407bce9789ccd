"""EvolutionaryMPC: the paper's EMPC (Section "Evolutionary MPC", Algorithm 1) on a Taichi kernel.

Per generation, in one kernel launch, every candidate is bred and rolled out:
cold start draws each knot uniformly within the input bounds; warm start keeps the
``num_parents`` best knot sets (elitism: they survive unchanged) and fills the rest of the
population with children of two parents drawn uniformly, each parameter inherited from either
parent with probability ½, then each input mutated with probability ½ by adding N(0, σ) to its
knots, clipped to the bounds. The parents carry over to the next control step shifted one step
in time. u is the best parent's input at t = 0. Following the paper's conclusion, σ may shrink
with the distance to the goal so that EMPC holds the system near it.
"""
# No "from __future__ import annotations": Taichi reads kernel annotations as types.
import numpy as np
import taichi as ti

from ocpkit._checks import integer, positive
from ocpkit.kernels.random import normal, uniform
from ocpkit.solvers.sampling import SamplingMPC


class EvolutionaryMPC(SamplingMPC):
    """Algorithm 1 with ``population`` (numSims), ``num_parents``, ``sigma`` (σ_noise: a scalar
    or one per input; default 10% of each input's range) and ``generations`` per control step.

    ``shrink_distance`` d: when set, σ_eff = σ_min + (σ − σ_min)·min(1, ‖x − x_goal‖ / d), with
    ``sigma_min`` (default σ/10). See :class:`ocpkit.solvers.sampling.SamplingMPC` for
    ``dynamics``, ``stage_cost``/``terminal_cost``, ``precision``, ``arch`` and ``seed``.
    """

    def __init__(self, ocp, *, population: int = 1024, num_parents: int = 16, sigma=None,
                 generations: int = 1, shrink_distance: float | None = None, sigma_min=None,
                 **options):
        population = integer(population, "population", 2)
        self.num_parents = integer(num_parents, "num_parents", 1)
        if self.num_parents >= population:
            raise ValueError(f"num_parents must be < population ({population}), got {num_parents}")
        super().__init__(ocp, population=population, generations=generations,
                         num_picked=self.num_parents, sigma=sigma, **options)
        self.shrink_distance = None if shrink_distance is None else positive(shrink_distance,
                                                                              "shrink_distance")
        self.sigma_min = self.sigma / 10 if sigma_min is None else np.broadcast_to(
            np.asarray(sigma_min, dtype=float), self.sigma.shape).copy()
        if not (np.isfinite(self.sigma_min).all() and (self.sigma_min >= 0).all()
                and (self.sigma_min <= self.sigma).all()):
            raise ValueError(f"sigma_min must be finite with 0 <= sigma_min <= sigma "
                             f"({self.sigma.tolist()}), got {self.sigma_min.tolist()}")
        self._sigma = ti.field(self.engine.ftype, shape=(2, ocp.nu))  # σ and σ_min
        self._sigma.from_numpy(np.stack([self.sigma, self.sigma_min]).astype(self.engine.ntype))
        self._generation_kernel = self._build_kernel()

    def _build_kernel(self):
        eng = self.engine
        F = eng.ftype
        N, p, m, k = eng.num_sims, eng.num_knots, eng.nu, self.num_parents
        knots, parents, rollout = eng.knots, eng.picked, eng.rollout
        lo, hi, sigma = self._u_min, self._u_max, self._sigma
        S = self._shift.tolist()
        # Random slots per candidate: parents, then a mutation flag per input, then a
        # crossover coin and a noise draw per parameter.
        MUTATE, CROSS, NOISE = 2, 2 + m, 2 + m + p * m

        @ti.func
        def parent(r, j: ti.template(), a: ti.template(), shift):
            """Knot j, input a of parent r; with ``shift``, of the parent advanced one control
            step (U⁺ = S U, clipped): the warm start from the previous step's parents."""
            v = parents[r, j, a]
            if shift:
                v = ti.cast(0.0, F)
                for l in ti.static(range(p)):
                    if ti.static(S[j][l] != 0.0):
                        v += S[j][l] * parents[r, l, a]
                v = ti.min(ti.max(v, lo[a]), hi[a])
            return v

        @ti.kernel
        def generation(key: ti.u32, counter: ti.u32, cold: ti.i32, shift: ti.i32, scale: F,
                       out: ti.types.ndarray()):
            for i in range(N):
                if cold:
                    for j, a in ti.static(ti.ndrange(p, m)):
                        r = ti.cast(uniform(key, counter, i, CROSS + j * m + a), F)
                        knots[i, j, a] = lo[a] + (hi[a] - lo[a]) * r
                elif i < k:
                    for j, a in ti.static(ti.ndrange(p, m)):
                        knots[i, j, a] = parent(i, j, a, shift)
                else:
                    p1 = ti.min(ti.cast(uniform(key, counter, i, 0) * k, ti.i32), k - 1)
                    p2 = ti.min(ti.cast(uniform(key, counter, i, 1) * k, ti.i32), k - 1)
                    for a in ti.static(range(m)):
                        mutate = uniform(key, counter, i, MUTATE + a) < 0.5
                        noise = sigma[1, a] + (sigma[0, a] - sigma[1, a]) * scale
                        for j in ti.static(range(p)):
                            slot = j * m + a
                            v = parent(p1, j, a, shift)
                            if uniform(key, counter, i, CROSS + slot) < 0.5:
                                v = parent(p2, j, a, shift)
                            if mutate:
                                v += noise * ti.cast(normal(key, counter, i, NOISE + slot), F)
                            knots[i, j, a] = ti.min(ti.max(v, lo[a]), hi[a])
                out[i] = rollout(i)

        return generation

    def reset(self):
        super().reset()
        self._shift_parents = False

    def _start(self, x, goal, cold):
        self._scale = 1.0  # σ_eff = σ_min + (σ − σ_min)·scale
        if self.shrink_distance is not None:
            self._scale = min(1.0, float(np.linalg.norm(x - goal)) / self.shrink_distance)
        if not cold and self._shift_parents:  # the last step ran out of time before a generation: its shift is owed
            parents = self.engine.picked
            parents.from_numpy(self._shifted(parents.to_numpy().astype(np.float64)).astype(self.engine.ntype))
        self._shift_parents = not cold  # the first generation breeds from the shifted parents

    def _generation(self, cold):
        self._generation_kernel(self.key, self.counter & 0xFFFFFFFF, int(cold), int(self._shift_parents),
                                self._scale, self._cost)
        self._shift_parents = False
        idx, cost = self._ranked(self.num_parents)
        self._best = self.engine.pick(idx)[0]
        return float(cost[0])

    def _result(self):
        return self._best


SOLVERS = {"empc": EvolutionaryMPC}
