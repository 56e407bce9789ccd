"""The frame shared by the sampling planners (EMPC, CEM, MPPI) on one rollout engine.

Each control step: linearize the model about (x, ū) as LinearMPC does (``linearization``), copy x,
the goal and (A_d, B_d, w_d) to the device, run ``generations`` rounds of the planner's update rule
over populations rolled out by :class:`ocpkit.codegen.kernels.rollout.Rollout`, and copy the chosen knots back.

``variant="preconditioned"`` (the default) fixes what defeats the paper's Algorithm 1 on the N-link
robots (DESIGN, "Sampling planners: what we learnt"): the knot QP's Hessian is so anisotropic
(condition 1e5–1e7 from 3 links) that isotropic mutations land far uphill. Each step the
:class:`ocpkit.solvers.preconditioner.Preconditioner` builds the condensed knot QP ½zᵀPz + qᵀz at this step's
linearization (the rollout cost of affine dynamics is exactly twice it plus a constant), factors P = LLᵀ, and
supplies *seeds* evaluated in every population: the optimum of that QP within the input bounds (a Newton candidate,
:func:`ocpkit.qp.boxqp.solve_box_qp`; with obstacles or state bounds, within their linearized rows too, by DAQP) and
the input that holds the goal (u_g corrected for gravity and other static loads). Perturbations are drawn as L⁻ᵀε
(covariance ∝ P⁻¹), so every direction costs alike. CEM and MPPI start each step's Gaussian at the best by rollout of
their incumbent and the seeds (:class:`ocpkit.solvers.gaussian.GaussianSampling`). The fitness stays the rollout, so
``dynamics="nonlinear"`` and any CasADi stage cost keep working; the QP only shapes the search.
``variant="paper"`` is the plain algorithm: isotropic sampling in input coordinates, no seeds.

Both variants select by constraint domination ("feasibility first", Deb's rule) wherever they compare candidates —
EMPC's parents and its pick, CEM's elites, MPPI's weights, the incumbent against the seeds and the plan returned: each
rollout brings its cost J (with the exact penalties of :func:`ocpkit.codegen.kernels.rollout.fitness`) and its violation
V of the obstacle clearances and hard state bounds (:func:`ocpkit.codegen.kernels.rollout.violation`, judged on the
rollout's ``dynamics``); a candidate with V ≤ FEASIBILITY_TOLERANCE beats every other, among the others the smaller V
wins, among the feasible the smaller J (:func:`best_first`). By the penalty alone the weight decides: at
``obstacle_weight`` 10 all three planners drove nlink:3 through a ball on its path (down to −0.09 m); by domination none
did, at any weight. The rollouts stay affine by default even around obstacles, the violation then judged on the affine
prediction while the controller's certificate rolls the plan out on the nonlinear model: on nlink:3 past a ball, affine
rollouts kept the arm clear but 8–49 % of their steps were "soft" (the prediction's drift over the horizon), where
``dynamics="nonlinear"`` made every step a certified success; on the docs' Panda reach the nonlinear rollouts took
194 s to compile and 213 ms a step, and their population diverged (final distance 1.03 m instead of 1 mm). Choose
"nonlinear" where the robot's discrete model is cheap and stable over the horizon.

A step follows a goal window and moving obstacles (``solve(x, goal_window, obstacles=…)``, TAKES) through the
kernels' data: each rollout's stage k reads row k of the goal and obstacle windows (:meth:`Rollout.load`), so
nothing is compiled or built again when they change. ``initial_guess`` is the step's incumbent — EMPC's parents,
CEM's and MPPI's starting mean, the preconditioner's linearization plan — in place of the shifted previous plan. The
preconditioner's knot QP takes the windows too (its seeds: the QP's optimum along them, and the input holding
stage 0's goal).

Timings: ``model`` is the linearization; ``build`` the preconditioner's QP; ``solve`` the rest
(``factor``, ``seed`` — the Newton (or DAQP) and holding candidates —, ``copies`` between host and device and
``generations``, each also reported on its own), as the paper counts EMPC's solve time.
"""

# No "from __future__ import annotations": Taichi reads kernel annotations as types.
import time

import numpy as np
import taichi as ti

from ocpkit._checks import choice, integer, positive
from ocpkit.controller import Controller, check_linearization
from ocpkit.status import EXCEPTION, LIMITED, NAN, SUCCESS, OperationCosts, Reason, Solution
from ocpkit.codegen.kernels.random import seed_key
from ocpkit.codegen.kernels.rollout import FEASIBILITY_TOLERANCE, Rollout
from ocpkit.solvers.methods import SAMPLING, VARIANTS
from ocpkit.solvers.preconditioner import Preconditioner

SEEDS = 2  # Newton candidate, holding input
PARTS = ("model", "build", "factor", "seed", "copies", "generations", "solve", "total")


def excess(results: np.ndarray) -> np.ndarray:
    """Each candidate's violation beyond FEASIBILITY_TOLERANCE (0: feasible) from rollout ``results`` (N, 2) of
    (cost, violation); a candidate whose cost or violation is not finite counts as infinitely violating (a NaN
    state can make every clearance test pass)."""
    results = results.astype(np.float64)
    cost, violation = results[:, 0], results[:, 1]
    out = np.where(violation <= FEASIBILITY_TOLERANCE, 0.0, violation)
    out[~(np.isfinite(cost) & np.isfinite(violation))] = np.inf
    return out


def best_first(results: np.ndarray, count: int) -> np.ndarray:
    """Indices of the ``count`` best candidates by constraint domination, best first, from rollout ``results``
    (N, 2) of (cost, violation): by :func:`excess`, then cost (NaN counting as +inf), then candidate number (the
    selection is deterministic)."""
    keys = (excess(results), np.nan_to_num(results[:, 0].astype(np.float64), nan=np.inf))
    idx = np.arange(len(results))
    for key in keys:  # narrow by partitions while the rows kept tie on every key so far: no full sort of N rows
        if idx.size <= count:
            break
        k = key[idx]
        kth = np.partition(k, count - 1)[count - 1]
        idx = idx[k <= kth]
        if (k[k <= kth] != kth).any():
            break
    order = np.lexsort((idx,) + tuple(key[idx] for key in reversed(keys)))
    return idx[order[:count]]


def clip_func(offset: int, m: int):
    """``clip(v, a, data)`` (a ``@ti.func``): v within input a's bounds, read from the "bounds" section of the engine's
    data at ``offset`` (u_min, then u_max; ``m`` inputs)."""

    @ti.func
    def clip(v, a, data: ti.template()):
        return ti.min(ti.max(v, data[offset + a]), data[offset + m + a])

    return clip


def seed_func(offset: int, d: int, p: int, m: int):
    """``seed(s, j, a, data)`` (a ``@ti.func``): knot j, input a of seed s (0: the Newton candidate, 1: the holding
    input), read from the "preconditioner" section at ``offset`` after L⁻ᵀ (d × d)."""

    @ti.func
    def seed(s, j, a, data: ti.template()):
        return data[offset + d * d + (s * p + j) * m + a]

    return seed


class SamplingMPC(Controller):
    """Base class: subclasses implement ``_start``, ``_generation`` and ``_result``.

    A step takes a goal window, moved obstacles and an initial guess (module docstring).

    ``population`` candidates per generation, ``generations`` per control step; ``variant``
    "preconditioned" (default) or "paper" (module docstring); ``dynamics`` "affine" (re-linearized
    each step) or "nonlinear" (the discrete model F in the kernel), which also judges each candidate's violation of
    the obstacles and state bounds (module docstring: which to choose around obstacles);
    ``stage_cost``/``terminal_cost`` replace the OCP's cost in the fitness (any CasADi Function of (x, u, goal) /
    (x, goal), goal of ``ocp.ng`` entries, non-smooth allowed; default:
    :func:`ocpkit.codegen.kernels.rollout.fitness`, the OCP's terms and the exact penalties of its state bounds and a
    task's obstacles); ``seed`` makes runs repeatable.
    ``linearization`` picks the affine model's expansion input as in LinearMPC. ``time_limit`` (s) bounds the whole
    step: each stage — the linearization, the preconditioner, the copies to the device, each generation — starts only
    if its measured time (:class:`ocpkit.status.OperationCosts`) and that of the stages that must follow it fit in
    what is left. Where the first generation cannot fit, the step answers at once from the incumbent plan advanced a
    step (:meth:`Controller.fallback`, "limited") and the next step that searches advances the incumbent by the steps
    it missed; where the preconditioner cannot fit, a warm step searches with the previous step's (seeds and whitening)
    and says so; where later generations cannot, the step returns the best candidate so far ("limited"), as it does
    when its last generation ends past the budget. A new controller's first step compiles the kernels and is not
    measured (0.5 s for a generation on nlink:13, which as a measurement locked it out of a 100 ms budget), its
    second measures: neither is bounded, so call :meth:`warm_up` (two steps) first. ``threads`` limits BLAS/OpenMP
    threads inside a step (see Controller); Taichi's own CPU threads are set at its start (``OCPKIT_CPU_THREADS``).
    """

    TAKES = frozenset({"goal window", "obstacles", "initial guess"})

    def __init__(
        self,
        ocp,
        *,
        population: int = SAMPLING["population"].default,
        generations: int = SAMPLING["generations"].default,
        num_picked: int = 1,
        variant: str = SAMPLING["variant"].default,
        dynamics: str = SAMPLING["dynamics"].default,
        stage_cost=None,
        terminal_cost=None,
        precision: str = SAMPLING["precision"].default,
        arch: str = SAMPLING["arch"].default,
        seed: int = SAMPLING["seed"].default,
        linearization: str = SAMPLING["linearization"].default,
        time_limit: float | None = None,
        raise_on_fail: bool = SAMPLING["raise_on_fail"].default,
        threads: int | None = SAMPLING["threads"].default,
    ):
        super().__init__(ocp, raise_on_fail=raise_on_fail, threads=threads)
        self.variant = choice(variant, VARIANTS, "variant")
        self.preconditioned = variant == "preconditioned"
        self.time_limit = None if time_limit is None else positive(time_limit, "time_limit")
        self.linearization = check_linearization(linearization)
        self.population = integer(population, "population", 1)
        self.generations = integer(generations, "generations", 1)
        if not (np.isfinite(ocp.u_min).all() and np.isfinite(ocp.u_max).all()):
            raise ValueError(
                f"{type(self).__name__} samples within the input bounds, which must be "
                f"finite; got u_min={ocp.u_min.tolist()}, u_max={ocp.u_max.tolist()}"
            )
        if (stage_cost is not None or terminal_cost is not None) and (ocp.has_state_bounds or ocp.task_functions):
            raise ValueError(
                f"{type(self).__name__}: stage_cost/terminal_cost replace the whole fitness, which "
                "carries the OCP's state bounds and task as penalties: build yours on "
                "ocpkit.codegen.kernels.rollout.fitness(ocp), or leave them out of the OCP"
            )
        self.key = seed_key(seed)
        p, m = ocp.knots, ocp.nu
        # The warm start's time shift is linear in the knots: U⁺ = S U.
        self._shift = ocp.parameterization.shift(np.eye(p))
        self.engine = Rollout(
            ocp,
            self.population,
            num_picked=num_picked,
            dynamics=dynamics,
            stage_cost=stage_cost,
            terminal_cost=terminal_cost,
            precision=precision,
            arch=arch,
            sections=self._sections(),
            step_sections={"preconditioner": p * m * (p * m + SEEDS)} if self.preconditioned else None,
        )
        self.engine.write("bounds", np.concatenate([ocp.u_min, ocp.u_max]))
        self._affine = dynamics == "affine"
        self._costs = OperationCosts()  # the stages of a step (see time_limit)
        self._compiled = False  # whether a step has run: the first one compiles the kernels, its times are not kept
        self._results = self.engine.results()  # the last generation's (cost, violation) per candidate
        # each candidate's ε, drawn once and read by every row of its mutation (EMPC's L⁻ᵀε, CEM's and MPPI's G ε)
        self._eps = ti.ndarray(self.engine.ftype, (self.population, p * m))
        if self.preconditioned:
            self.preconditioner = Preconditioner(ocp)

    def _sections(self) -> dict:
        """The engine's data sections this planner's kernels read, set once (:class:`Rollout` ``sections``): the input
        bounds (u_min, then u_max). Preconditioned, its "preconditioner" step section holds L⁻ᵀ then the seeds (Newton
        candidate, holding input), sent with each step's load."""
        return {"bounds": 2 * self.ocp.nu}

    @property
    def path(self) -> str:
        """The Taichi kernel and its arch."""
        return f"Taichi kernel ({self.engine.arch})"

    def __repr__(self):
        return (
            f"{type(self).__name__}({self.variant}, population={self.population}, "
            f"generations={self.generations}, {self.ocp!r})"
        )

    def reset(self) -> None:
        """Cold start: forget the plan and restart the random stream."""
        super().reset()
        self.counter = 0  # generations drawn so far; with the seed it keys every random draw
        self._warm = False
        self._missed = 0  # steps answered without a search since the last search: the incumbent's owed shifts

    def _solve(self, x: np.ndarray, goal: np.ndarray) -> Solution:
        ocp = self.ocp
        times = self._times = dict.fromkeys(PARTS, 0.0)
        # The step's incumbent: the user's guess, else the previous plan; a cold start has neither.
        self._guess = None if self.guess is None else np.clip(self.guess, ocp.u_min, ocp.u_max)
        cold = not self._warm and self._guess is None
        pre = self.preconditioner if self.preconditioned else None
        # A cold start has no incumbent: it needs this step's seeds. Otherwise the preconditioner may be an earlier's.
        fresh = pre is not None and (cold or pre.L is None)
        linearize = self._affine or pre is not None
        must = ("start", "load") + (("model",) if linearize else ()) + (("preconditioner",) if fresh else ())
        if not self._fits("generation", *must):
            return self._missed_step(("generation",) + must, times)
        model = None
        if linearize:
            start = time.perf_counter()
            model = self.affine_model(x, goal, self.linearization)
            times["model"] = self._measured("model", start)
            if model is None:
                self._warm = False
                return self.fallback(
                    NAN, f"non-finite affine model at x = {x.tolist()}", times, reason=Reason.NON_FINITE_MODEL
                )
        start = time.perf_counter()
        stale = False
        try:
            if pre is not None:
                if fresh or self._fits("preconditioner", "load", "start", "generation"):
                    self._precondition(model, x, goal, times)
                else:
                    stale = True
                if not self._fits("generation", "load", "start"):
                    self._close_times(start)
                    return self._missed_step(("generation", "load", "start"), times)
            t = time.perf_counter()
            self.engine.load(x, self.goal_window, model if self._affine else None, self._moved_obstacles())
            times["copies"] += self._measured("load", t)
            t = time.perf_counter()
            self._start(x, goal, cold)
            self._missed = 0
            self._measured("start", t)
            best, done = (np.inf, np.inf), 0
            while done < self.generations and (done == 0 or self._fits("generation")):
                t = time.perf_counter()
                best = self._generation(cold and done == 0)
                self._measured("generation", t)
                self.counter += 1
                done += 1
            knots, best = self._result(best)
            self._compiled = True
        except ti.TaichiCompilationError:
            # A kernel that does not compile is a bug, the same at every step: raised, never a fallback at every
            # step (variant="paper" of CEM and MPPI ran whole closed loops on the fallback input that way).
            self._warm = False
            raise
        except Exception as exc:  # a failed step must not raise inside the control loop
            self._close_times(start)
            self._warm = False
            return self.fallback(
                EXCEPTION, f"{type(exc).__name__}: {exc}", times, self.generations, reason=Reason.SOLVER_ERROR
            )
        self._close_times(start)
        cost, violation = best
        if not np.isfinite(cost) or not np.isfinite(knots).all():
            self._warm = False
            return self.fallback(
                NAN, f"best rollout cost {cost}", times, self.generations, reason=Reason.NON_FINITE_SOLUTION
            )
        self._warm = True
        knots = np.clip(knots, ocp.u_min, ocp.u_max)
        u = np.clip(ocp.parameterization.u_at(knots, 0), ocp.u_min, ocp.u_max)
        found = f"cost {cost:.6g}" + (f", predicted violation {violation:.3g}" if self.engine.constrained else "")
        if stale:
            found += "; preconditioner of an earlier step (time budget)"
        late = ""
        if done < self.generations:
            late = f"time limit {self.time_limit:g} s reached after {done} of {self.generations} generations"
        elif self._out_of_time():
            late = f"time limit {self.time_limit:g} s exceeded by the last generation"
        if late:
            return Solution(
                u=u,
                knots=knots,
                status=LIMITED,
                iterations=done,
                times=times,
                reason=Reason.TIME_BUDGET,
                raw_status=f"{late} (best {found})",
            )
        return Solution(
            u=u, knots=knots, status=SUCCESS, raw_status=f"best {found}", iterations=self.generations, times=times
        )

    def _precondition(self, model, x: np.ndarray, goal: np.ndarray, times: dict) -> None:
        """Update the preconditioner at this step's linearization and stage its whitening and seeds (the step's load
        sends them)."""
        t = time.perf_counter()
        pre, ocp = self.preconditioner, self.ocp
        warm = self._guess if self._guess is not None else None if self.plan is None else self._shifted(self.plan)
        n, window = ocp.nx, self.goal_window
        pre.update(
            model,
            x,
            window[:, :n] if self.moving else goal,
            warm,
            times,
            window[:, n:] if self.moving else self.task_goal[n:],
            self.deadline(self.time_limit),
            self._moved_obstacles(),
        )
        t_copy = time.perf_counter()
        self.engine.stage("preconditioner", np.concatenate([pre.whiten.ravel(), pre.newton.ravel(), pre.hold.ravel()]))
        times["copies"] += time.perf_counter() - t_copy
        self._measured("preconditioner", t)

    def _fits(self, op: str, *after: str) -> bool:
        """Whether stage ``op`` fits in what is left of the step's budget with the stages ``after`` still to come, by
        their measured times (always, without a budget)."""
        left = self.remaining(self.time_limit)
        return self._costs.fits(op, None if left is None else left - sum(map(self._costs.predict, after)))

    def _measured(self, op: str, since: float) -> float:
        """Record stage ``op``, begun at perf_counter ``since``, as just ended; its seconds."""
        seconds = time.perf_counter() - since
        if self._compiled:
            self._costs.add(op, seconds)
        return seconds

    def _missed_step(self, stages: tuple, times: dict) -> Solution:
        """The fallback of a step whose budget cannot pay for ``stages``: the incumbent plan advanced a step; the
        next search advances its own incumbent by the steps missed."""
        self._missed += 1
        left = max(0.0, self.remaining(self.time_limit))
        need = sum(map(self._costs.predict, stages))
        return self.fallback(
            LIMITED,
            f"time budget: {1e3 * left:.3g} ms left, {' + '.join(stages)} measured at {1e3 * need:.3g} ms",
            times,
            reason=Reason.TIME_BUDGET,
        )

    def _close_times(self, start: float) -> None:
        """Everything after the linearization except the preconditioner's QP build counts as solve."""
        self._times["solve"] = time.perf_counter() - start - self._times["build"]

    def _out_of_time(self) -> bool:
        end = self.deadline(self.time_limit)
        return end is not None and time.perf_counter() >= end

    def _launch(self, kernel, *args) -> None:
        """Run one population kernel, its time counted as ``generations``."""
        t = time.perf_counter()
        kernel(*args)
        self._times["generations"] += time.perf_counter() - t

    def _pick(self, indices) -> np.ndarray:
        """:meth:`Rollout.pick`, its time counted as ``copies``."""
        t = time.perf_counter()
        picked = self.engine.pick(indices)
        self._times["copies"] += time.perf_counter() - t
        return picked

    def _shifted(self, knots: np.ndarray, steps: int = 1) -> np.ndarray:
        """Knots (…, p, m) advanced ``steps`` control steps and clipped to the input bounds."""
        for _ in range(steps):
            knots = np.clip(np.einsum("jl,...la->...ja", self._shift, knots), self.ocp.u_min, self.ocp.u_max)
        return knots

    def _ranked(self, count: int) -> np.ndarray:
        """Indices of the ``count`` best candidates of the last generation by constraint domination, best first
        (:func:`best_first`)."""
        return best_first(self._results, count)

    def _outcome(self, i: int) -> tuple[float, float]:
        """(cost, violation) of candidate i of the last generation."""
        return float(self._results[i, 0]), float(self._results[i, 1])

    def _start(self, x: np.ndarray, goal: np.ndarray, cold: bool) -> None:
        """Prepare this control step's search: from ``self._guess`` where given, else (warm) from the previous
        step's; ``cold``: from neither."""
        raise NotImplementedError

    def _generation(self, cold: bool) -> tuple[float, float]:
        """One population: sample, roll out, update; returns the (cost, violation) of its best candidate."""
        raise NotImplementedError

    def _result(self, best: tuple[float, float]) -> tuple[np.ndarray, tuple[float, float]]:
        """The knots (p, m) to apply, on the host, and their (cost, violation); ``best``: the last generation's
        best candidate's."""
        raise NotImplementedError
