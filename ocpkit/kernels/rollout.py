"""Population rollouts: N candidate knot sets simulated over the horizon, one cost each.

This is the inner loop of Algorithm 1 (lines 11-17 of the paper's EMPC): each candidate's
knots U (p × m) become inputs through the Parameterization basis (``get_u_from_U``), the
model is stepped T times and the stage and terminal costs are summed:

    J = Σ_{k=0}^{T-1} l(x_k, u_k, x_goal) + l_T(x_T, x_goal).

(The x_0 term is the same for every candidate, so rankings equal the OCP's objective.)
Dynamics are either the paper's affine model x⁺ = A_d x + B_d u + w_d, refreshed by the
caller each control step, or the full nonlinear discrete model F translated from CasADi
(the paper's future work). Costs are translated CasADi Functions, so non-smooth ones
(if/else, |·|, penalties) are evaluated exactly as written.
"""

# No "from __future__ import annotations": Taichi reads kernel annotations as types.
import casadi as ca
import numpy as np
import taichi as ti

from ocpkit._checks import choice
from ocpkit.kernels import runtime
from ocpkit.kernels.translate import translate

DYNAMICS = ("affine", "nonlinear")


class Rollout:
    """Rollout engine for ``num_sims`` candidates of ``ocp`` on the Taichi runtime.

    ``knots`` (num_sims, p, m) and ``cost`` (num_sims,) are device fields; ``rollout(i)`` is
    a ``@ti.func`` that simulates candidate i and writes ``cost[i]``, for solver kernels
    that generate candidates and roll them out in one launch; ``picked`` (num_picked, p, m)
    receives the candidates chosen by :meth:`pick` (parents, elites). ``stage_cost``
    (x, u, x_goal) -> scalar and ``terminal_cost`` (x, x_goal) -> scalar default to the
    OCP's quadratic ones.
    """

    def __init__(self, ocp, num_sims: int, *, num_picked: int = 1, dynamics: str = "affine",
                 stage_cost=None, terminal_cost=None, precision: str = "float64",
                 arch: str = "auto"):
        if isinstance(num_sims, bool) or not isinstance(num_sims, (int, np.integer)) or num_sims < 1:
            raise ValueError(f"num_sims must be a positive integer, got {num_sims!r}")
        if (isinstance(num_picked, bool) or not isinstance(num_picked, (int, np.integer))
                or not 1 <= num_picked <= num_sims):
            raise ValueError(f"num_picked must be an integer in [1, num_sims={num_sims}], "
                             f"got {num_picked!r}")
        choice(dynamics, DYNAMICS, "dynamics")
        self.ftype, self.ntype = runtime.float_types(precision)
        self.arch = runtime.init(arch)
        n, m = ocp.nx, ocp.nu
        basis = np.asarray(ocp.parameterization.basis, dtype=np.float64)
        T, p = basis.shape
        self.num_sims, self.nx, self.nu, self.horizon, self.num_knots = int(num_sims), n, m, T, p
        self.dynamics, self.precision = dynamics, precision
        stage_cost = ocp.stage_cost if stage_cost is None else stage_cost
        terminal_cost = ocp.terminal_cost if terminal_cost is None else terminal_cost
        _check_signature("stage_cost", stage_cost, [(n, 1), (m, 1), (n, 1)], [(1, 1)])
        _check_signature("terminal_cost", terminal_cost, [(n, 1), (n, 1)], [(1, 1)])
        stage = translate(stage_cost, precision=precision).func
        terminal = translate(terminal_cost, precision=precision).func

        F = self.ftype
        self.knots = ti.field(F, shape=(num_sims, p, m))
        self.cost = ti.field(F, shape=num_sims)
        self.picked = ti.field(F, shape=(num_picked, p, m))
        self._index = ti.field(ti.i32, shape=num_picked)
        self._basis = ti.field(F, shape=(T, p))
        self._basis.from_numpy(basis.astype(self.ntype))
        self._x0 = ti.field(F, shape=n)
        self._goal = ti.field(F, shape=n)
        if dynamics == "affine":
            self._A = ti.field(F, shape=(n, n))
            self._B = ti.field(F, shape=(n, m))
            self._w = ti.field(F, shape=n)
            A, B, w = self._A, self._B, self._w

            # Rows unrolled, columns looped: a full unroll runs ~20% faster on the CPU but
            # takes ~20 s to compile for nlink:13 instead of ~1 s.
            @ti.func
            def step(x, u):
                xn = ti.Vector.zero(F, n)
                for r in ti.static(range(n)):
                    s = w[r]
                    for c in range(n):
                        s += A[r, c] * x[c]
                    for c in range(m):
                        s += B[r, c] * u[c]
                    xn[r] = s
                return xn
        else:
            discrete = ocp.discrete()
            _check_signature("ocp.discrete()", discrete, [(n, 1), (m, 1)], [(n, 1)])
            step = translate(discrete, precision=precision).func

        knots, cost, basis_f, x0, goal = self.knots, self.cost, self._basis, self._x0, self._goal

        @ti.func
        def rollout(i):
            x = ti.Vector([x0[r] for r in ti.static(range(n))], dt=F)
            g = ti.Vector([goal[r] for r in ti.static(range(n))], dt=F)
            J = ti.cast(0.0, F)
            for k in range(T):
                u = ti.Vector.zero(F, m)
                for j in ti.static(range(p)):
                    phi = basis_f[k, j]
                    for a in ti.static(range(m)):
                        u[a] += phi * knots[i, j, a]
                J += stage(x, u, g)[0]
                x = step(x, u)
            J += terminal(x, g)[0]
            cost[i] = J

        @ti.kernel
        def evaluate_all():
            for i in range(knots.shape[0]):
                rollout(i)

        picked, index = self.picked, self._index

        @ti.kernel
        def gather(count: ti.i32):
            for r, j, a in ti.ndrange(count, p, m):
                picked[r, j, a] = knots[index[r], j, a]

        self.rollout = rollout
        self._evaluate_all = evaluate_all
        self._gather = gather

    def set_state(self, x0: np.ndarray, goal: np.ndarray) -> None:
        """Copy the initial state x_0 and the goal state to the device."""
        self._x0.from_numpy(_vector("x0", x0, self.nx).astype(self.ntype))
        self._goal.from_numpy(_vector("goal", goal, self.nx).astype(self.ntype))

    def set_affine(self, A_d: np.ndarray, B_d: np.ndarray, w_d: np.ndarray) -> None:
        """Copy this control step's affine model x⁺ = A_d x + B_d u + w_d to the device."""
        if self.dynamics != "affine":
            raise ValueError("set_affine needs dynamics='affine'")
        n, m = self.nx, self.nu
        self._A.from_numpy(_matrix("A_d", A_d, (n, n)).astype(self.ntype))
        self._B.from_numpy(_matrix("B_d", B_d, (n, m)).astype(self.ntype))
        self._w.from_numpy(_vector("w_d", w_d, n).astype(self.ntype))

    def evaluate(self, knots: np.ndarray) -> np.ndarray:
        """Roll out the candidates ``knots`` (num_sims, p, m); returns their costs."""
        knots = np.asarray(knots, dtype=np.float64)
        shape = (self.num_sims, self.num_knots, self.nu)
        if knots.shape != shape:
            raise ValueError(f"knots must have shape {shape}, got {knots.shape}")
        self.knots.from_numpy(knots.astype(self.ntype))
        self._evaluate_all()
        return self.cost.to_numpy().astype(np.float64)


    def pick(self, indices: np.ndarray) -> None:
        """Copy candidates ``indices`` (best first) into ``picked[0:len(indices)]`` on the device."""
        indices = np.asarray(indices, dtype=np.int32)
        count = indices.size
        if not 1 <= count <= self.picked.shape[0] or indices.min() < 0 or indices.max() >= self.num_sims:
            raise ValueError(f"indices must be 1..{self.picked.shape[0]} candidate numbers in "
                             f"[0, {self.num_sims}), got {indices.tolist()}")
        padded = np.zeros(self.picked.shape[0], dtype=np.int32)
        padded[:count] = indices
        self._index.from_numpy(padded)
        self._gather(count)


def _check_signature(name, function, inputs, outputs) -> None:
    if not isinstance(function, ca.Function):
        raise TypeError(f"{name} must be a casadi.Function, got {type(function).__name__}")
    got_in = [tuple(function.size_in(j)) for j in range(function.n_in())]
    got_out = [tuple(function.size_out(j)) for j in range(function.n_out())]
    if got_in != inputs or got_out != outputs:
        raise ValueError(f"{name} must map inputs of shapes {inputs} to outputs {outputs}, "
                         f"got {got_in} -> {got_out}")


def _vector(name, value, size) -> np.ndarray:
    value = np.asarray(value, dtype=np.float64).reshape(-1)
    if value.shape != (size,):
        raise ValueError(f"{name} must have {size} entries, got {value.size}")
    return value


def _matrix(name, value, shape) -> np.ndarray:
    value = np.asarray(value, dtype=np.float64)
    if value.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {value.shape}")
    return value
