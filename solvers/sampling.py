"""The frame shared by the sampling planners (EMPC, CEM, MPPI) on one rollout engine.

Each control step: linearize the model about (x, ū) as LinearMPC does (``linearization``)
when the affine dynamics are used (the paper's EMPC), copy x, the goal and (A_d, B_d, w_d) to
the device, run ``generations`` rounds of the planner's update rule over populations rolled
out by :class:`ocpkit.kernels.rollout.Rollout`, and copy the chosen knots back. Timings:
``model`` is the linearization, ``solve`` everything on the device including the copies
(as the paper counts EMPC's solve time), ``build`` is zero: nothing is assembled.
"""
# No "from __future__ import annotations": Taichi reads kernel annotations as types.
import time

import numpy as np
import taichi as ti

from ocpkit._checks import array, integer, positive
from ocpkit.controller import EXCEPTION, LIMITED, NAN, SUCCESS, Controller, Solution, check_linearization
from ocpkit.kernels.random import normal, seed_key
from ocpkit.kernels.rollout import Rollout


class SamplingMPC(Controller):
    """Base class: subclasses implement ``_start(cold)`` and ``_generation(cold)`` and ``_result()``.

    ``population`` candidates per generation, ``generations`` per control step; ``dynamics``
    "affine" (re-linearized each step) or "nonlinear" (the discrete model F in the kernel);
    ``stage_cost``/``terminal_cost`` replace the OCP's quadratic costs (any CasADi Function
    of (x, u, x_goal) / (x, x_goal), non-smooth allowed); ``seed`` makes runs repeatable.
    ``linearization`` picks the affine model's expansion input as in LinearMPC. ``time_limit`` (s)
    stops the generations once exceeded (a launched generation always completes): the step then
    returns the best candidate so far with status "limited".
    """

    def __init__(self, ocp, *, population: int = 1024, generations: int = 1, num_picked: int = 1,
                 sigma=None, dynamics: str = "affine", stage_cost=None, terminal_cost=None,
                 precision: str = "float64", arch: str = "auto", seed: int = 0,
                 linearization: str = "goal", time_limit: float | None = None, raise_on_fail: bool = False):
        super().__init__(ocp, raise_on_fail=raise_on_fail)
        self.time_limit = None if time_limit is None else positive(time_limit, "time_limit")
        self.linearization = check_linearization(linearization)
        self.population = integer(population, "population", 1)
        self.generations = integer(generations, "generations", 1)
        if ocp.has_state_bounds:
            raise ValueError(f"{type(self).__name__} does not enforce state bounds (x_min/x_max): express them "
                             f"as a penalty in stage_cost, or use LinearMPC/NonlinearMPC")
        if not (np.isfinite(ocp.u_min).all() and np.isfinite(ocp.u_max).all()):
            raise ValueError(f"{type(self).__name__} samples within the input bounds, which must be "
                             f"finite; got u_min={ocp.u_min.tolist()}, u_max={ocp.u_max.tolist()}")
        span = ocp.u_max - ocp.u_min
        self.sigma = 0.1 * span if sigma is None else array(np.broadcast_to(sigma, span.shape),
                                                             "sigma", span.shape)
        if (self.sigma < 0).any():
            raise ValueError(f"sigma must be >= 0, got {self.sigma.tolist()}")
        self.key = seed_key(seed)
        self.engine = Rollout(ocp, self.population, num_picked=num_picked, dynamics=dynamics,
                              stage_cost=stage_cost, terminal_cost=terminal_cost,
                              precision=precision, arch=arch)
        F = self.engine.ftype
        self._u_min = ti.field(F, shape=ocp.nu)
        self._u_max = ti.field(F, shape=ocp.nu)
        self._u_min.from_numpy(ocp.u_min.astype(self.engine.ntype))
        self._u_max.from_numpy(ocp.u_max.astype(self.engine.ntype))
        self._affine = dynamics == "affine"
        self._cost = np.empty(self.population, dtype=self.engine.ntype)  # the last generation's costs
        p = ocp.knots
        # The warm start's time shift is linear in the knots: U⁺ = S U.
        self._shift = ocp.parameterization.shift(np.eye(p))

    def __repr__(self):
        return (f"{type(self).__name__}(population={self.population}, generations={self.generations}, "
                f"{self.ocp!r})")

    def reset(self) -> None:
        """Cold start: forget the plan and restart the random stream."""
        super().reset()
        self.counter = 0  # generations drawn so far; with the seed it keys every random draw
        self._warm = False

    def _solve(self, x: np.ndarray, goal: np.ndarray) -> Solution:
        ocp = self.ocp
        times = {"model": 0.0, "build": 0.0, "solve": 0.0, "total": 0.0}
        if self._affine:
            start = time.perf_counter()
            model = self.affine_model(x, goal, self.linearization)
            if model is None:
                self._warm = False
                return self.fallback(NAN, f"non-finite affine model at x = {x.tolist()}", times)
            times["model"] = time.perf_counter() - start
        start = time.perf_counter()
        try:
            self.engine.load(x, goal, model if self._affine else None)
            cold = not self._warm
            self._start(x, goal, cold)
            best, done = np.inf, 0
            while done < self.generations and not self._out_of_time(start):
                best = self._generation(cold and done == 0)
                self.counter += 1
                done += 1
            knots = self._result() if done else None
        except Exception as exc:  # a failed step must not raise inside the control loop
            times["solve"] = time.perf_counter() - start
            self._warm = False
            return self.fallback(EXCEPTION, f"{type(exc).__name__}: {exc}", times, self.generations)
        times["solve"] = time.perf_counter() - start
        if knots is None:
            return self.fallback(LIMITED, f"time limit {self.time_limit:g} s reached before a generation", times)
        if not np.isfinite(best) or not np.isfinite(knots).all():
            self._warm = False
            return self.fallback(NAN, f"best rollout cost {best}", times, self.generations)
        self._warm = True
        knots = np.clip(knots, ocp.u_min, ocp.u_max)
        u = np.clip(ocp.parameterization.u_at(knots, 0), ocp.u_min, ocp.u_max)
        if done < self.generations:
            return Solution(u=u, knots=knots, status=LIMITED, iterations=done, times=times,
                            raw_status=f"time limit {self.time_limit:g} s reached after {done} of "
                                       f"{self.generations} generations (best cost {best:.6g})")
        return Solution(u=u, knots=knots, status=SUCCESS, raw_status=f"best cost {best:.6g}",
                        iterations=self.generations, times=times)

    def _out_of_time(self, start: float) -> bool:
        return self.time_limit is not None and time.perf_counter() - start >= self.time_limit

    def _shifted(self, knots: np.ndarray) -> np.ndarray:
        """Knots (…, p, m) advanced one control step and clipped to the input bounds."""
        return np.clip(np.einsum("jl,...la->...ja", self._shift, knots), self.ocp.u_min, self.ocp.u_max)

    def _ranked(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        """Indices and costs of the ``count`` cheapest candidates of the last generation, best
        first (NaN counts as +inf). Ties keep candidate order, so the selection is deterministic.
        """
        cost = np.nan_to_num(self._cost.astype(np.float64), nan=np.inf)
        idx = np.argpartition(cost, count - 1)[:count] if count < cost.size else np.arange(cost.size)
        idx = idx[np.lexsort((idx, cost[idx]))]
        return idx, cost[idx]

    def _start(self, x: np.ndarray, goal: np.ndarray, cold: bool) -> None:
        """Prepare this control step's search (warm start from the previous step unless cold)."""
        raise NotImplementedError

    def _generation(self, cold: bool) -> float:
        """One population: sample, roll out, update; returns the best cost seen."""
        raise NotImplementedError

    def _result(self) -> np.ndarray:
        """The knots (p, m) to apply, on the host."""
        raise NotImplementedError


class GaussianSampling(SamplingMPC):
    """Base of CEM and MPPI: each generation samples knots ~ N(mean, std²) per parameter, clipped
    to the input bounds; candidate 0 is the mean itself so the incumbent is always evaluated."""

    def __init__(self, ocp, **options):
        super().__init__(ocp, **options)
        eng = self.engine
        F = eng.ftype
        N, p, m = eng.num_sims, eng.num_knots, eng.nu
        knots, rollout, lo, hi = eng.knots, eng.rollout, self._u_min, self._u_max

        @ti.kernel
        def generation(key: ti.u32, counter: ti.u32, distribution: ti.types.ndarray(), out: ti.types.ndarray()):
            for i in range(N):
                for j, a in ti.static(ti.ndrange(p, m)):
                    v = ti.cast(distribution[0, j, a], F)
                    if i > 0:
                        v += ti.cast(distribution[1, j, a], F) * ti.cast(normal(key, counter, i, j * m + a), F)
                    knots[i, j, a] = ti.min(ti.max(v, lo[a]), hi[a])
                out[i] = rollout(i)

        self._gaussian_kernel = generation

    def _sample(self, mean: np.ndarray, std: np.ndarray) -> None:
        """Roll out one population drawn from N(mean, std²) (one call: the distribution goes in,
        the costs come back in ``self._cost``)."""
        self._gaussian_kernel(self.key, self.counter & 0xFFFFFFFF, np.stack([mean, std]), self._cost)
