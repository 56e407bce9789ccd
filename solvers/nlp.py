"""NonlinearMPC: the OCP as a nonlinear program solved by IPOPT (or CasADi's SQP), the "fmincon" baseline.

The paper's first parameterization experiments solved the MPC problem with MATLAB's fmincon (Section
III-C, experimental setup); here the same OCP is transcribed by multiple shooting and handed to IPOPT
through CasADi. Decision
variables are the predicted states x_1 … x_T and the knots U (p, m), with the parameterization substituted
symbolically (u_k = Σ_j φ_kj U_j), so a knot-parameterized problem has p·m input unknowns, not T·m.

``dynamics="nonlinear"`` predicts with the model's discrete dynamics F(x, u) (RK4); ``"affine"`` with the
affine model x⁺ = A_d x + B_d u + w_d about (x, ū), ū chosen by ``linearization`` exactly as in LinearMPC:
LinearMPC's problem solved by a general NLP solver (as the paper did with fmincon).
The NLP is built once per OCP with parameters (x_0, the goal window[, the obstacle window][, A_d, B_d, w_d]) and
re-solved every step, warm-started from the previous primal and dual solution shifted by one step. So a goal that
moves over the horizon (stage k's terms towards row k of the window, the terminal terms towards row T), obstacles that
move (x_k's clearances against their row k) and a user's plan (``initial_guess``: the primal start, its states rolled
out on the discrete model, the multipliers as at a cold start) change parameters and the start, never the NLP
(:mod:`ocpkit.model.reference`). The affine model is expanded about stage 0's goal, as in LinearMPC.

Its derivatives (``hessian``): by default Gauss–Newton. The constraint Jacobian is assembled from the affine
model (A_k, B_k) of every stage, compiled C under the OCP's ``compiled`` policy, and the Hessian of the Lagrangian
is the cost's with the task's residuals linearized inside their squares (Q and R alone without a task), the
curvature of the dynamics and the clearances left out. A KKT point of the NLP is the same, only the rate of
convergence changes (Puma 560, T = 50, 5 knots, 3 closed loops of 20 steps: IPOPT's iterations a step median 6,
4–14, instead of 5, 3–12; 47 ms a step instead of 2.1 s, the same closed-loop cost). ``hessian="exact"`` keeps
CasADi's AD of the whole NLP, the reference.

One more method solves the same NLP (real-time iteration, a QP step per control step, is its own controller:
:class:`ocpkit.solvers.rti.RealTimeIteration`, ``solvers.make("rti", ocp)``):

* ``method="fatrop"``: CasADi's fatrop plugin, an interior-point method that factorizes the KKT system by a
  Riccati recursion over the stages. It needs the variables and constraints in stage order
  [u_0, x_1, u_1, …, x_T] with gap rows x_{k+1} − F(x_k, u_k); with knots (p < T) the knots are the controls of
  stage 0 and are carried along as extra states (U_{k+1} = U_k), so every stage stays a stage. fatrop takes no
  derivative functions, so its Gauss–Newton NLP is written with the dynamics and the task's residuals replaced
  by their first-order models about the current point, frozen by ``casadi.stop_diff``: the same values and first
  derivatives, and the Gauss–Newton Hessian as its exact one. On the Panda (T = 50, 5 knots) it took 153 ms a
  step against IPOPT's 58 ms: CasADi's AD of that graph costs 16 ms an iteration (IPOPT's derivative functions
  6 ms), its own iteration 6 ms as IPOPT's, and it takes more iterations (median 7 against 5).

Which arguments each method takes, with their meaning and default there: :data:`ocpkit.solvers.methods.METHODS`. The
NLP itself, in either order, and its Gauss–Newton derivatives: :class:`ocpkit.solvers.shooting.MultipleShooting`.
"""

from __future__ import annotations

import re
import time

import casadi as ca
import numpy as np

from ocpkit._checks import choice, integer, positive
from ocpkit.codegen.compiled import SwitchingFunction
from ocpkit.controller import Controller, check_linearization
from ocpkit.status import EXCEPTION, INFEASIBLE, LIMITED, NAN, SUCCESS, OperationCosts, Reason, Solution
from ocpkit.model.ocp import OCP
from ocpkit.solvers import methods
from ocpkit.solvers.methods import DYNAMICS, HESSIANS, NONLINEAR
from ocpkit.solvers.shooting import MultipleShooting

METHODS = tuple(methods.METHODS)
SOLVER_NAMES = {"ipopt": "IPOPT", "sqp": "sqpmethod", "fatrop": "fatrop"}
# Solver options NonlinearMPC sets from its own arguments: refused in ``options``, naming the argument.
SET_BY_ARGUMENT = {
    "max_iter": "max_iter",
    "max_wall_time": "time_limit",
    "time_limit": "time_limit",
    "iteration_callback": "time_limit",
}
# How CasADi names an option its solver does not know.
_UNKNOWN = re.compile(r"(?:No such IPOPT option|Unknown option|Fatrop option not supported): (\w+)")

# IPOPT's ApplicationReturnStatus and sqpmethod's return_status, as ocpkit statuses (unlisted: exception).
_STATUS = {
    "Solve_Succeeded": SUCCESS,
    "Solved_To_Acceptable_Level": SUCCESS,
    "Feasible_Point_Found": LIMITED,  # a feasible point of a square problem, no optimality claimed
    "Maximum_Iterations_Exceeded": LIMITED,
    "Maximum_CpuTime_Exceeded": LIMITED,
    "Maximum_WallTime_Exceeded": LIMITED,
    "Search_Direction_Becomes_Too_Small": LIMITED,
    "Infeasible_Problem_Detected": INFEASIBLE,
    "Restoration_Failed": INFEASIBLE,
    "Not_Enough_Degrees_Of_Freedom": INFEASIBLE,
    "Invalid_Number_Detected": NAN,
    "Diverging_Iterates": NAN,
    "User_Requested_Stop": LIMITED,  # sqpmethod stopped by _Deadline at the step's budget
}
# Why a return status is not a success (Solution.reason); a status not named here: by its Status (_FAILED).
_REASON = {
    "Feasible_Point_Found": Reason.NOT_CONVERGED,
    "Maximum_Iterations_Exceeded": Reason.ITERATION_LIMIT,
    "Maximum_CpuTime_Exceeded": Reason.TIME_BUDGET,
    "Maximum_WallTime_Exceeded": Reason.TIME_BUDGET,
    "Search_Direction_Becomes_Too_Small": Reason.NOT_CONVERGED,
    "Infeasible_Problem_Detected": Reason.NLP_INFEASIBLE,
    "Restoration_Failed": Reason.NLP_INFEASIBLE,
    "Not_Enough_Degrees_Of_Freedom": Reason.NLP_INFEASIBLE,
    "User_Requested_Stop": Reason.TIME_BUDGET,
}
_FAILED = {
    LIMITED: Reason.ITERATION_LIMIT,
    INFEASIBLE: Reason.NLP_INFEASIBLE,
    NAN: Reason.NON_FINITE_SOLUTION,
    EXCEPTION: Reason.SOLVER_ERROR,
}


class NonlinearMPC(MultipleShooting, Controller):
    """Multiple-shooting MPC solved as an NLP: ``method`` "ipopt" (interior point), "sqp" (CasADi
    ``sqpmethod`` with the qrqp QP solver) or "fatrop" (structure-exploiting interior point, stage-ordered NLP),
    over the ``dynamics`` "nonlinear" (F) or "affine" model (ipopt and sqp only), with the ``hessian``
    "gauss-newton" (default; derivatives from the per-stage affine model, see the module docstring) or "exact"
    (CasADi's AD of the whole NLP). Real-time iteration is its own controller, :class:`RealTimeIteration`
    (``ocpkit.solvers.rti``, ``solvers.make("rti", ocp)``).

    Each method takes the arguments :data:`ocpkit.solvers.methods.METHODS` lists for it, with their meaning and
    default there (None: that default); one it does not take is refused (ValueError naming the methods that do).
    ``max_iter`` and ``time_limit`` (wall-clock seconds: IPOPT's max_wall_time, checked by SQP after each of its
    iterations; :attr:`ceiling`, 10 s, where none is given; fatrop takes none) limit each solve; a solve stopped by
    either is ``limited`` and falls back. IPOPT checks its clock once per
    iteration, after derivative evaluations it cannot interrupt (with the exact Hessian, 30 ms of constraint
    Jacobian at nlink:7, T=50 before the first check), so with a time limit a solve starts only if the measured
    time of one iteration (median of the last five solves: wall time / (iterations + 1)) fits in the step's
    budget. Both can be changed between steps (the solver is remade over the NLP, which is not rebuilt). ``options``
    pass through to IPOPT (e.g. ``{"tol": 1e-10}``), to ``sqpmethod`` (e.g. ``{"qpsol": "osqp"}``) or to fatrop. An
    option that does not apply to the method — unknown to its solver, or one NonlinearMPC sets from its own arguments
    (SET_BY_ARGUMENT: ``max_iter``, ``max_wall_time`` from ``time_limit``) — is refused at construction
    (ValueError naming the option and the method).
    ``linearization`` ("goal" or "plan") is the affine model's expansion input, as in LinearMPC.
    """

    TAKES = frozenset({"goal window", "obstacles", "initial guess"})

    def __init__(
        self,
        ocp: OCP,
        *,
        method: str = NONLINEAR["method"].default,
        dynamics: str | None = None,
        linearization: str | None = None,
        hessian: str | None = None,
        max_iter: int | None = None,
        time_limit: float | None = None,
        options: dict | None = None,
        warm_start: bool = NONLINEAR["warm_start"].default,
        raise_on_fail: bool = NONLINEAR["raise_on_fail"].default,
    ):
        if not isinstance(ocp, OCP):
            raise TypeError(f"ocp must be an ocpkit OCP, got {type(ocp).__name__}")
        if method == "rti":
            raise ValueError(
                "method 'rti' is its own controller now: solvers.make('rti', ocp, iterations=…) or "
                "ocpkit.solvers.rti.RealTimeIteration(ocp, …)"
            )
        choice(method, METHODS, "method")
        given = {
            "dynamics": dynamics,
            "linearization": linearization,
            "hessian": hessian,
            "max_iter": max_iter,
            "time_limit": time_limit,
            "options": options,
        }
        takes = methods.METHODS[method]
        for name, value in given.items():
            if value is not None and name not in takes:
                raise ValueError(_not_taken(name, method))
        setting = {
            name: takes[name].default if value is None and name in takes else value for name, value in given.items()
        }
        if options is not None and not isinstance(options, dict):
            raise TypeError(f"options must be a dict or None, got {type(options).__name__}")
        _check_options(method, options or {})
        if method == "fatrop" and ocp.task_functions is not None and ocp.task_functions.pairs:
            # Declared as fatrop's stage path constraints (ng per stage after each stage's gap rows) they were
            # solved while inactive, but with a clearance active fatrop stalled at dual infeasibility 2.5e-3 for 200
            # iterations (nlink:3, T = 20), where IPOPT converged in 20.
            raise ValueError(
                "method 'fatrop' takes a task's cost terms but not its obstacles (it stalls on an active "
                "clearance constraint): use method 'ipopt' or solver 'rti'"
            )
        self.method = method
        # fatrop takes no dynamics (it predicts with the nonlinear model) nor linearization
        self.dynamics = choice(setting["dynamics"] or DYNAMICS[0], DYNAMICS, "dynamics")
        self.linearization = check_linearization(setting["linearization"] or "goal")
        self.hessian = choice(setting["hessian"], HESSIANS, "hessian")
        self.options = dict(options or {})
        self.warm_start = bool(warm_start)
        self._limits = (integer(setting["max_iter"], "max_iter", 1), self._checked_time_limit(time_limit))
        self._build(ocp)
        self._costs = OperationCosts()
        super().__init__(ocp, raise_on_fail=raise_on_fail)

    @property
    def max_iter(self) -> int:
        return self._limits[0]

    @max_iter.setter
    def max_iter(self, value: int) -> None:
        self._limits = (integer(value, "max_iter", 1), self._limits[1])
        self._apply_limits()

    # seconds: the budget of a step without a time_limit (IPOPT's max_wall_time, SQP's deadline), as LinearMPC's
    # ceiling: without it an IPOPT or SQP step had no bound at all
    ceiling = 10.0

    @property
    def time_limit(self) -> float | None:
        return self._limits[1]

    @time_limit.setter
    def time_limit(self, value: float | None) -> None:
        self._limits = (self._limits[0], self._checked_time_limit(value))
        self._apply_limits()

    def _apply_limits(self) -> None:
        """Put ``max_iter`` and ``time_limit`` in force: the NLP solver made anew over the NLP built once (the build
        cost 0.14 s on nlink:7, T = 50, and warm_up's two changes of the time limit made two)."""
        self._solver = self._nlpsol()

    def _checked_time_limit(self, value):
        if value is None:
            return None
        if "time_limit" not in methods.METHODS[self.method]:
            raise ValueError(_not_taken("time_limit", self.method))
        return positive(value, "time_limit")

    @property
    def path(self) -> str:
        """The NLP solver's name (the method)."""
        return self.method

    def __repr__(self):
        return f"NonlinearMPC({self.method}, {self.dynamics}, {self.ocp!r})"

    def _nlpsol(self) -> ca.Function:
        """The NLP solver over the built NLP (``_nlp``: plugin, problem, options) with ``max_iter``, the time limit
        (IPOPT's max_wall_time) and ``options`` in its options."""
        plugin, nlp, opts = self._nlp
        limits = {"max_iter": self.max_iter}
        if self.method == "ipopt":
            limits["max_wall_time"] = self.ceiling if self.time_limit is None else self.time_limit
        if plugin == "sqpmethod":
            opts = {**opts, **limits, **self.options}
        else:
            opts = {**opts, plugin: {**opts[plugin], **limits, **self.options}}
        try:
            return ca.nlpsol("nonlinear_mpc", plugin, nlp, opts)
        except RuntimeError as exc:
            raise _refused(self.method, exc) from None

    def reset(self) -> None:
        super().reset()
        self._warm = None  # (w, lam_x, lam_g) of the last successful solve

    def _discard(self) -> None:
        self._warm = None

    def _solve(self, x: np.ndarray, goal: np.ndarray) -> Solution:
        ocp, times = self.ocp, {"model": 0.0, "build": 0.0, "solve": 0.0}
        n, m, T, p = ocp.nx, ocp.nu, ocp.horizon, ocp.knots
        t0 = time.perf_counter()
        if isinstance(self._stage_model, SwitchingFunction) and self._stage_model.compiled() is not None:
            self._build(ocp)  # the background compile finished: the compiled affine model into the derivatives
            times["build"] = time.perf_counter() - t0
            t0 = time.perf_counter()
        params = [x, self.goal_window.ravel()]  # (T+1, ng) by rows: the NLP's (ng, T+1) by columns
        if self._pairs:  # x_1 … x_T's obstacles, (T, N, 4) by rows: the NLP's (4, N·T) by columns
            params.append(self.obstacle_window[1:].ravel())
        if self.dynamics == "affine":
            model = self.affine_model(x, goal, self.linearization)
            if model is None:
                times["model"] = time.perf_counter() - t0
                return self._fail(
                    NAN, f"non-finite affine model at x = {x.tolist()}", times, reason=Reason.NON_FINITE_MODEL
                )
            Ad, Bd, wd = model
            params += [Ad.ravel(order="F"), Bd.ravel(order="F"), wd]
        t1 = time.perf_counter()
        times["model"] = t1 - t0
        w0, lam_x0, lam_g0 = self._initial_guess(x, goal)
        if self._order is not None:  # fatrop's stage order; the carried knot copies start at the knots
            w, (lam_x0, lam_g0) = np.empty(self._lbx.size), (None, None)
            w[self._order] = w0
            for start in self._copies:
                w[start : start + p * m] = w0[self._nX :]
            w0 = w
        args = {
            "x0": w0,
            "p": np.concatenate(params),
            "lbx": self._lbx,
            "ubx": self._ubx,
            "lbg": self._lbg,
            "ubg": self._ubg,
        }
        if lam_x0 is not None:
            args.update(lam_x0=lam_x0, lam_g0=lam_g0)
        t2 = time.perf_counter()
        times["build"] += t2 - t1
        left = self.remaining(self.time_limit)
        # A solve costs at least its set-up and one iteration (max_wall_time is checked after an iteration): two.
        if not self._costs.fits("iteration", None if left is None else left / 2):
            return self.fallback(
                LIMITED,
                f"time budget: {1e3 * max(left, 0.0):.3g} ms left, an IPOPT iteration "
                f"measured at {1e3 * self._costs.predict('iteration'):.3g} ms (a solve "
                f"is at least two)",
                times,
                reason=Reason.TIME_BUDGET,
            )
        if self.method == "sqp":
            self._deadline.deadline = self.deadline(self.ceiling if self.time_limit is None else self.time_limit)
        try:
            res = self._solver(**args)
        except Exception as exc:  # a solver that throws must not stop the control loop
            times["solve"] = time.perf_counter() - t2
            return self._fail(EXCEPTION, f"{type(exc).__name__}: {exc}", times, reason=Reason.SOLVER_ERROR)
        times["solve"] = time.perf_counter() - t2
        try:
            stats = self._solver.stats()
            raw = str(stats["return_status"])
        except (RuntimeError, KeyError):  # sqpmethod can stop (e.g. on a failed QP) without a return status
            stats, raw = {}, "no return status"
        iterations = int(stats.get("iter_count", 0))
        self._costs.add("iteration", times["solve"] / (iterations + 1))
        status = _STATUS.get(raw, EXCEPTION)
        if self._order is not None and raw not in _STATUS:  # fatrop: a return code and its success flag
            raw = f"fatrop return status {raw}"
            status = SUCCESS if stats.get("success", False) else LIMITED if iterations >= self.max_iter else EXCEPTION
        w = np.asarray(res["x"], dtype=float).ravel()
        lam_x = np.asarray(res["lam_x"], dtype=float).ravel()
        if self._order is not None:
            w, lam_x = w[self._order], lam_x[self._order]
        if status == SUCCESS and not np.isfinite(w).all():
            status = NAN
        if status != SUCCESS:
            return self._fail(status, raw, times, iterations, reason=_REASON.get(raw, _FAILED[status]))
        self._warm = (w, lam_x, np.asarray(res["lam_g"], dtype=float).ravel())
        # IPOPT relaxes bounds by its bound_relax_factor (1e-8 relative); project the knots back.
        knots = np.clip(w[self._nX :].reshape(p, m), ocp.u_min, ocp.u_max)
        x_pred = np.vstack([x, w[: self._nX].reshape(T, n)])
        return Solution(
            u=ocp.parameterization.u_at(knots, 0),
            knots=knots,
            status=SUCCESS,
            raw_status=raw,
            iterations=iterations,
            x_pred=x_pred,
            times=times,
        )

    def _initial_guess(self, x: np.ndarray, goal: np.ndarray):
        """A user's plan (``initial_guess``): its knots (clipped) and the states they roll out to from x_0 (held at
        x_0 where the rollout is not finite), no multipliers. Cold: states held at x_0 and knots at the input goal
        u_g (clipped). Warm: the previous solution shifted a step."""
        ocp, n, T = self.ocp, self.ocp.nx, self.ocp.horizon
        if self.guess is not None:
            knots = np.clip(self.guess, ocp.u_min, ocp.u_max)
            states = self.rollout(x, ocp.parameterization.inputs(knots))[1:]
            if not np.isfinite(states).all():
                states = np.tile(x, (T, 1))
            return np.r_[states.ravel(), knots.ravel()], None, None
        if self._warm is None or not self.warm_start:
            knots = self.goal_knots(goal)
            return np.r_[np.tile(x, T), knots.ravel()], None, None
        w, lam_x, lam_g = self._warm
        shifted = ocp.parameterization.shift(w[self._nX :].reshape(ocp.knots, ocp.nu))
        lam_u = lam_x[self._nX :]
        if ocp.parameterization.kind == "identity":
            lam_u = _shift_blocks(lam_u, ocp.nu)
        # Knot bound multipliers stay put otherwise: knots sit at fixed fractions of the horizon.
        lam_gaps, lam_clear = lam_g[: self._gaps], lam_g[self._gaps :]
        if self._pairs:
            lam_clear = _shift_blocks(lam_clear, self._pairs)
        return (
            np.r_[_shift_blocks(w[: self._nX], n), shifted.ravel()],
            np.r_[_shift_blocks(lam_x[: self._nX], n), lam_u],
            np.r_[_shift_blocks(lam_gaps, n), lam_clear],
        )

    def _fail(self, status, raw, times, iterations=0, *, reason: Reason) -> Solution:
        """Fallback solution and a cold start for the next step (no stale warm start)."""
        self._warm = None
        return self.fallback(status, raw, times, iterations, reason=reason)


def _not_taken(argument: str, method: str) -> str:
    """Why ``argument`` is refused for ``method``: the methods that take it
    (:data:`ocpkit.solvers.methods.METHODS`)."""
    return (
        f"{argument} does not apply to method {method!r}: it applies to methods {', '.join(methods.taking(argument))}"
    )


def _check_options(method: str, options: dict) -> None:
    """Refuse (ValueError) an option NonlinearMPC sets from its own arguments, or one fatrop rejects; IPOPT and
    sqpmethod check theirs as they are made (:meth:`NonlinearMPC._nlpsol`)."""
    for name in options:
        argument = SET_BY_ARGUMENT.get(name)
        if argument is not None and argument not in methods.METHODS[method]:
            raise ValueError(f"option {name!r} does not apply to method {method!r}: it takes no {argument}")
        if argument is not None:
            raise ValueError(
                f"option {name!r} does not apply to method {method!r}: NonlinearMPC sets it from its "
                f"argument; use {argument}="
            )
    if method == "fatrop" and options:
        _check_fatrop_options(options)


def _refused(method: str, exc: RuntimeError) -> ValueError:
    """The ValueError for options ``method``'s solver rejected with ``exc``: one line naming the option where CasADi
    says which."""
    unknown = _UNKNOWN.search(str(exc))
    if unknown:
        return ValueError(
            f"option {unknown.group(1)!r} does not apply to method {method!r} (not one of "
            f"{SOLVER_NAMES[method]}'s options)"
        )
    return ValueError(f"options rejected by {method}: {' '.join(str(exc).split())}")


def _check_fatrop_options(options: dict) -> None:
    """fatrop reads its options at the first solve (an unknown one made every step an "exception"): try them on a
    one-stage NLP, a few milliseconds, and refuse what it rejects (:func:`_refused`)."""
    w = ca.MX.sym("w", 2)
    opts = {
        "structure_detection": "manual",
        "N": 1,
        "nx": [0, 1],
        "nu": [1, 0],
        "ng": [0, 0],
        "print_time": False,
        "error_on_fail": False,
        "fatrop": {"print_level": 0, **options},
    }
    try:
        ca.nlpsol("fatrop_options", "fatrop", {"x": w, "f": ca.sumsqr(w), "g": w[1] - w[0]}, opts)(x0=0, lbg=0, ubg=0)
    except RuntimeError as exc:
        raise _refused("fatrop", exc) from None


def _shift_blocks(v: np.ndarray, size: int) -> np.ndarray:
    """A stacked per-step vector advanced one step (blocks of ``size``), its last block repeated."""
    return np.r_[v[size:], v[-size:]]


SOLVERS = {"ipopt": NonlinearMPC}
