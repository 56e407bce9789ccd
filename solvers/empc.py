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
from ocpkit.solvers.sampling import SEEDS, SamplingMPC, clip_func, seed_func


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
        self.engine.write("shift", self._shift_rows.values())
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
            self._generation_kernel = self._kernel("preconditioned")
        else:
            if scales is not None:
                raise ValueError(
                    "scales applies to variant='preconditioned' only; the paper's variant mutates with sigma"
                )
            self._paper_settings(sigma, shrink_distance, sigma_min)
            self._generation_kernel = self._kernel("paper")

    def _sections(self) -> dict:
        """The planner's sections and EMPC's: the shift S's rows (:class:`SparseRows`) and, with the paper's variant,
        σ then σ_min."""
        self._shift_rows = SparseRows(self._shift)
        sigma = {} if self.preconditioned else {"sigma": 2 * self.ocp.nu}
        return {**super()._sections(), "shift": self._shift_rows.size, **sigma}

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
        self.engine.write("sigma", np.concatenate([self.sigma, self.sigma_min]))

    def _kernel(self, variant: str):
        """The generation kernel of ``variant``, shared by every EMPC of this engine's shape."""
        eng = self.engine
        shape = (eng.ftype, eng.num_knots, eng.nu, self._shift_rows.width, eng.layout)
        build = _paper_kernel if variant == "paper" else _preconditioned_kernel
        return runtime.shared(("empc", variant, *eng.key, self._shift_rows.width), lambda: build(eng.record, *shape))

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
        eng = self.engine
        if self.preconditioned:
            log_lo, log_span = math.log(self.scales[0]), math.log(self.scales[1] / self.scales[0])
            args = (key, counter, shift, log_lo, log_span, eng.knots, eng.picked, eng.data, self._eps, self._results)
        else:
            args = (key, counter, int(cold), shift, self._scale, eng.knots, eng.picked, eng.data, self._results)
        self._launch(self._generation_kernel, *args)
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


@ti.func
def _two_parents(key, counter, i, count):
    """Child i's two parents, each uniform among the first ``count`` of the pool (random slots 0 and 1)."""
    p1 = ti.min(ti.cast(uniform(key, counter, i, 0) * count, ti.i32), count - 1)
    p2 = ti.min(ti.cast(uniform(key, counter, i, 1) * count, ti.i32), count - 1)
    return p1, p2


def _parent_func(ftype, p, width, layout):
    """``parent(r, j, a, shift, parents, data)``: knot j, input a of parent r; with ``shift``, of the parent advanced
    one control step (U⁺ = S U, clipped): the warm start from the previous step's parents. S enters by its nonzeros
    per row (``width``; the "shift" section): a run-time loop over them, S dense for the piecewise-linear basis (its
    pseudo-inverse), p nonzeros a row."""
    columns = layout["shift"]
    weights = columns + p * width
    clip = clip_func(layout["bounds"], layout.sizes["bounds"] // 2)

    @ti.func
    def parent(r, j, a, shift, parents: ti.template(), data: ti.template()):
        v = parents[r, j, a]
        if shift:
            v = ti.cast(0.0, ftype)
            for s in range(width):
                column = ti.cast(data[columns + j * width + s], ti.i32)
                v += data[weights + j * width + s] * parents[r, column, a]
            v = clip(v, a, data)
        return v

    return parent


def _paper_kernel(record, F, p, m, width, layout):
    """Algorithm 1's generation: a cold start draws every knot uniformly within the bounds; else the parents carry
    over and the rest are children by uniform crossover and Gaussian mutation (σ, σ_min: the "sigma" section)."""
    parent = _parent_func(F, p, width, layout)
    clip = clip_func(layout["bounds"], m)
    bounds, sigma = layout["bounds"], layout["sigma"]
    # Random slots per candidate: parents, then a mutation flag per input, then a
    # crossover coin and a noise draw per parameter.
    MUTATE, CROSS, NOISE = 2, 2 + m, 2 + m + p * m

    @ti.kernel
    def generation(
        key: ti.u32,
        counter: ti.u32,
        cold: ti.i32,
        shift: ti.i32,
        scale: F,
        knots: ti.types.ndarray(),
        parents: ti.types.ndarray(),
        data: ti.types.ndarray(),
        out: ti.types.ndarray(),
    ):
        for i in range(knots.shape[0]):
            k = parents.shape[0]
            if cold:
                for j in range(p):
                    for a in range(m):
                        r = ti.cast(uniform(key, counter, i, CROSS + j * m + a), F)
                        lo, hi = data[bounds + a], data[bounds + m + a]
                        knots[i, j, a] = lo + (hi - lo) * r
            elif i < k:
                for j in range(p):
                    for a in range(m):
                        knots[i, j, a] = parent(i, j, a, shift, parents, data)
            else:
                p1, p2 = _two_parents(key, counter, i, k)
                for a in range(m):
                    mutate = uniform(key, counter, i, MUTATE + a) < 0.5
                    high, low = data[sigma + a], data[sigma + m + a]
                    noise = low + (high - low) * scale
                    for j in range(p):
                        slot = j * m + a
                        v = parent(p1, j, a, shift, parents, data)
                        if uniform(key, counter, i, CROSS + slot) < 0.5:
                            v = parent(p2, j, a, shift, parents, data)
                        if mutate:
                            v += noise * ti.cast(normal(key, counter, i, NOISE + slot), F)
                        knots[i, j, a] = clip(v, a, data)
            record(i, knots, data, out)

    return generation


def _preconditioned_kernel(record, F, p, m, width, layout):
    """The preconditioned generation: the parents and the seeds carry over; each child crosses two of them and
    is mutated by s·L⁻ᵀε, s log-uniform in [exp(log_lo), exp(log_lo + log_span)] (module docstring)."""
    parent = _parent_func(F, p, width, layout)
    d = p * m
    clip = clip_func(layout["bounds"], m)
    seed = seed_func(layout["preconditioner"], d, p, m)
    whiten = layout["preconditioner"]  # L⁻ᵀ (d × d), then the seeds
    # Random slots per candidate: two parents, the mutation scale, a crossover coin per parameter;
    # the normal draws ε use their own stream.
    SCALE, CROSS = 2, 3

    @ti.func
    def breeder(r, j, a, shift, parents: ti.template(), data: ti.template()):
        """Member r of the breeding pool: the parents, then the seeds."""
        v = ti.cast(0.0, F)
        if r < parents.shape[0]:
            v = parent(r, j, a, shift, parents, data)
        else:
            v = seed(r - parents.shape[0], j, a, data)
        return v

    @ti.kernel
    def generation(
        key: ti.u32,
        counter: ti.u32,
        shift: ti.i32,
        log_lo: ti.f64,
        log_span: ti.f64,
        knots: ti.types.ndarray(),
        parents: ti.types.ndarray(),
        data: ti.types.ndarray(),
        eps: ti.types.ndarray(),
        out: ti.types.ndarray(),
    ):
        for i in range(knots.shape[0]):
            pool = parents.shape[0] + SEEDS
            if i < pool:  # the elites and the seeds themselves
                for j in range(p):
                    for a in range(m):
                        knots[i, j, a] = breeder(i, j, a, shift, parents, data)
            else:
                p1, p2 = _two_parents(key, counter, i, pool)
                s = ti.cast(ti.exp(log_lo + log_span * uniform(key, counter, i, SCALE)), F)
                for c in range(d):
                    eps[i, c] = ti.cast(normal(key, counter, i, c), F)
                for j in range(p):  # crossover, then the mutation s·L⁻ᵀε, then the clip, in place
                    for a in range(m):
                        r = j * m + a
                        mate = p1 if uniform(key, counter, i, CROSS + r) < 0.5 else p2
                        acc = ti.cast(0.0, F)
                        for c in range(r, d):  # L⁻ᵀ is upper triangular
                            acc += data[whiten + r * d + c] * eps[i, c]
                        knots[i, j, a] = clip(breeder(mate, j, a, shift, parents, data) + s * acc, a, data)
            record(i, knots, data, out)

    return generation


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
