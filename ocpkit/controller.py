"""The controller interface every solver implements, and the Solution of one MPC step.

A Controller is anything with ``reset()`` and ``solve(x, goal) -> Solution``. A solver that fails at run
time does not raise inside a control loop: its Solution carries a non-success status and a safe fallback
input (the previous plan advanced one step, clipped to the input bounds).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ocpkit._checks import choice
from ocpkit.numeric import BufferedFunction
from ocpkit.ocp import OCP

SUCCESS, LIMITED, INFEASIBLE, NAN, EXCEPTION = "success", "limited", "infeasible", "nan", "exception"
STATUSES = (SUCCESS, LIMITED, INFEASIBLE, NAN, EXCEPTION)


LINEARIZATIONS = ("goal", "plan")


def check_linearization(mode: str) -> str:
    """A valid choice of the affine model's expansion input (see :meth:`Controller.affine_model`)."""
    choice(mode, LINEARIZATIONS, "linearization")
    return mode


class SolverError(RuntimeError):
    """Raised by ``solve`` for a failed step when the controller was built with ``raise_on_fail=True``."""


@dataclass
class Solution:
    """One MPC step: the input to apply, the knots and predicted states behind it, status and timings (s)."""

    u: np.ndarray
    knots: np.ndarray
    status: str
    raw_status: str = ""
    iterations: int = 0
    x_pred: np.ndarray | None = None
    times: dict = field(default_factory=lambda: {"model": 0.0, "build": 0.0, "solve": 0.0, "total": 0.0})
    fallback: bool = False

    @property
    def ok(self) -> bool:
        return self.status == SUCCESS

    def to_dict(self) -> dict:
        """JSON-ready summary (first input, knots, status, iterations, times)."""
        return {"u": self.u.tolist(), "knots": self.knots.tolist(), "status": self.status,
                "raw_status": self.raw_status, "iterations": int(self.iterations), "fallback": self.fallback,
                "times": {k: float(v) for k, v in self.times.items()}}


class Controller:
    """Base class: keeps the last plan for warm starts and fallbacks; subclasses implement ``_solve``."""

    def __init__(self, ocp: OCP, *, raise_on_fail: bool = False):
        if not isinstance(ocp, OCP):
            raise TypeError(f"ocp must be an ocpkit OCP, got {type(ocp).__name__}")
        self.ocp = ocp
        self.raise_on_fail = bool(raise_on_fail)
        self._affine_model = None  # the OCP's affine model, bound to numpy buffers at its first use
        self.reset()

    def reset(self) -> None:
        """Forget the previous plan (cold start)."""
        self.plan: np.ndarray | None = None  # knots (p, m) of the last successful solve
        self._goal = np.zeros(self.ocp.nx)

    def solve(self, x, goal) -> Solution:
        """Solve the MPC problem from state x towards goal state ``goal``; return the first input and more."""
        x = self.ocp.check_state(x, "x")
        goal = self.ocp.check_state(goal, "goal")
        start = time.perf_counter()
        self._goal = goal  # for the fallback's cold-start input
        sol = self._solve(x, goal)
        if sol.ok and not (np.all(np.isfinite(sol.u)) and np.all(np.isfinite(sol.knots))):
            sol = self.fallback(NAN, f"{sol.raw_status} with non-finite result", sol.times, sol.iterations)
        sol.times["total"] = time.perf_counter() - start
        if sol.ok:
            self.plan = sol.knots
        elif self.raise_on_fail:
            raise SolverError(f"{type(self).__name__} failed: {sol.status} ({sol.raw_status})")
        else:
            self.plan = sol.knots  # the fallback plan, so repeated failures keep advancing it
        return sol

    def _solve(self, x: np.ndarray, goal: np.ndarray) -> Solution:
        raise NotImplementedError

    def affine_model(self, x: np.ndarray, goal: np.ndarray, mode: str):
        """(A_d, B_d, w_d) of the OCP's affine model about (x, ū), or None if any entry is not finite.

        ū is the input goal u_g(goal) for ``mode`` "goal", or for "plan" the input the previous plan
        expects now (u_g at a cold start). LinearMPC documents why "goal" is the default.
        """
        ocp = self.ocp
        u_bar = (ocp.input_goal(goal) if self.plan is None or mode == "goal"
                 else ocp.parameterization.u_at(ocp.parameterization.shift(self.plan), 0))
        if self._affine_model is None:
            self._affine_model = BufferedFunction(ocp.affine())
        Ad, Bd, wd = self._affine_model(x, u_bar)
        if not (np.isfinite(Ad).all() and np.isfinite(Bd).all() and np.isfinite(wd).all()):
            return None
        return Ad, Bd, wd.ravel()

    def fallback(self, status: str, raw_status: str, times: dict | None = None, iterations: int = 0) -> Solution:
        """A failed step: the previous plan advanced one step and clipped to the input bounds."""
        ocp = self.ocp
        if self.plan is None:
            knots = np.tile(ocp.input_goal(self._goal), (ocp.knots, 1))
        else:
            knots = ocp.parameterization.shift(self.plan)
        knots = np.clip(np.nan_to_num(knots), ocp.u_min, ocp.u_max)
        u = np.clip(ocp.parameterization.u_at(knots, 0), ocp.u_min, ocp.u_max)
        times = dict(times or {"model": 0.0, "build": 0.0, "solve": 0.0, "total": 0.0})
        return Solution(u=u, knots=knots, status=status, raw_status=raw_status, iterations=iterations,
                        times=times, fallback=True)
