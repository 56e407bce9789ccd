"""The sampling planners' preconditioner: the knot QP at this step's linearization, its Cholesky factor P = LLᵀ
(perturbations L⁻ᵀε, covariance ∝ P⁻¹, cost alike in every direction) and the seeds every population evaluates (the
QP's optimum within the bounds and the input that holds the goal); :mod:`ocpkit.solvers.sampling` says why."""

from __future__ import annotations

import time

import casadi as ca
import numpy as np
import scipy.linalg

from ocpkit.codegen.kernels.rollout import constrained
from ocpkit.qp.daqp import DAQP
from ocpkit.qp.boxqp import solve_box_qp
from ocpkit.qp.transcription import CondensedQP
from ocpkit.status import SUCCESS


class Preconditioner:
    """The knot QP ½zᵀPz + qᵀz (z = knots, p·m) of ``ocp`` at one linearization, P = LLᵀ, and the seeds.

    :meth:`update` builds it with :class:`ocpkit.qp.transcription.CondensedQP` (the structure-exploiting
    build LinearMPC uses), factors P and computes ``newton`` (the QP's optimum within the input
    bounds, warm-started from the previous plan) and ``hold`` (:meth:`holding_input` at every knot).
    ``whiten`` = L⁻ᵀ maps N(0, I) draws to N(0, P⁻¹).

    With obstacles or state bounds the QP also holds them as LinearMPC does, hard rows: the state bounds on the
    affine prediction and each obstacle clearance linearized about the warm start's prediction (ocpkit.qp.task_rows).
    ``newton`` is then that QP's optimum by DAQP, a candidate that keeps the constraints to first order, and the
    box-constrained optimum only where the rows cannot all be met (a start inside a margin), DAQP fails or runs out
    of the step's time; ``seed_status`` says which. P, and so the preconditioning, is the same either way: hard rows
    add no cost. On the docs' Panda reach this seed is what keeps the hand out of the sphere: with the
    box-constrained one alone no candidate was feasible for long stretches and the hand ended 7–13 cm inside.
    """

    def __init__(self, ocp):
        self.ocp = ocp
        # A task's terms enter by Gauss-Newton about the warm start.
        self.transcription = CondensedQP(ocp)
        self.rows = constrained(ocp)
        self._daqp = DAQP(max_iter=1000, eps=1e-9) if self.rows else None
        self.seed_status = "box QP"
        self.lo, self.hi = np.tile(ocp.u_min, ocp.knots), np.tile(ocp.u_max, ocp.knots)
        x, u = ocp.model.x, ocp.model.u
        f = ocp.model.xdot
        self._statics = ca.Function("statics", [x, u], [f, ca.jacobian(f, u)])
        self._hold_goal, self._hold = None, None
        self.L = None  # until the first update

    def holding_input(self, goal: np.ndarray) -> np.ndarray:
        """u_g corrected so that the continuous dynamics rest at the goal: u_g − J⁺ f(x_goal, u_g) with
        J = ∂f/∂u (exact for robots, whose dynamics are affine in the torques: gravity compensation),
        clipped to the input bounds; u_g where that is not finite. Cached per goal."""
        ocp = self.ocp
        if self._hold_goal is None or not np.array_equal(goal, self._hold_goal):
            u_g = np.clip(ocp.input_goal(goal), ocp.u_min, ocp.u_max)
            f, J = (np.asarray(v, dtype=float) for v in self._statics(goal, u_g))
            u = u_g - np.linalg.lstsq(J, f.ravel(), rcond=None)[0]
            self._hold = np.clip(u, ocp.u_min, ocp.u_max) if np.isfinite(u).all() else u_g
            self._hold_goal = goal.copy()
        return self._hold

    def update(
        self,
        model,
        x,
        goal,
        warm: np.ndarray | None,
        times: dict,
        targets=None,
        deadline: float | None = None,
        obstacles=None,
    ) -> None:
        """Build, factor and seed for the affine ``model`` = (A_d, B_d, w_d) at state x towards ``goal``, the goal
        state held (n,) or at every stage (T+1, n); ``warm`` (p, m) starts the Newton candidate (the holding input
        of stage 0's goal if None) and, with a task, is where its terms and obstacles are linearized towards
        ``targets`` (held, or per stage (T+1, ·)), the obstacles where the task declares them or at every stage,
        ``obstacles`` (T+1, N, 4). DAQP stops at ``deadline`` (a perf_counter value; None: none). Adds its parts
        to ``times``."""
        p, m = self.ocp.knots, self.ocp.nu
        t0 = time.perf_counter()
        now = goal[0] if np.ndim(goal) == 2 else goal
        task = {}
        if self.transcription.task is not None:
            knots = np.tile(self.holding_input(now), (p, 1)) if warm is None else warm
            task = {"targets": targets, "knots": knots, "obstacles": obstacles}
        qp = self.transcription.build(*model, x, goal, **task)
        t1 = time.perf_counter()
        self.P, self.q = qp.P, qp.q
        try:
            self.L = np.linalg.cholesky(self.P)
        except np.linalg.LinAlgError:  # P ≻ 0 in exact arithmetic (R ≻ 0); lift rounding-level negatives
            w, V = np.linalg.eigh(self.P)
            self.L = np.linalg.cholesky((V * np.maximum(w, 1e-12 * w.max())) @ V.T)
        self.whiten = scipy.linalg.solve_triangular(self.L, np.eye(p * m), lower=True).T
        t2 = time.perf_counter()
        self.hold = np.tile(self.holding_input(now), (p, 1))
        start = self.hold if warm is None else warm
        self.newton = self._constrained_seed(qp, deadline)
        if self.newton is None:
            self.newton = solve_box_qp(self.P, self.q, self.lo, self.hi, start.ravel()).z.reshape(p, m)
        times["build"] += t1 - t0
        times["factor"] += t2 - t1
        times["seed"] += time.perf_counter() - t2

    def _constrained_seed(self, qp, deadline) -> np.ndarray | None:
        """The knots (p, m) of ``qp``'s optimum with its constraint rows, by DAQP (cold: the rows change with the
        linearization) within ``deadline``, or None where it has no rows beyond the knots' box or DAQP finds none."""
        if not self.rows or qp.C.shape[0] == len(qp.box):
            self.seed_status = "box QP"
            return None
        result = self._daqp.solve(qp, None, deadline)
        self.seed_status = f"DAQP {result.raw_status}"
        if result.status != SUCCESS or not np.isfinite(result.z).all():
            return None
        return np.clip(result.z, self.lo, self.hi).reshape(self.ocp.knots, self.ocp.nu)

    def whitened(self, knots: np.ndarray, center: np.ndarray) -> np.ndarray:
        """Lᵀ(U − center) for knots (…, p, m): deviations in the coordinates where P is the identity."""
        d = self.L.shape[0]
        return (knots.reshape(-1, d) - center.reshape(d)) @ self.L
