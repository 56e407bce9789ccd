"""What a success certifies about the task, and the safe input when no plan can be trusted.

A QP's KKT certificate (:mod:`ocpkit.qp.certificate`) proves the QP was solved, not that the plan keeps the robot clear
of obstacles: the QP's rows are linearized, softened where they cannot be met, and a sampling planner's fitness only
penalizes them. :class:`PlanCheck` therefore rolls a plan out on the controller's *nonlinear* discrete model (the
OCP's F, RK4 or Euler at its substeps) and checks x_1 … x_T against

* every obstacle clearance: d − margin ≥ −``CLEARANCE_TOL`` (never below d = 0, a collision, whatever the margin);
* every finite state bound, to ``STATE_TOL`` relative to max(1, |bound|);
* finiteness (a diverging prediction).

A step whose plan fails is not a success: "soft" (the input is still applied: it is the solver's best answer, often
the way out of a start inside a margin) with the constraint, stage and amount in its raw status, or a refused step
when the prediction is not finite.

:class:`Brake` is the input of a refused step when the previous plan cannot be trusted: u minimizing the joint
velocities one step ahead, ‖v(x⁺)‖² with x⁺ = A_d x + B_d u + w_d the affine model about (x, u_hold), within the
input bounds (a box QP) — full braking torque while the robot moves, gravity compensation once it rests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ocpkit.qp.boxqp import solve_box_qp
from ocpkit.numeric import BufferedFunction
from ocpkit.status import Reason

# Clearance (m) a certified plan may lose below the task's margin on the nonlinear rollout: a linearized row met
# exactly by the QP is met to O(step²) by the nonlinear prediction. A certified plan never collides (d ≥ 0).
CLEARANCE_TOL = 1e-3
# Relative excess of a state bound a certified plan may show (of max(1, |bound|)).
STATE_TOL = 1e-3


@dataclass(frozen=True)
class Violation:
    """The worst broken constraint of a plan: ``kind`` (the :class:`~ocpkit.status.Reason` CLEARANCE, STATE_BOUND,
    COLLISION or NON_FINITE_PREDICTION: "clearance", "state bound", "collision", "non-finite"), the stage k of x_k
    (1 … T) where it is worst, by how much (m, or the state's unit), and which (a pair or a state)."""

    kind: Reason
    stage: int
    amount: float
    which: str = ""

    def __str__(self) -> str:
        if self.kind is Reason.NON_FINITE_PREDICTION:
            return f"prediction not finite from x_{self.stage} on the nonlinear model"
        if self.kind is Reason.COLLISION:
            return f"prediction collides at x_{self.stage} ({self.amount:.3g} m deep) on the nonlinear model"
        return (
            f"{self.kind} {self.which} violated by {self.amount:.3g} at x_{self.stage} of the plan on the "
            f"nonlinear model"
        )


class PlanCheck:
    """The task certificate of a plan (module docstring): ``violation(xs)`` for predicted states x_0 … x_T."""

    def __init__(self, ocp):
        self.ocp = ocp
        tf = ocp.task_functions
        self.pairs = tf.pairs if tf is not None else 0
        self.margin = ocp.task.margin if self.pairs else 0.0
        lo, hi = ocp.x_min, ocp.x_max
        self._bounded = np.flatnonzero(np.isfinite(lo) | np.isfinite(hi))
        self._lo, self._hi = lo[self._bounded], hi[self._bounded]
        scale = np.maximum(1.0, np.abs(np.where(np.isfinite(lo), lo, 0.0)))
        self._lo_tol = STATE_TOL * scale[self._bounded]
        scale = np.maximum(1.0, np.abs(np.where(np.isfinite(hi), hi, 0.0)))
        self._hi_tol = STATE_TOL * scale[self._bounded]
        # d − margin may fall to −CLEARANCE_TOL, but never below −margin (a collision)
        self._clear_tol = min(CLEARANCE_TOL, max(self.margin, 0.0))

    @property
    def needed(self) -> bool:
        """Whether the OCP has anything to certify beyond finiteness (obstacles or finite state bounds)."""
        return bool(self.pairs or self._bounded.size)

    def violation(self, xs: np.ndarray, ahead: int = 0, obstacles: np.ndarray | None = None) -> Violation | None:
        """The worst violation along x_1 … x_T of ``xs`` (T+1, n), or None if the plan keeps them all; the obstacles
        the task's declared ones, or ``obstacles`` (T+1, N, 4), where each is at each stage (moving). With ``ahead``
        a collision within x_1 … x_ahead — true clearance below zero and below x_0's (a start already inside an
        obstacle may move within it, not deeper) — comes first, as kind COLLISION: a plan that drives into an
        obstacle within those steps is refused, not applied as "soft"."""
        X = xs[1:]
        bad = ~np.isfinite(X).all(axis=1)
        if bad.any():
            return Violation(Reason.NON_FINITE_PREDICTION, int(np.argmax(bad)) + 1, np.inf)
        worst = None
        if self._bounded.size:
            V = X[:, self._bounded]
            excess = np.maximum(self._lo - self._lo_tol - V, V - self._hi - self._hi_tol)
            k, j = np.unravel_index(int(np.argmax(excess)), excess.shape)
            if excess[k, j] > 0:
                amount = float(excess[k, j] + (self._lo_tol[j] if V[k, j] < self._lo[j] else self._hi_tol[j]))
                worst = Violation(Reason.STATE_BOUND, int(k) + 1, amount, f"x[{int(self._bounded[j])}]")
        if self.pairs:
            tf = self.ocp.task_functions
            centres = np.asarray(self.ocp.task_maps()["spheres"](X.T)[0]).reshape(3, len(X), -1)
            moving = (None, None) if obstacles is None else (obstacles[1 : len(xs)], obstacles[:1])
            # (pairs, stages): pair robot sphere · N + obstacle
            d = tf.pair_clearances(centres, moving[0]).reshape(len(X), -1).T
            if ahead:
                start = np.asarray(tf.spheres(xs[0])[0]).reshape(3, 1, -1)
                floor = min(0.0, float(tf.pair_clearances(start, moving[1]).min()) + self.margin)
                near = d[:, :ahead].min(axis=0) + self.margin  # true clearance at x_1 … x_ahead
                if near.min() < floor - 1e-9:
                    k = int(np.argmax(near < floor - 1e-9))
                    return Violation(Reason.COLLISION, k + 1, float(-near[k]), "(robot spheres in an obstacle)")
            k = int(np.argmin(d.min(axis=0)))
            pair = int(np.argmin(d[:, k]))
            if d[pair, k] < -self._clear_tol:
                robot, obstacle = divmod(pair, len(self.ocp.task.obstacles))
                worst = Violation(
                    Reason.CLEARANCE, k + 1, float(-d[pair, k]), f"(robot sphere {robot}, obstacle {obstacle})"
                )
        return worst


def spectral_radius(ocp, x: np.ndarray, u: np.ndarray) -> float:
    """max |eig A_d| of the OCP's affine model about (x, u): how much its prediction grows a step (NaN where the
    model is not finite there)."""
    Ad = np.asarray(ocp.affine()(x, u)[0], dtype=float)
    return float(np.abs(np.linalg.eigvals(Ad)).max()) if np.isfinite(Ad).all() else float("nan")


class Brake:
    """The braking input at a state (module docstring), or None for models that are not x = [q, q̇]."""

    def __init__(self, ocp):
        self.ocp = ocp
        self.nq = ocp.model.second_order  # nq where x = [q, q̇], else None
        self._affine = None

    def __call__(self, x: np.ndarray, u_hold: np.ndarray) -> np.ndarray | None:
        """u within the input bounds that brings q̇ closest to rest one step ahead, about ``u_hold``; None where the
        model is not second order or its affine model is not finite at x."""
        ocp = self.ocp
        if self.nq is None:
            return None
        if self._affine is None:
            self._affine = BufferedFunction(ocp.affine())
        u_hold = np.clip(u_hold, ocp.u_min, ocp.u_max)
        Ad, Bd, wd = (np.asarray(v, dtype=float) for v in self._affine(x, u_hold))
        v = slice(self.nq, ocp.nx)
        Bv = Bd[v]
        rest = Ad[v] @ x + Bd[v] @ u_hold + wd.ravel()[v]  # q̇⁺ at u_hold; q̇⁺(u) = rest + Bv (u − u_hold)
        if not (np.isfinite(Bv).all() and np.isfinite(rest).all()):
            return None
        H = Bv.T @ Bv
        # unique: the nearest to u_hold when Bv is rank-deficient
        H += 1e-9 * max(np.trace(H) / ocp.nu, 1e-12) * np.eye(ocp.nu)
        res = solve_box_qp(H, Bv.T @ rest, ocp.u_min - u_hold, ocp.u_max - u_hold)
        u = u_hold + res.z
        return np.clip(u, ocp.u_min, ocp.u_max) if np.isfinite(u).all() else None
