"""EvolutionaryMPC: the paper's EMPC (Section "Evolutionary MPC", Algorithm 1) on a Taichi kernel.

Per generation, in one kernel launch, every candidate is bred and rolled out. The ``num_parents``
best knot sets survive unchanged (elitism) and carry over to the next control step shifted one step
in time; the rest of the population are children of two parents drawn uniformly, each parameter
inherited from either parent with probability ½, then mutated and clipped to the bounds. u is the
best candidate's input at t = 0. "Best", for the parents and the pick, is by constraint domination in both
variants (:func:`ocpkit.solvers.sampling.best_first`): a candidate clear of the obstacles and within the
state bounds beats every one that is not, whatever their costs.

``variant="paper"`` is Algorithm 1 as printed: a cold start draws each knot uniformly within the input
bounds; each input of a child is mutated with probability ½ by adding N(0, σ) to its knots; σ may
shrink with the distance to the goal (the paper's conclusion) so that EMPC holds the system near it.

``variant="preconditioned"`` (default; :mod:`ocpkit.solvers.sampling`) breeds from the parents and the
seeds (Newton candidate, holding input), which are also candidates of every population; a cold start
takes the holding input as every parent. Each child is mutated by s·L⁻ᵀε, ε ~ N(0, I), with a scale s
drawn log-uniformly from ``scales`` in whitened units, so its expected extra cost, s²·p·m on the QP's
quadratic model, spans small refinements to bold jumps whatever the conditioning.
"""

# No "from __future__ import annotations": Taichi reads kernel annotations as types.
import math

import numpy as np
import taichi as ti

from ocpkit._checks import integer, positive
from ocpkit.codegen.kernels import runtime
from ocpkit.codegen.kernels.random import normal, uniform
from ocpkit.codegen.kernels.rollout import SparseRows
from ocpkit.solvers.methods import EMPC
from ocpkit.solvers.sampling import SEEDS, SamplingMPC


class EvolutionaryMPC(SamplingMPC):
    """Algorithm 1 with ``population`` (numSims), ``num_parents`` and ``generations`` per control step.

    Preconditioned (default): ``scales`` = (s_min, s_max), the log-uniform range of the whitened
    mutation scale (default (1e-2, 1e2)). Paper: ``sigma`` (σ_noise: a scalar or one per input; default
    10 % of each input's range) and ``shrink_distance`` d: when set, σ_eff = σ_min + (σ − σ_min)·
    min(1, ‖x − x_goal‖ / d), with ``sigma_min`` (default σ/10). See
    :class:`ocpkit.solvers.sampling.SamplingMPC` for ``variant``, ``dynamics``,
    ``stage_cost``/``terminal_cost``, ``precision``, ``arch`` and ``seed``.
    """

    def __init__(
        self,
        ocp,
        *,
        population: int = EMPC["population"].default,
        num_parents: int = EMPC["num_parents"].default,
        generations: int = EMPC["generations"].default,
        scales=None,
        sigma=None,
        shrink_distance: float | None = None,
        sigma_min=None,
        variant: str = EMPC["variant"].default,
        **options,
    ):
        population = integer(population, "population", 2)
        self.num_parents = integer(num_parents, "num_parents", 1)
        if self.num_parents >= population:
            raise ValueError(f"num_parents must be < population ({population}), got {num_parents}")
        super().__init__(
            ocp, population=population, generations=generations, num_picked=self.num_parents, variant=variant, **options
        )
        # Candidates below this index are carried over (the parents, then the seeds); the rest are bred.
        self._first_child = self.num_parents + (SEEDS if self.preconditioned else 0)
        paper_only = {"sigma": sigma, "shrink_distance": shrink_distance, "sigma_min": sigma_min}
        given = [name for name, value in paper_only.items() if value is not None]
        if self.preconditioned:
            if given:
                raise ValueError(
                    f"{', '.join(given)} apply to variant='paper' only; the preconditioned "
                    f"variant draws its mutation scale from scales"
                )
            self.scales = _scales(scales)
            self._generation_kernel = self._preconditioned_kernel()
        else:
            if scales is not None:
                raise ValueError(
                    "scales applies to variant='preconditioned' only; the paper's variant mutates with sigma"
                )
            self._paper_settings(sigma, shrink_distance, sigma_min)
            self._generation_kernel = self._paper_kernel()

    def _paper_settings(self, sigma, shrink_distance, sigma_min):
        ocp = self.ocp
        span = ocp.u_max - ocp.u_min
        self.sigma = 0.1 * span if sigma is None else np.broadcast_to(np.asarray(sigma, dtype=float), span.shape).copy()
        if not (np.isfinite(self.sigma).all() and (self.sigma >= 0).all()):
            raise ValueError(f"sigma must be finite and >= 0, got {self.sigma.tolist()}")
        self.shrink_distance = None if shrink_distance is None else positive(shrink_distance, "shrink_distance")
        self.sigma_min = (
            self.sigma / 10
            if sigma_min is None
            else np.broadcast_to(np.asarray(sigma_min, dtype=float), self.sigma.shape).copy()
        )
        if not (
            np.isfinite(self.sigma_min).all() and (self.sigma_min >= 0).all() and (self.sigma_min <= self.sigma).all()
        ):
            raise ValueError(
                f"sigma_min must be finite with 0 <= sigma_min <= sigma "
                f"({self.sigma.tolist()}), got {self.sigma_min.tolist()}"
            )
        self._sigma = ti.field(self.engine.ftype, shape=(2, ocp.nu))  # σ and σ_min
        runtime.stage(self._sigma, np.stack([self.sigma, self.sigma_min]))

    def _parent_func(self):
        """``parent(r, j, a, shift)``: knot j, input a of parent r; with ``shift``, of the parent
        advanced one control step (U⁺ = S U, clipped): the warm start from the previous step's parents."""
        eng = self.engine
        F = eng.ftype
        parents, lo, hi = eng.picked, self._u_min, self._u_max
        # S's nonzeros by row, in float64 as the Python constants they were when the kernel unrolled S (each product
        # rounded to the knots' type). A run-time loop over them: S is dense for the piecewise-linear basis (its
        # pseudo-inverse), p nonzeros a row.
        shift_rows = SparseRows(self._shift)
        columns, weights, width = shift_rows.columns, shift_rows.weights, shift_rows.width

        @ti.func
        def parent(r, j, a, shift):
            v = parents[r, j, a]
            if shift:
                v = ti.cast(0.0, F)
                for s in range(width):
                    v += ti.cast(weights[j, s] * parents[r, columns[j, s], a], F)
                v = ti.min(ti.max(v, lo[a]), hi[a])
            return v

        return parent

    def _paper_kernel(self):
        eng = self.engine
        F = eng.ftype
        N, p, m, k = eng.num_sims, eng.num_knots, eng.nu, self.num_parents
        knots, record = eng.knots, eng.record
        lo, hi, sigma = self._u_min, self._u_max, self._sigma
        parent = self._parent_func()
        # Random slots per candidate: parents, then a mutation flag per input, then a
        # crossover coin and a noise draw per parameter.
        MUTATE, CROSS, NOISE = 2, 2 + m, 2 + m + p * m

        @ti.kernel
        def generation(key: ti.u32, counter: ti.u32, cold: ti.i32, shift: ti.i32, scale: F, out: ti.types.ndarray()):
            for i in range(N):
                if cold:
                    for j in range(p):
                        for a in range(m):
                            r = ti.cast(uniform(key, counter, i, CROSS + j * m + a), F)
                            knots[i, j, a] = lo[a] + (hi[a] - lo[a]) * r
                elif i < k:
                    for j in range(p):
                        for a in range(m):
                            knots[i, j, a] = parent(i, j, a, shift)
                else:
                    p1 = ti.min(ti.cast(uniform(key, counter, i, 0) * k, ti.i32), k - 1)
                    p2 = ti.min(ti.cast(uniform(key, counter, i, 1) * k, ti.i32), k - 1)
                    for a in range(m):
                        mutate = uniform(key, counter, i, MUTATE + a) < 0.5
                        noise = sigma[1, a] + (sigma[0, a] - sigma[1, a]) * scale
                        for j in range(p):
                            slot = j * m + a
                            v = parent(p1, j, a, shift)
                            if uniform(key, counter, i, CROSS + slot) < 0.5:
                                v = parent(p2, j, a, shift)
                            if mutate:
                                v += noise * ti.cast(normal(key, counter, i, NOISE + slot), F)
                            knots[i, j, a] = ti.min(ti.max(v, lo[a]), hi[a])
                record(i, out)

        return generation

    def _preconditioned_kernel(self):
        eng = self.engine
        F = eng.ftype
        N, p, m, k = eng.num_sims, eng.num_knots, eng.nu, self.num_parents
        d, pool = p * m, self.num_parents + SEEDS
        knots, record = eng.knots, eng.record
        lo, hi, whiten, seeds = self._u_min, self._u_max, self._whiten, self._seeds
        parent = self._parent_func()
        log_lo, log_span = math.log(self.scales[0]), math.log(self.scales[1] / self.scales[0])
        # Random slots per candidate: two parents, the mutation scale, a crossover coin per parameter;
        # the normal draws ε use their own stream.
        SCALE, CROSS = 2, 3
        eps = ti.field(F, shape=(N, d))  # each child's ε, drawn once and read by every row of L⁻ᵀε

        @ti.func
        def breeder(r, j, a, shift):
            """Member r of the breeding pool: the parents, then the seeds."""
            v = ti.cast(0.0, F)
            if r < k:
                v = parent(r, j, a, shift)
            else:
                v = seeds[r - k, j, a]
            return v

        @ti.kernel
        def generation(key: ti.u32, counter: ti.u32, shift: ti.i32, out: ti.types.ndarray()):
            for i in range(N):
                if i < pool:  # the elites and the seeds themselves
                    for j in range(p):
                        for a in range(m):
                            knots[i, j, a] = breeder(i, j, a, shift)
                else:
                    p1 = ti.min(ti.cast(uniform(key, counter, i, 0) * pool, ti.i32), pool - 1)
                    p2 = ti.min(ti.cast(uniform(key, counter, i, 1) * pool, ti.i32), pool - 1)
                    s = ti.cast(ti.exp(log_lo + log_span * uniform(key, counter, i, SCALE)), F)
                    for c in range(d):
                        eps[i, c] = ti.cast(normal(key, counter, i, c), F)
                    for j in range(p):  # crossover, then the mutation s·L⁻ᵀε, then the clip, in place
                        for a in range(m):
                            r = j * m + a
                            mate = p1 if uniform(key, counter, i, CROSS + r) < 0.5 else p2
                            acc = ti.cast(0.0, F)
                            for c in range(r, d):  # L⁻ᵀ is upper triangular
                                acc += whiten[r, c] * eps[i, c]
                            knots[i, j, a] = ti.min(ti.max(breeder(mate, j, a, shift) + s * acc, lo[a]), hi[a])
                record(i, out)

        return generation

    def reset(self):
        super().reset()
        self._shift_parents = False
        self.child_wins = self.generations_run = 0  # see child_win_rate

    def _start(self, x, goal, cold):
        parents = self.engine.picked
        guess = self._guess
        if guess is not None or (cold and self.preconditioned):  # every parent starts as the guess or holding input
            start = guess if guess is not None else self.preconditioner.hold
            parents.from_numpy(np.broadcast_to(start, parents.shape).astype(self.engine.ntype))
        elif not cold and (owed := self._missed + int(self._shift_parents)):  # steps that ran no generation
            parents.from_numpy(self._shifted(parents.to_numpy().astype(np.float64), owed).astype(self.engine.ntype))
        # the first generation breeds from the shifted parents; a guess is this step's plan, not shifted
        self._shift_parents = not cold and guess is None
        self._scale = 1.0  # paper: σ_eff = σ_min + (σ − σ_min)·scale
        if not self.preconditioned and self.shrink_distance is not None:
            self._scale = min(1.0, float(np.linalg.norm(x - goal)) / self.shrink_distance)

    def _generation(self, cold):
        key, counter, shift = self.key, self.counter & 0xFFFFFFFF, int(self._shift_parents)
        if self.preconditioned:
            self._launch(self._generation_kernel, key, counter, shift, self._results)
        else:
            self._launch(self._generation_kernel, key, counter, int(cold), shift, self._scale, self._results)
        self._shift_parents = False
        idx = self._ranked(self.num_parents)
        self._best = self._pick(idx)[0]
        self.child_wins += int(idx[0] >= self._first_child)
        self.generations_run += 1
        return self._outcome(idx[0])

    @property
    def child_win_rate(self) -> float:
        """The share of generations since the last reset whose best candidate was a newly bred child, not a
        carried-over parent or (preconditioned) a seed: how often Algorithm 1's search, rather than what it
        started from, set the plan (NaN before the first generation)."""
        return self.child_wins / self.generations_run if self.generations_run else float("nan")

    def _result(self, best):
        return self._best, best


def _scales(scales) -> tuple[float, float]:
    if scales is None:
        return 1e-2, 1e2
    try:
        lo, hi = (float(s) for s in scales)
    except (TypeError, ValueError):
        raise TypeError(f"scales must be two numbers (s_min, s_max), got {scales!r}") from None
    if not (np.isfinite([lo, hi]).all() and 0 < lo <= hi):
        raise ValueError(f"scales must satisfy 0 < s_min <= s_max < inf, got {scales!r}")
    return lo, hi


SOLVERS = {"empc": EvolutionaryMPC}
