"""LinearMPC: re-linearized convex MPC, sparse or condensed, with any input parameterization (paper Section V).

Each control step linearizes the model about the current state and the input the previous plan
expected now, builds the chosen transcription from the affine model (A_d, B_d, w_d), and solves the QP
with DAQP (the condensed form's default), ProxQP (dense backend for the condensed form, sparse for the sparse
form), OSQP (the paper's own solver) or HPIPM. Input bounds are imposed on the knots, which keeps the whole
piecewise-linear (or zero-order-hold) input trajectory within bounds because every u_k is a convex combination of
knots. In the default configuration a robot's step runs as compiled C once it is built (:mod:`ocpkit.export.native`).
"""

from __future__ import annotations

import threading
import time
import warnings
import weakref

import numpy as np

from ocpkit.export import native as _native
from ocpkit._checks import choice, integer, positive
from ocpkit.qp.certificate import certify
from ocpkit.controller import Controller, check_linearization
from ocpkit.status import EXCEPTION, INFEASIBLE, LIMITED, NAN, SUCCESS, OperationCosts, Reason, Solution
from ocpkit.export import ExportedMPC
from ocpkit.numeric import BufferedFunction
from ocpkit.model.ocp import OCP
from ocpkit.qp.backends import QP_SOLVERS, make_backend
from ocpkit.qp.interface import Result, skipped, time_left
from ocpkit.qp.sensitivity import feedback_gain
from ocpkit.safety import spectral_radius
from ocpkit.qp.sparse import SparseQP
from ocpkit.qp.transcription import CondensedQP

DEFAULT_QP = {"condensed": "daqp", "sparse": "proxqp"}  # LinearMPC's qp=None, by form
TRANSCRIPTIONS = {"sparse": SparseQP, "condensed": CondensedQP}  # the forms, by name
SOFTENED_AFTER_C = "Python step (softened QP after the C step)"  # the path of a step the C step handed back


class LinearMPC(Controller):
    """Re-linearized MPC through a QP (paper Section V). Each step linearizes the model, transcribes the OCP into the
    ``form`` "condensed" (small matrix: the knots) or "sparse" (large matrix: knots and states) QP and solves it with
    ``qp``: "daqp" (dense active set, condensed form only; its default), "proxqp" (the sparse form's default),
    "osqp" (the paper's solver) or "hpipm" (sparse traditional form, hard state bounds); warm-started from the
    previous answer. ``max_iter`` caps the QP iterations.

    ``time_limit`` (s) bounds the whole step from the start of ``solve``: iterative solvers get the time left, and an
    operation that cannot be stopped (the affine model and build, a factorization, the C step) starts only if its
    measured time fits (the first step, with nothing measured, calibrates: ``warm_up``). Without one the budget is
    :attr:`ceiling`; ``float("inf")`` removes it. A step over budget is "limited" with the fallback and keeps the
    solver's iterate for the next, warm step.

    ``state_bounds`` "soft" (default; "hard" for HPIPM) makes the state bounds an exact L1 penalty (slacks s ≥ 0 at
    cost ``slack_weight``·Σ(s + ½s²)): a state past a bound drives back to it instead of failing. DAQP solves the hard
    QP first and the soft one only where it is infeasible, the same solution wherever the penalty is exact.
    ``linearization`` is the expansion point: "goal" (default) about the input goal u_g of stage 0's goal, "plan"
    about the input the previous plan expects now (the paper's scheme), "trajectory" stage by stage along the
    shifted plan (the LTV model; it follows plans that leave the neighbourhood of x). About a nonzero torque an arm's
    linearized dynamics are unstable and the condensed P ill-conditioned, hence "goal".

    With a task (``ocp.task``) the condensed QP carries the terms' Gauss–Newton model about the plan and the
    obstacles' clearances linearized there (:class:`ocpkit.qp.task_rows.TaskRows`), hard first, softened where they
    cannot be met. Every "success" passes the KKT certificate (:mod:`ocpkit.qp.certificate`), else it is "limited".

    ``native`` runs the whole step as compiled C (:mod:`ocpkit.export.native`; the condensed form with DAQP, hard
    QP only: a failure goes on to the softer QPs in Python). None (default) follows the OCP's ``compiled`` policy and
    builds it in the background while the Python step runs; True builds it now (a ValueError where this
    configuration has none); False keeps the Python step. Changing ``max_iter`` returns to the Python step.

    ``gains`` (set at construction) has every successful step also compute ``Solution.gains``, the first input's
    feedback gain K = ∂u₀/∂x₀ of the solved QP (:mod:`ocpkit.qp.sensitivity`), for an inner loop's
    u = u₀ + K (x − x₀) between steps. It runs the Python step (the C step returns no QP to differentiate) and has
    none with a task's terms or obstacles.

    A step takes a goal window (stage k's terms towards row k, the input term towards row k's input goal, the
    terminal terms row T), moved obstacles (rows and certificate at x_k against row k; nothing rebuilt) and an
    initial guess (the plan in place of the previous one shifted: the linearization and Gauss–Newton points, and
    ProxQP's and OSQP's primal start) (:meth:`Controller.solve`). The C step takes the window and the obstacles
    (``<name>_step_window``); a step with a guess runs in Python ("Python step (initial guess)" in its path).
    """

    CEILING_MIN, CEILING_PER_VARIABLE = 10.0, 1e-4  # seconds: the default budget (:attr:`ceiling`)
    TAKES = frozenset({"goal window", "obstacles", "initial guess"})

    def __init__(
        self,
        ocp: OCP,
        *,
        form: str = "condensed",
        qp: str | None = None,
        max_iter: int = 10_000,
        eps: float = 1e-9,
        time_limit: float | None = None,
        warm_start: bool = True,
        raise_on_fail: bool = False,
        linearization: str = "goal",
        state_bounds: str | None = None,
        slack_weight: float = 1e3,
        threads: int | None = 1,
        native: bool | None = None,
        gains: bool = False,
    ):
        self.linearization = check_linearization(linearization, trajectory=True)
        choice(form, tuple(TRANSCRIPTIONS), "form")
        qp = DEFAULT_QP[form] if qp is None else choice(qp, QP_SOLVERS, "qp")
        if not isinstance(ocp, OCP):
            raise TypeError(f"ocp must be an ocpkit OCP, got {type(ocp).__name__}")
        if state_bounds is None:
            state_bounds = "hard" if qp == "hpipm" else "soft"
        choice(state_bounds, ("soft", "hard"), "state_bounds")
        if qp == "hpipm" and state_bounds == "soft" and ocp.has_state_bounds:
            raise ValueError("qp 'hpipm' supports hard state bounds only: pass state_bounds='hard'")
        self.form, self.qp_name, self.state_bounds = form, qp, state_bounds
        if not isinstance(gains, bool):
            raise TypeError(f"gains must be True or False, got {gains!r}")
        self._gains = gains
        self.warm_start = bool(warm_start)
        self.time_limit = time_limit
        self.slack_weight = positive(slack_weight, "slack_weight")
        self.transcription = TRANSCRIPTIONS[form](ocp, soft=state_bounds == "soft", slack_weight=self.slack_weight)
        # The QPs a step solves, in order, until one is not infeasible. DAQP, an exact method, finds a hard QP
        # infeasible at once: it solves the hard QP first and the soft one only where that is infeasible — the
        # same solution where the penalty is exact, and a few variables instead of two slacks per bounded state
        # per step (docs: Reference, "Statuses"). The iterative backends (ProxQP, OSQP) only stop at their limits on an
        # infeasible QP: they solve the soft QP alone. A task's obstacle rows likewise: hard first, then only they
        # softened (a start in the margin, a plan that cannot clear every linearized row: one slack per stage, far
        # fewer variables than the soft QP's), then all.
        task = getattr(self.transcription, "task", None)
        obstacles = task is not None and task.obstacles
        chain = [TRANSCRIPTIONS[form](ocp)]
        if obstacles:
            chain.append(TRANSCRIPTIONS[form](ocp, soft_obstacles=True, slack_weight=self.slack_weight))
        if self.transcription.soft:
            chain.append(self.transcription)
        self._transcriptions = tuple(chain) if qp == "daqp" and len(chain) > 1 else (self.transcription,)
        if qp == "hpipm" and not (form == "sparse" and ocp.knots == ocp.horizon):
            raise ValueError(
                f"qp 'hpipm' needs form 'sparse' and the identity parameterization (knots = horizon, "
                f"traditional MPC), got form {form!r} with {ocp.knots} knots over {ocp.horizon} steps"
            )
        if ocp.task_functions is not None and form != "condensed":
            raise ValueError(
                f"a task's terms and obstacles enter the condensed QP (Gauss-Newton about the plan): "
                f"pass form='condensed', got form {form!r}"
            )
        if qp == "daqp" and form != "condensed":
            raise ValueError(f"qp 'daqp' is a dense solver: it needs form 'condensed', got form {form!r}")
        eps = positive(eps, "eps")
        self._backend = make_backend(qp, self.transcription, 1, eps)
        self._costs = OperationCosts()  # the affine model and QP build ("prepare"); the C step ("C step")
        self.max_iter = max_iter
        super().__init__(ocp, raise_on_fail=raise_on_fail, threads=threads)
        self._native = self._native_build = self._native_failure = None
        self._diagnosed = None  # the ill-conditioning diagnosis (_divergence), once computed
        self._native_loaded = threading.Event()  # set once the build has finished and its loading was tried
        if native is not None and not isinstance(native, bool):
            raise TypeError(f"native must be True, False or None, got {native!r}")
        why = self._no_native_step()
        if native and why:
            raise ValueError(f"native=True: this LinearMPC has no C step: {why}")
        if native or (native is None and not why and _native.wanted(ocp)):
            build = _native.start(
                ocp,
                eps=self._backend.tolerance,
                max_iter=self.max_iter,
                wait=bool(native),
                linearization=self.linearization,
                **self._native_options(),
            )
            if build is not None:
                self._native_build, self._native_iter = build, self.max_iter
                if not build.done():
                    # Until the C step is ready the Python step stays on CasADi's VM: a second compile (the affine
                    # model's) beside the C step's would only compete with this loop and delay the C step.
                    self._affine_model = BufferedFunction(ocp.model.affine(ocp.dt, ocp.substeps, ocp.integrator))
                me = weakref.ref(self)
                build.add_done_callback(lambda done: (ctrl := me()) is not None and ctrl._load_native(done))

    def _load_native(self, build) -> None:
        """Load the built C step (in the thread that finished the build, so a running loop never waits for it)."""
        try:
            self._native = ExportedMPC(self.ocp, build.result(), name=_native.NAME)
        except Exception as exc:  # noqa: BLE001 - the loop says it once and keeps its Python step
            self._native_failure = exc
        finally:
            self._native_loaded.set()

    def _native_options(self) -> dict:
        """The C step's settings beyond the linearization (the real-time iteration's iterations and tol)."""
        return {}

    def _no_native_step(self) -> str | None:
        """Why this configuration has no exported C step (None: it has one)."""
        for bad, why in (
            (self.form != "condensed", f"form {self.form!r} (the C step is the condensed QP)"),
            (self.qp_name != "daqp", f"qp {self.qp_name!r} (the C step solves with DAQP)"),
            (
                self.linearization == "trajectory" and self.ocp.task_functions is not None,
                "a task with the trajectory linearization (the C step's task terms are linearized about one model)",
            ),
            (
                self.transcription.soft and len(self._transcriptions) == 1,
                "soft state bounds with a backend that solves the soft QP alone",
            ),
            (self._gains, "gains (the C step returns no QP to differentiate)"),
        ):
            if bad:
                return why
        return None

    @property
    def gains(self) -> bool:
        """Whether each successful step computes ``Solution.gains`` (the constructor's ``gains``)."""
        return self._gains

    @property
    def native(self) -> bool:
        """Whether the next step runs as the compiled C step (its library built and loaded)."""
        return self._native_step() is not None

    def wait_compiled(self, timeout: float | None = None) -> bool:
        """Block until the background build of the C step has finished and it is loaded (then True: steps run in
        C); without a C step, until the Python step's affine model is compiled (:meth:`Controller.wait_compiled`)."""
        if self._native_build is not None:
            self._native_loaded.wait(timeout)
        for tr in self._transcriptions:
            if getattr(tr, "task", None) is not None:
                tr.task.wait(timeout)
        return self.native or super().wait_compiled(timeout)

    def _native_step(self):
        """The loaded C step (an ExportedMPC); None: the Python step."""
        if self._native_failure is not None:
            warnings.warn(f"LinearMPC keeps its Python step: {self._native_failure}", RuntimeWarning, stacklevel=4)
            self._native_failure = self._native_build = None
            self._affine_model = None  # the OCP's default affine model from now on (compiled when it can be)
        if self._native is None or self._native_iter != self.max_iter:
            return None
        return self._native

    @property
    def time_limit(self) -> float | None:
        """The step budget in seconds (None: unbounded); settable between steps."""
        return self._time_limit

    @time_limit.setter
    def time_limit(self, value: float | None) -> None:
        self._time_limit = (
            None if value is None else float("inf") if value == float("inf") else positive(value, "time_limit")
        )

    @property
    def max_iter(self) -> int:
        """The QP solver's iteration limit (settable between steps)."""
        return self._backend.max_iter

    @max_iter.setter
    def max_iter(self, value: int) -> None:
        self._backend.max_iter = integer(value, "max_iter", 1)
        self._backend.reset()

    @property
    def path(self) -> str:
        """ "C step" (compiled C, loaded), "Python step, C step building" (until the background build lands) or
        "Python step"."""
        if getattr(self, "_native", None) is not None and self._native_iter == self.max_iter:
            return "C step"
        if getattr(self, "_native_build", None) is not None and not self._native_loaded.is_set():
            return "Python step, C step building"
        return "Python step"

    def __repr__(self):
        return f"LinearMPC({self.form}, {self.qp_name}, {self.path}, {self.ocp!r})"

    def reset(self) -> None:
        super().reset()
        self._discard()
        if getattr(self, "_native", None) is not None:  # the C step keeps its own plan and warm start
            self._native.reset()

    def _discard(self) -> None:
        self._warm = None
        self._x_plan = None  # predicted states x_0 … x_T of the last successful step (trajectory linearization)
        self._backend.reset()

    def _divergence(self) -> str:
        """Why a QP is ill-conditioned, said once per controller (an eigenvalue problem: not on every failed step)."""
        if self._diagnosed is None:
            rho = spectral_radius(self.ocp, self._goal, self.ocp.input_goal(self._goal))
            self._diagnosed = (
                f" (|eig A_d| = {rho:.3g} a step: the model's RK4 step of {self.ocp.dt:g} s "
                f"diverges; more substeps, e.g. problem.ocp(..., substeps={2 * self.ocp.substeps}), "
                f"may help)"
                if rho > 2
                else f" (|eig A_d| = {rho:.3g} a step)"
            )
        return self._diagnosed

    @property
    def ceiling(self) -> float:
        """The step's budget when no ``time_limit`` is given (seconds): CEILING_MIN, or CEILING_PER_VARIABLE per QP
        variable where that is more. No MPC step is of use after it; it bounds the solvers that run on where nobody
        set a budget (docs: Reference, "Statuses")."""
        tr = self.transcription
        variables = tr.nz + (tr.ns if self.form == "condensed" else 0)
        return max(self.CEILING_MIN, self.CEILING_PER_VARIABLE * variables)

    def _deadline(self) -> float | None:
        return self.deadline(self.ceiling if self._time_limit is None else self._time_limit)

    def _solve(self, x: np.ndarray, goal: np.ndarray) -> Solution:
        step = self._native_step()
        beyond = step is not None and self._beyond_c_step()
        if step is not None and not beyond:
            return self._c_step(step, x, goal, self._deadline())
        sol = self._python_step(x, goal)
        if beyond:
            sol.path = sol.path or f"Python step ({beyond})"
        return sol

    def _python_step(self, x: np.ndarray, goal: np.ndarray) -> Solution:
        """The step in Python: the QP about the linearization point, solved."""
        along = self.shifted_plan(x, goal) if self.linearization == "trajectory" else None
        return self._qp_step(x, goal, along, self._deadline())

    def _beyond_c_step(self) -> str:
        """What this step has that the C step does not take ("": nothing; else the step runs in Python): an initial
        guess (the C step keeps its own plan). A goal window and moved obstacles it takes (``<name>_step_window``)."""
        return "initial guess" if self.guess is not None else ""

    def _c_step(self, step, x: np.ndarray, goal: np.ndarray, deadline: float | None) -> Solution:
        """The whole step (model, build, DAQP) as compiled C; a failure gives the Python step's fallback."""
        if not self._costs.fits("C step", time_left(deadline)):
            return self.fallback(
                LIMITED, skipped("C step", self._costs, deadline, 0).raw_status, reason=Reason.TIME_BUDGET
            )
        if step.sets_plan and self.plan is not None:  # the plan Python answered last (a softened QP, the brake)
            step.set_plan(self.plan)
        sol = step._solve(
            x, self.task_goal, window=self.goal_window if self.moving else None, obstacles=self._moved_obstacles()
        )
        self._costs.add("C step", step.step_seconds)
        self._warm, self._x_plan = None, None
        if sol.status == SUCCESS and deadline is not None and time.perf_counter() > deadline:
            sol.status, sol.raw_status = LIMITED, f"time budget exceeded ({sol.raw_status})"
            sol.reason = Reason.TIME_BUDGET
        if sol.status != SUCCESS and len(self._transcriptions) > 1 and sol.status != NAN:
            # The C step solved the hard QP: the soft one, in Python (state pushed past a bound, say).
            along = self.shifted_plan(x, goal) if self.linearization == "trajectory" else None
            sol = self._qp_step(x, goal, along, deadline, dict(sol.times), self._transcriptions[1:])
            sol.path = sol.path or SOFTENED_AFTER_C
            return sol
        if sol.status != SUCCESS:
            return self._fail(sol.status, sol.raw_status, sol.times, reason=sol.reason)
        return sol

    # C twin: step.in.c shifted_plan() and stage_models(); parity: tests/test_twins.py
    def shifted_plan(self, x: np.ndarray, goal: np.ndarray):
        """The linearization trajectory (x̄ (T, n), ū (T, m)) of this step: the last plan advanced one step, x̄_0 = x;
        the step's initial guess instead where given (not shifted).

        Its states are the last successful step's predictions shifted; where there are none (a cold start, under the
        input goal of stage 0, or after a fallback) x held, as NonlinearMPC and acados start cold (an unstable
        model's rollout runs far from x: :class:`~ocpkit.solvers.rti.RealTimeIteration`); a guess's, its rollout."""
        ocp, par = self.ocp, self.ocp.parameterization
        if self.guess is not None:
            us = par.inputs(self.guess)
            return self.rollout(x, us)[:-1], us
        us = par.inputs(np.tile(ocp.input_goal(goal), (ocp.knots, 1)) if self.plan is None else par.shift(self.plan))
        if self._x_plan is None:
            return np.tile(x, (ocp.horizon, 1)), us
        return np.vstack([x, self._x_plan[2:]]), us

    def _qp_step(
        self,
        x: np.ndarray,
        goal: np.ndarray,
        along,
        deadline: float | None,
        times: dict | None = None,
        transcriptions: tuple | None = None,
        knots=None,
    ) -> Solution:
        """One QP step: the affine model (about x, or per stage along ``along`` = (x̄, ū)), the build, the solve
        of each of ``transcriptions`` (default: this controller's) until one is not infeasible. A task's terms are
        linearized about ``knots`` (default: the step's initial guess, else the last plan shifted a step, or the
        input goal at a cold start). The cost follows the step's goal window, stage k towards row k, and the
        obstacle rows its obstacle window (:meth:`Controller.solve`); a held goal builds the held QP."""
        ocp, times = self.ocp, times or {"model": 0.0, "build": 0.0, "solve": 0.0}
        if not self._costs.fits("prepare", time_left(deadline)):
            res = skipped("prepare", self._costs, deadline, 0, name="model and QP build")
            return self.fallback(LIMITED, res.raw_status, times, reason=res.reason)
        t0 = time.perf_counter()
        if along is None:
            model = self.affine_model(x, goal, self.linearization)
        else:
            if not (np.isfinite(along[0]).all() and np.isfinite(along[1]).all()):
                model = None
            else:
                model = self.affine_models(*along)
        t1 = time.perf_counter()
        times["model"] += t1 - t0
        if model is None:
            return self._fail(
                NAN, f"non-finite affine model at x = {x.tolist()}", times, reason=Reason.NON_FINITE_MODEL
            )
        transcriptions = transcriptions or self._transcriptions
        task, n, guess = {}, ocp.nx, self.guess if knots is None else None  # the guess starts the step's first QP
        if ocp.task_functions is not None:
            if knots is None and self.guess is None:
                knots = self.goal_knots(goal) if self.plan is None else ocp.parameterization.shift(self.plan)
            targets = self.goal_window[:, n:] if self.moving else self.task_goal[n:]
            knots = self.guess if knots is None else knots
            task = {"targets": targets, "knots": knots, "obstacles": self._moved_obstacles()}
        x_goal = self.goal_window[:, :n] if self.moving else goal
        for tr in transcriptions:
            # a softer QP after an infeasible harder one: its own build time
            retry = None if tr is self._transcriptions[0] else f"QP {self._transcriptions.index(tr) + 1} build"
            if retry and not self._costs.fits(retry, time_left(deadline)):
                res = skipped(retry, self._costs, deadline, 0)
                return self._fail(LIMITED, res.raw_status, times, reason=res.reason)
            t1 = time.perf_counter()
            qp = tr.build(*model, x, x_goal, **task)
            t2 = time.perf_counter()
            times["build"] += t2 - t1
            self._costs.add(retry or "prepare", t2 - (t1 if retry else t0))
            problem = qp.check()
            if problem is not None:
                status = INFEASIBLE if problem.reason is Reason.BOUNDS_CROSSED else NAN
                return self._fail(status, problem, times, reason=problem.reason)
            if not qp.convex:
                problem = qp.not_definite(factorize=not self._backend.factorizes)
                if problem is not None:
                    return self._fail(EXCEPTION, problem, times, reason=problem.reason)
            try:
                warm = (tr.primal(qp, guess),) if guess is not None else self._warm if self.warm_start else None
                res = self._backend.solve(qp, warm, deadline)
            except Exception as exc:  # a backend that throws must not stop the control loop
                times["solve"] += time.perf_counter() - t2
                return self._fail(EXCEPTION, f"{type(exc).__name__}: {exc}", times, reason=Reason.SOLVER_ERROR)
            times["solve"] += time.perf_counter() - t2
            if res.status != INFEASIBLE:
                break
        if res.status == SUCCESS:
            if not np.isfinite(res.z).all():
                res.status, res.raw_status = NAN, f"{res.raw_status} with non-finite solution"
                res.reason = Reason.NON_FINITE_SOLUTION
            else:
                certificate = certify(qp, res.z, res.y, res.w)
                why = certificate.failed()
                if why is not None:  # not a solution (or an inaccurate one): no warm start from it
                    return self._fail(
                        LIMITED,
                        f"{res.raw_status} but certificate failed: {why}",
                        times,
                        res.iterations,
                        reason=Reason.CERTIFICATE_FAILED,
                    )
        if res.status != SUCCESS:
            return self._fail(res.status, res.raw_status, times, res.iterations, keep=res, reason=res.reason)
        self._warm = res.duals
        knots = tr.knots(res.z).copy()
        x_pred = tr.states(res.z) if self.form == "sparse" else tr.states(res.z, x)
        u = ocp.parameterization.u_at(knots, 0)
        self._x_plan = x_pred
        gains = feedback_gain(tr, qp, model, res.z, res.w) if self._gains else None
        return Solution(
            u=u,
            knots=knots,
            status=SUCCESS,
            raw_status=res.raw_status,
            iterations=res.iterations,
            x_pred=x_pred,
            times=times,
            certificate=certificate,
            gains=gains,
        )

    def _fail(
        self, status, raw, times, iterations=0, keep: Result | None = None, *, reason: Reason | None = None
    ) -> Solution:
        """Fallback solution. After "limited" the backend's workspace stays and its (finite) iterate is the next
        warm start: resetting it made every later step start cold, so a budget between the warm and the cold
        solve time never succeeded again. Any other failure leaves a clean workspace (no stale warm start).
        An ill-conditioned QP's raw status adds why (the model's divergence)."""
        self._x_plan = None  # the plan advances by the fallback now, not by the predictions
        if reason is Reason.ILL_CONDITIONED:
            raw = f"{raw}{self._divergence()}"
        if status == LIMITED and keep is not None:
            if keep.duals and all(np.isfinite(d).all() for d in keep.duals):
                self._warm = keep.duals
        else:
            self._discard()
        return self.fallback(status, raw, times, iterations, reason=reason)


SOLVERS = {"qp": LinearMPC}
