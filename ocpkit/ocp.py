"""The optimal control problem: model, time step, horizon, quadratic cost, bounds and parameterization.

The paper's MPC problem (eq. mpc_problem) with a zero-order-hold discrete model:

    min  Σ_{k=0}^{T-1} (u_k − u_g)ᵀ R (u_k − u_g) + Σ_{k=1}^{T-1} (x_k − x_goal)ᵀ Q (x_k − x_goal)
         + (x_T − x_goal)ᵀ Q_T (x_T − x_goal)
    s.t. x_{k+1} = F(x_k, u_k),  u = φ U (the parameterization),  u_min ≤ u_k ≤ u_max,  x_min ≤ x_k ≤ x_max.

x_0 is the measured state, so its cost term is a constant and is left out. The input goal is
u_g = u_goal + K x_goal with K = ``u_goal_gain`` (zero by default, the paper's u_goal = 0): for a robot whose
inputs are servo set points (Baxter) the input that holds the goal is the goal position itself. Every solver reads this one
description: the QPs through its affine model, IPOPT through F, EMPC through the translated kernels.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from ocpkit._checks import array, bounds, integer, positive, weight
from ocpkit.compiled import SwitchingFunction, compile_function, compile_in_background
from ocpkit.model import Model
from ocpkit.parameterization import Parameterization

# The default path (``compiled`` not given) compiles the affine model in the background only from this size up
# (CasADi VM instructions of the continuous Jacobian, Model.jacobian, which the affine model evaluates 4 times
# per RK4 step): below it the VM takes tens of µs and a compile would only cost CPU. nlink:3 has 822, nlink:5 3k,
# nlink:7 6.5k, nlink:13 24k.
BACKGROUND_MIN_INSTRUCTIONS = 2_000


class OCP:
    """A validated MPC problem; see the module docstring for the objective and constraints."""

    def __init__(self, model: Model, dt: float, horizon: int, Q, R, *, Q_terminal=None, u_goal=None,
                 u_goal_gain=None, u_min=None, u_max=None, x_min=None, x_max=None,
                 parameterization: Parameterization | None = None, substeps: int = 1, compiled: bool | None = None):
        if not isinstance(model, Model):
            raise TypeError(f"model must be an ocpkit Model, got {type(model).__name__}")
        n, m = model.nx, model.nu
        self.model = model
        self.dt = positive(dt, "dt")
        self.horizon = integer(horizon, "horizon", 1)
        self.substeps = integer(substeps, "substeps", 1)
        self.compiled = None if compiled is None else bool(compiled)
        self.nx, self.nu = n, m
        self.Q = weight(Q, "Q", n, definite=False)
        self.R = weight(R, "R", m, definite=True)
        self.Q_terminal = self.Q if Q_terminal is None else weight(Q_terminal, "Q_terminal", n, definite=False)
        self.u_goal = np.zeros(m) if u_goal is None else bounds(u_goal, u_goal, "u_goal", "u_goal", m)[0]
        if not np.all(np.isfinite(self.u_goal)):
            raise ValueError(f"u_goal must be finite, got {self.u_goal.tolist()}")
        self.u_goal_gain = np.zeros((m, n)) if u_goal_gain is None else array(u_goal_gain, "u_goal_gain", (m, n))
        self.u_min, self.u_max = bounds(u_min, u_max, "u_min", "u_max", m)
        self.x_min, self.x_max = bounds(x_min, x_max, "x_min", "x_max", n)
        if parameterization is None:
            parameterization = Parameterization.identity(self.horizon)
        if not isinstance(parameterization, Parameterization):
            raise TypeError(f"parameterization must be a Parameterization, got {type(parameterization).__name__}")
        if parameterization.horizon != self.horizon:
            raise ValueError(f"parameterization has horizon {parameterization.horizon}, the OCP {self.horizon}")
        self.parameterization = parameterization
        self._compiled_affine = None  # compiled=True: the compiled model; None: the switching one, once made
        self.knots = parameterization.knots
        x, u, xg = ca.SX.sym("x", n), ca.SX.sym("u", m), ca.SX.sym("x_goal", n)
        ex, eu = x - xg, u - ca.DM(self.u_goal) - ca.mtimes(ca.DM(self.u_goal_gain), xg)
        self.stage_cost = ca.Function("stage_cost", [x, u, xg], [ca.bilin(ca.DM(self.Q), ex, ex)
                                      + ca.bilin(ca.DM(self.R), eu, eu)], ["x", "u", "x_goal"], ["l"])
        self.terminal_cost = ca.Function("terminal_cost", [x, xg], [ca.bilin(ca.DM(self.Q_terminal), ex, ex)],
                                         ["x", "x_goal"], ["l_T"])

    def __repr__(self):
        return (f"OCP({self.model.name!r}, dt={self.dt}, horizon={self.horizon}, "
                f"{self.parameterization.kind} knots={self.knots})")

    @property
    def has_state_bounds(self) -> bool:
        return bool(np.isfinite(self.x_min).any() or np.isfinite(self.x_max).any())

    def input_goal(self, x_goal) -> np.ndarray:
        """u_g = u_goal + K x_goal: the input the cost pulls towards for this goal."""
        return self.u_goal + self.u_goal_gain @ np.asarray(x_goal, dtype=float)

    def discrete(self) -> ca.Function:
        """The discrete model F(x, u) -> x⁺ every solver predicts with."""
        return self.model.discrete(self.dt, self.substeps)

    def affine(self) -> ca.Function:
        """The affine model (x̄, ū) -> (A_d, B_d, w_d) of :meth:`discrete`.

        ``compiled=True``: compiled C, compiled here and now (see :mod:`ocpkit.compiled`: about 2x faster for large
        robots after a one-off compile, cached by hash). ``compiled=False``: CasADi's virtual machine.
        Not given (default): the virtual machine, which switches by itself to the compiled C as soon as a compile
        started in the background at this first call finishes (models of ``BACKGROUND_MIN_INSTRUCTIONS`` and
        more; a :class:`ocpkit.compiled.SwitchingFunction`); without a C compiler, the VM with one warning."""
        fn = self.model.affine(self.dt, self.substeps)
        if self.compiled:
            if self._compiled_affine is None:
                self._compiled_affine = compile_function(fn)
            return self._compiled_affine
        if self.compiled is None and self.model.jacobian.n_instructions() >= BACKGROUND_MIN_INSTRUCTIONS:
            if self._compiled_affine is None:
                future = compile_in_background(fn)
                self._compiled_affine = fn if future is None else SwitchingFunction(fn, future)
            current = self._compiled_affine
            if isinstance(current, SwitchingFunction) and current.compiled() is not None:
                return current.compiled()
            return current
        return fn

    def check_state(self, x, name: str = "x") -> np.ndarray:
        """x as a finite float64 vector of length nx, or a ValueError naming ``name``."""
        return array(x, name, (self.nx,))
