"""The controller interface every solver implements (its statuses and Solution: :mod:`ocpkit.status`).

A Controller is anything with ``reset()`` and ``solve(x, goal) -> Solution``. A solver that fails at run
time does not raise inside a control loop: its Solution carries a non-success status and a safe fallback
input — the previous plan advanced one step while its prediction stays finite, within the state bounds and clear
of obstacles (for at most ``stale_steps`` refused steps in a row), else a brake to rest within the input bounds
(:mod:`ocpkit.safety`). A success certifies the task as well as the optimizer: its plan, rolled out on the
controller's nonlinear model, keeps every obstacle clearance and state bound, or the step is "soft".
"""

from __future__ import annotations

import threading
import time
import warnings

import numpy as np

from ocpkit._checks import choice, integer, positive
from ocpkit.codegen.compiled import SwitchingFunction
from ocpkit.numeric import BufferedFunction, ThreadLimit
from ocpkit.model.ocp import OCP
from ocpkit.safety import Brake, PlanCheck, spectral_radius
from ocpkit.status import INFEASIBLE, LIMITED, NAN, SOFT, OperationCosts, Reason, Solution

LINEARIZATIONS = ("goal", "plan")
# LinearMPC also linearizes stage by stage along the shifted plan (LTV); other controllers take one model.
TRAJECTORY = "trajectory"

# A state or goal farther than STATE_SCALE times the problem's scale from the origin makes every QP
# meaningless (ProxQP ran 54 s at x = 1e20 on the pendulum): it is answered "nan" before any solver runs.
# The problem's scale is max(1, the largest finite |state bound|).
STATE_SCALE = 1e6
# Largest violation of an input bound accepted from a solver that reports success (as ocpkit.export's
# FEAS_TOL); within it, u and the knots are clipped to the bounds.
BOUND_TOL = 1e-6


def bound_scale(lower, upper) -> float:
    """max(1, the largest finite |bound|): the scale of a pair of bound vectors."""
    finite = np.abs(np.concatenate([lower, upper]))
    return max(1.0, float(finite[np.isfinite(finite)].max(initial=0.0)))


def state_limit(ocp: OCP) -> float:
    """|x|, |goal| beyond which a step is answered "nan" without a solve: STATE_SCALE × the problem's scale."""
    return STATE_SCALE * bound_scale(ocp.x_min, ocp.x_max)


def check_linearization(mode: str, trajectory: bool = False) -> str:
    """A valid choice of the affine model's expansion input (see :meth:`Controller.affine_model`); with
    ``trajectory`` also "trajectory", one model per stage (see :meth:`Controller.affine_models`)."""
    choice(mode, LINEARIZATIONS + ((TRAJECTORY,) if trajectory else ()), "linearization")
    return mode


class SolverError(RuntimeError):
    """Raised by ``solve`` for a failed step when the controller was built with ``raise_on_fail=True``."""


class Controller:
    """Base class: keeps the last plan for warm starts and fallbacks; subclasses implement ``_solve``.

    ``solve`` wraps every solver's ``_solve`` with what real-time use needs:

    * a per-controller lock: one controller used from several threads at once solves one step at a time
      (its workspace, warm start and plan are never shared by two steps in flight);
    * BLAS/OpenMP threads limited to ``threads`` (1 by default; None leaves them alone) through threadpoolctl;
    * states or goals beyond ``state_limit`` (STATE_SCALE × the problem's scale) answered "nan" at once;
    * verification before "success": finite u and knots, input bounds violated by at most ``BOUND_TOL``
      (then clipped), otherwise the fallback with status "limited";
    * the task certificate of a success (:class:`ocpkit.safety.PlanCheck`, where the OCP has obstacles or state
      bounds): the plan rolled out on the nonlinear model keeps every clearance and state bound, else the step is
      "soft" (its input applied; the violation in ``violation`` and ``reason``, in words in ``raw_status``), or
      refused where the prediction is not finite or collides within ``COLLISION_AHEAD`` steps (deeper than the
      start: a start inside an obstacle may still move);
    * a safe fallback on a refused step (:meth:`fallback`); ``stale_steps`` (settable, default STALE_STEPS) bounds
      how many refused steps in a row may replay the previous plan before the controller brakes;
    * a state outside the model's trust region — a bounded joint velocity beyond ``TRUST_REGION`` times its bound —
      answered "infeasible" with the brake, before any solver runs;
    * at the first step after :meth:`reset`, a RuntimeWarning where the discrete model diverges numerically at the
      start (|eig A_d| beyond what the continuous dynamics explain: the integrator's step is too long).

    A "soft" step does not raise with ``raise_on_fail``: its input is the solver's answer.
    """

    STALE_STEPS = 5  # the default of ``stale_steps``: 50 ms of replayed plan at 100 Hz
    # A joint velocity beyond this many times its bound leaves the model's trust region: no solve, the brake. The
    # Panda's RTI, re-solving from 6-15 rad/s (limits 2.2-2.6), planned torques at their limits that spun it further.
    TRUST_REGION = 1.5
    # A plan whose nonlinear prediction collides (deeper than the start) within this many steps is refused: the
    # sampling planners, judging collisions on the affine model, had applied such plans as "soft" on the Panda.
    COLLISION_AHEAD = 5
    # What a step takes beyond a held goal (solve's arguments): "goal window" (a goal that moves over the horizon),
    # "obstacles" (where the task's obstacles are now), "initial guess" (a user's plan)
    TAKES: frozenset = frozenset()

    def __init__(self, ocp: OCP, *, raise_on_fail: bool = False, threads: int | None = 1):
        if not isinstance(ocp, OCP):
            raise TypeError(f"ocp must be an ocpkit OCP, got {type(ocp).__name__}")
        self.ocp = ocp
        self.raise_on_fail = bool(raise_on_fail)
        self.threads = threads
        self.state_limit = state_limit(ocp)
        self._input_scale = bound_scale(ocp.u_min, ocp.u_max)  # BOUND_TOL's scale
        self._lock = threading.RLock()
        self._step_start = None  # perf_counter at the start of the step in flight (time budgets count from it)
        self._affine_model = None  # the OCP's affine model, bound to numpy buffers at its first use
        self._affine_map = None  # (threads, the same mapped over the horizon): per-stage models; and the rollout
        self._rollout = None
        self.stale_steps = self.STALE_STEPS
        self._plan_check = PlanCheck(ocp)
        self._check_costs = OperationCosts()  # the certificate's measured time, kept out of the solvers' budgets
        self._brake = Brake(ocp)
        self._declared = ocp.obstacle_window()  # the task's declared obstacles at every stage (None: it has none)
        nq = ocp.model.second_order
        velocities = np.arange(nq or 0, ocp.nx if nq else 0)
        bound = np.maximum(np.abs(ocp.x_min[velocities]), np.abs(ocp.x_max[velocities]))
        self._trusted = velocities[np.isfinite(bound)], self.TRUST_REGION * bound[np.isfinite(bound)]
        self.reset()

    @property
    def threads(self) -> int | None:
        """BLAS/OpenMP threads inside a step (threadpoolctl); None: not limited."""
        return self._threads

    @threads.setter
    def threads(self, value: int | None) -> None:
        self._threads = None if value is None else integer(value, "threads", 1)

    @property
    def stale_steps(self) -> int:
        """Refused steps in a row that may replay the previous plan (while it is safe) before the brake."""
        return self._stale_steps

    @stale_steps.setter
    def stale_steps(self, value: int) -> None:
        self._stale_steps = integer(value, "stale_steps", 0)

    @property
    def state_limit(self) -> float:
        """Largest |x_i| or |goal_i| a step accepts; beyond it the step is "nan" without a solve."""
        return self._state_limit

    @state_limit.setter
    def state_limit(self, value: float) -> None:
        self._state_limit = positive(value, "state_limit")

    def reset(self) -> None:
        """Forget the previous plan (cold start)."""
        self.plan: np.ndarray | None = None  # knots (p, m) of the last step: the solver's plan, or the fallback's
        self._goal = np.zeros(self.ocp.nx)
        self._x = np.zeros(self.ocp.nx)  # the state of the step in flight (the fallback brakes from it)
        self.task_goal = np.zeros(self.ocp.ng)
        self.goal_window = np.zeros((self.ocp.horizon + 1, self.ocp.ng))
        self.moving, self.obstacle_window, self.guess = False, self._declared, None
        self._refused = 0  # refused steps in a row
        self._first_step = True  # the divergence warning is due

    def solve(self, x, goal, *, obstacles=None, initial_guess=None) -> Solution:
        """Solve the MPC problem from state x towards ``goal``; return the first input and more.

        ``goal`` is the goal state, or with a task (``ocp.task``) the goal vector [x_goal; targets] of
        :meth:`OCP.goal`, held over the horizon; or the goal at every stage k = 0 … T, (T+1, ng): a reference's
        window (:mod:`ocpkit.model.reference`). ``obstacles``: where the task's obstacles are now, (N, 4) (centre,
        radius), or at every stage, (T+1, N, 4); None: where the task declares them. ``initial_guess``: a plan to
        start from instead of the previous step's, as knots (p, m) or inputs (T, m). A controller takes what its
        class lists in ``TAKES`` and refuses the rest naming it.

        Solvers' ``_solve`` receive stage 0's x_goal; the whole goal vector of stage 0 is ``self.task_goal``, the
        window ``self.goal_window`` (``self.moving``: whether it moves), the obstacles ``self.obstacle_window`` and
        the guess's knots ``self.guess`` (None: none given)."""
        ocp = self.ocp
        x = ocp.check_state(x, "x")
        window = ocp.goal_window(goal)
        moving = window.strides[0] != 0 and bool((window != window[0]).any())  # a held goal's rows are one row
        obstacle_window = self._declared if obstacles is None else ocp.obstacle_window(obstacles)
        guess = None if initial_guess is None else ocp.guess_knots(initial_guess)
        for given, what in (
            (moving, "goal window"),
            (obstacles is not None, "obstacles"),
            (guess is not None, "initial guess"),
        ):
            if given and what not in self.TAKES:
                raise ValueError(
                    f"{type(self).__name__} does not take a moving {what} yet (it takes: "
                    f"{', '.join(sorted(self.TAKES)) or 'a held goal only'})"
                )
        full = window[0]
        goal = full[: ocp.nx]
        with self._lock, ThreadLimit(self._threads):
            start = self._step_start = time.perf_counter()
            self._goal = goal  # for the fallback's cold-start input
            self._x = x
            self.task_goal, self.goal_window, self.moving = full, window, moving
            self.obstacle_window, self.guess = obstacle_window, guess
            big = max(np.abs(x).max(initial=0.0), np.abs(window if moving else full).max(initial=0.0))
            if big > self._state_limit:
                sol = self.fallback(
                    NAN,
                    f"state or goal magnitude {big:.3g} beyond state_limit {self._state_limit:.3g}: no solver run",
                    reason=Reason.STATE_BEYOND_LIMIT,
                )
            elif outside := self._outside_trust_region(x):
                sol = self.fallback(INFEASIBLE, outside, replay=False, reason=Reason.OUTSIDE_TRUST_REGION)
            else:
                if self._first_step:
                    self._warn_divergence(x, goal)
                path = self.path
                sol = self._certified(x, self._verified(self._solve(x, goal)))
                sol.path = sol.path or path
            sol.times["total"] = time.perf_counter() - start
            self._step_start = None
            self._first_step = False
            if sol.fallback and self.raise_on_fail:
                raise SolverError(f"{type(self).__name__} failed: {sol.status} ({sol.raw_status})")
            self._refused = self._refused + 1 if sol.fallback else 0
            self.plan = sol.knots  # a fallback's too, so repeated failures keep advancing it
            return sol

    def warm_up(self, x, goal, steps: int = 2) -> Solution:
        """``steps`` steps from x towards ``goal`` without the time budget (``time_limit``, where the solver has
        one); the last one's solution.

        The first step of a new controller measures what its operations cost and so is not bounded; call this
        once before a real-time loop (with its first state and goal) and every step of the loop is. The second
        step is warm, as the loop's will be, and outweighs the first's one-off costs in the measurements. The
        fallback is computed once too (and dropped): the first run of its code is slow, and the loop's first refused
        step would pay it on top of its budget."""
        steps = integer(steps, "steps", 1)
        limit = getattr(self, "time_limit", None)
        if limit is not None:
            self.time_limit = None
        try:
            for _ in range(steps):
                sol = self.solve(x, goal)
            self.fallback(LIMITED, "warm-up")
            return sol
        finally:
            if limit is not None:
                self.time_limit = limit

    @property
    def path(self) -> str:
        """What answers the next step, in a few words (in every Solution as ``path``, and in ``repr``): solvers
        with a slower start-up path say which one runs until the fast one is ready."""
        return type(self).__name__

    def wait_compiled(self, timeout: float | None = None) -> bool:
        """Block until the OCP's affine model has switched to compiled C after its background compile (tests,
        benchmarks: the steady state); whether compiled code is in place (False: it stays on the VM)."""
        fn = self.ocp.affine()
        if isinstance(fn, SwitchingFunction):
            return fn.wait(timeout) is not None
        return fn.class_name() == "External"

    def _verified(self, sol: Solution) -> Solution:
        """``sol`` if it is a usable success (u and knots finite, within the input bounds up to BOUND_TOL, then
        clipped to them); otherwise the fallback with a non-success status. Failures pass through."""
        if not sol.ok:
            return sol
        ocp = self.ocp
        u, knots = np.asarray(sol.u, dtype=float), np.asarray(sol.knots, dtype=float)
        # Clipped first: how far clipping moved an entry is its bound violation (NaN or inf where it is not finite):
        # one pass where a finiteness test and four differences took 12 us of a 0.2 ms step
        u_in, knots_in = u.clip(ocp.u_min, ocp.u_max), knots.clip(ocp.u_min, ocp.u_max)
        moved = float(np.abs(u_in - u).max(initial=0.0)), float(np.abs(knots_in - knots).max(initial=0.0))
        limit = BOUND_TOL * self._input_scale
        if not (moved[0] <= limit and moved[1] <= limit):
            if not (np.isfinite(u).all() and np.isfinite(knots).all()):
                return self._rejected(NAN, f"{sol.raw_status} with non-finite result", sol, Reason.NON_FINITE_SOLUTION)
            return self._rejected(
                LIMITED, f"{sol.raw_status} but an input bound violated by {max(moved):.3g}", sol, Reason.INPUT_BOUND
            )
        sol.u, sol.knots = u_in, knots_in
        return sol

    def _certified(self, x: np.ndarray, sol: Solution) -> Solution:
        """``sol`` if it is no success or its plan passes the task certificate (:class:`ocpkit.safety.PlanCheck`);
        "soft" where the plan breaks a clearance or a state bound; refused where its prediction diverges ("nan") or
        collides within COLLISION_AHEAD steps ("infeasible")."""
        if not (sol.ok and self._plan_check.needed):
            return sol
        start = time.perf_counter()
        xs = self.rollout(x, self.ocp.parameterization.inputs(sol.knots))
        violation = self._plan_check.violation(xs, ahead=self.COLLISION_AHEAD, obstacles=self._moved_obstacles())
        self._check_costs.add("certificate", time.perf_counter() - start)
        if violation is None:
            return sol
        if violation.kind in (Reason.NON_FINITE_PREDICTION, Reason.COLLISION):
            return self._rejected(
                NAN if violation.kind is Reason.NON_FINITE_PREDICTION else INFEASIBLE,
                f"{sol.raw_status} but its {violation}",
                sol,
                violation.kind,
            )
        sol.status, sol.raw_status, sol.violation = SOFT, f"{sol.raw_status}; soft: {violation}", violation
        sol.reason = violation.kind
        return sol

    def _moved_obstacles(self) -> np.ndarray | None:
        """The step's obstacle window where it is not the declared obstacles' (None: the declared ones)."""
        return None if self.obstacle_window is self._declared else self.obstacle_window

    def _outside_trust_region(self, x: np.ndarray) -> str:
        """Why x is outside the model's trust region (a joint velocity beyond TRUST_REGION times its bound), or ""."""
        index, limit = self._trusted
        excess = np.abs(x[index]) - limit
        if not index.size or excess.max() <= 0.0:
            return ""
        i = int(np.argmax(excess))
        return (
            f"x[{int(index[i])}] = {x[index[i]]:.3g} beyond {self.TRUST_REGION:g} x its bound "
            f"{limit[i] / self.TRUST_REGION:.3g}: outside the model's trust region, no solver run"
        )

    def _warn_divergence(self, x: np.ndarray, goal: np.ndarray) -> None:
        """Warn where the discrete model about (x, u_g) grows faster than the continuous dynamics do: |eig A_d|
        above max(1, exp(dt · max Re eig A_c)) by more than 5 % (an integrator step too long for the stiffest
        joint, as for a light wrist at 10 ms)."""
        ocp = self.ocp
        u = np.clip(ocp.input_goal(goal), ocp.u_min, ocp.u_max)
        rho = spectral_radius(ocp, x, u)
        Ac = np.asarray(ocp.model.jacobian(x, u)[1], dtype=float)
        if not (np.isfinite(rho) and np.isfinite(Ac).all()):
            return
        expected = max(1.0, float(np.exp(ocp.dt * np.linalg.eigvals(Ac).real.max())))
        if rho > 1.05 * expected:
            warnings.warn(
                f"{type(self).__name__}: the controller's discrete model diverges at the start: |eig A_d| = "
                f"{rho:.3g} a step where the continuous dynamics grow by {expected:.3g}; its "
                f"{ocp.integrator} step of {ocp.dt / ocp.substeps:g} s is too long for the model: more "
                f"substeps, e.g. problem.ocp(..., substeps={2 * ocp.substeps}), should help",
                RuntimeWarning,
                stacklevel=3,
            )

    def _rejected(self, status: str, raw: str, sol: Solution, reason: Reason) -> Solution:
        """A "success" that failed verification: the solver's workspace is stale, so reset it (``_discard``)."""
        self._discard()
        return self.fallback(status, raw, sol.times, sol.iterations, reason=reason)

    def _discard(self) -> None:
        """Drop solver state a rejected result may have left (warm starts, workspaces); subclasses extend."""

    def deadline(self, budget: float | None) -> float | None:
        """The perf_counter time by which the solver must be done for the step to keep ``budget`` (None: no budget,
        or an infinite one): the step's start plus the budget, less the task certificate's measured time."""
        if budget is None or budget == float("inf") or self._step_start is None:
            return None
        return self._step_start + budget - self._check_costs.predict("certificate")

    def remaining(self, budget: float | None) -> float | None:
        """Seconds left to the solver of a step budget ``budget`` counted from the start of the step in flight (None:
        no budget), less the task certificate's measured time (it runs after the solver, inside the budget)."""
        end = self.deadline(budget)
        return None if end is None else end - time.perf_counter()

    def _solve(self, x: np.ndarray, goal: np.ndarray) -> Solution:
        raise NotImplementedError

    def affine_model(self, x: np.ndarray, goal: np.ndarray, mode: str):
        """(A_d, B_d, w_d) of the OCP's affine model about (x, ū), or None if any entry is not finite.

        ū is the input goal u_g(goal) for ``mode`` "goal", or for "plan" the input the previous plan
        expects now (u_g at a cold start), the step's initial guess's first where given. LinearMPC documents why
        "goal" is the default.
        """
        ocp, par = self.ocp, self.ocp.parameterization
        u_bar = (
            ocp.input_goal(goal)
            if (self.plan is None and self.guess is None) or mode == "goal"
            else par.u_at(par.shift(self.plan) if self.guess is None else self.guess, 0)
        )
        if self._affine_model is None:
            self._affine_model = BufferedFunction(ocp.affine())
        Ad, Bd, wd = self._affine_model(x, u_bar)
        if not (np.isfinite(Ad).all() and np.isfinite(Bd).all() and np.isfinite(wd).all()):
            return None
        return Ad, Bd, wd.ravel()

    def affine_models(self, xs: np.ndarray, us: np.ndarray):
        """Per-stage affine models (A_k, B_k, w_k), (T, n, n), (T, n, m), (T, n), about (x̄_k, ū_k) for the rows of
        ``xs`` (T, n) and ``us`` (T, m) — one call of the OCP's affine model mapped over the horizon
        (``Function.map``) — or None if any entry is not finite. The LTV model of real-time iteration.

        These T evaluations are nearly all of an LTV/RTI step. With ``ocp.compiled`` the mapped model is the
        compiled C one (:meth:`OCP.affine`, a CasADi external mapped serially), the same numbers as the SX virtual
        machine's. With ``threads`` > 1 the stages are split over that many threads (``map(T, "thread", threads)``);
        the default 1 evaluates them in the calling thread (a second thread only competes with other processes)."""
        ocp = self.ocp
        n, m, T = ocp.nx, ocp.nu, ocp.horizon
        parallel = min(self._threads or 1, T)
        if self._affine_map is None or self._affine_map[0] != parallel:
            fn = ocp.affine()
            mapped = fn.map(T) if parallel == 1 else fn.map(T, "thread", parallel)
            self._affine_map = (parallel, BufferedFunction(mapped))
        A, B, w = self._affine_map[1](np.asarray(xs, dtype=float).T, np.asarray(us, dtype=float).T)
        if not (np.isfinite(A).all() and np.isfinite(B).all() and np.isfinite(w).all()):
            return None
        return A.reshape(n, T, n).transpose(1, 0, 2), B.reshape(n, T, m).transpose(1, 0, 2), w.T

    def rollout(self, x: np.ndarray, us: np.ndarray) -> np.ndarray:
        """States x_0 … x_T (T+1, n) of the OCP's discrete model from x under the inputs ``us`` (T, m), in one call
        (``Function.mapaccum``)."""
        ocp = self.ocp
        if self._rollout is None:
            self._rollout = BufferedFunction(ocp.discrete().mapaccum(ocp.horizon))
        (X,) = self._rollout(x, np.asarray(us, dtype=float).T)
        return np.vstack([x, X.T])

    def goal_knots(self, goal) -> np.ndarray:
        """The input goal u_g held at every knot and clipped to the input bounds: the cold-start plan."""
        ocp = self.ocp
        return np.clip(np.tile(ocp.input_goal(goal), (ocp.knots, 1)), ocp.u_min, ocp.u_max)

    # C twin: step.in.c fallback() and shifted_knots() (the "plan" replay); parity: tests/test_twins.py
    def fallback(
        self,
        status: str,
        raw_status: str,
        times: dict | None = None,
        iterations: int = 0,
        *,
        replay: bool = True,
        reason: Reason | None = None,
    ) -> Solution:
        """A refused step's safe input, said in ``path``: "fallback (plan)", the previous plan advanced one step, with
        ``replay``, for at most ``stale_steps`` refused steps in a row and only while its prediction from x is finite
        and keeps the task (:class:`ocpkit.safety.PlanCheck`); otherwise "fallback (brake)", the input that brings the
        joint velocities closest to rest within the input bounds (:class:`ocpkit.safety.Brake`), or "fallback (hold)",
        the input goal, for a model that is not x = [q, q̇]. Replaying a stale plan had spun the Panda to 1,400 rad/s."""
        ocp, par = self.ocp, self.ocp.parameterization
        knots, kind = None, "plan"
        if replay and self._refused < self.stale_steps:
            knots = self.goal_knots(self._goal) if self.plan is None else par.shift(self.plan)
            knots = np.clip(np.nan_to_num(knots), ocp.u_min, ocp.u_max)
            if self._plan_check.needed and self._plan_check.violation(
                self.rollout(self._x, par.inputs(knots)), obstacles=self._moved_obstacles()
            ):
                knots = None
        if knots is None:
            u_hold = np.clip(ocp.input_goal(self._goal), ocp.u_min, ocp.u_max)
            u = self._brake(self._x, u_hold)
            kind = "hold" if u is None else "brake"
            knots = np.tile(u_hold if u is None else u, (ocp.knots, 1))
        u = np.clip(par.u_at(knots, 0), ocp.u_min, ocp.u_max)
        times = dict(times or {"model": 0.0, "build": 0.0, "solve": 0.0, "total": 0.0})
        return Solution(
            u=u,
            knots=knots,
            status=status,
            raw_status=raw_status,
            iterations=iterations,
            times=times,
            fallback=True,
            path=f"fallback ({kind})",
            reason=reason,
        )
