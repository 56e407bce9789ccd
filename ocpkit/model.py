"""Continuous dynamics ẋ = f(x, u) declared once in CasADi, its discretization and affine model.

The paper's linear(ized) model is ẋ = A x + B u + w, discretized to x_{k+1} = A_d x_k + B_d u_k + w_d
(Section III-A, eq. first_order_integration). Here the discrete model is built first (RK4, or the exact
zero-order hold for linear dynamics) and the affine model is its first-order expansion about a point,
so the QPs, IPOPT, generated C and the Taichi kernels all see the same discrete dynamics.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from ocpkit._checks import positive


class Model:
    """Continuous dynamics ẋ = f(x, u) with named states and inputs.

    ``x`` and ``u`` are CasADi SX column symbols and ``xdot`` an SX expression in them; model parameters
    (masses, lengths, the error multiplier) are already numbers inside ``xdot``.
    """

    def __init__(self, name: str, x: ca.SX, u: ca.SX, xdot: ca.SX, *, state_names=None, input_names=None):
        for arg, value in (("x", x), ("u", u), ("xdot", xdot)):
            if not isinstance(value, ca.SX):
                raise TypeError(f"{arg} must be a casadi.SX expression, got {type(value).__name__}")
        if not (x.is_symbolic() and x.is_column()):
            raise ValueError("x must be a column of purely symbolic casadi.SX entries")
        if not (u.is_symbolic() and u.is_column()):
            raise ValueError("u must be a column of purely symbolic casadi.SX entries")
        if xdot.shape != x.shape:
            raise ValueError(f"xdot must have the shape of x {x.shape}, got {xdot.shape}")
        free = set(map(str, ca.symvar(xdot))) - set(map(str, ca.symvar(ca.vertcat(x, u))))
        if free:
            raise ValueError(f"xdot depends on symbols other than x and u: {sorted(free)}")
        self.name = name
        self.x, self.u, self.xdot = x, u, xdot
        self.nx, self.nu = x.numel(), u.numel()
        self.state_names = _names(state_names, self.nx, "x", "state_names")
        self.input_names = _names(input_names, self.nu, "u", "input_names")
        self.f = ca.Function("f", [x, u], [xdot], ["x", "u"], ["xdot"])
        self.linear = bool(ca.is_linear(xdot, ca.vertcat(x, u)))
        self._functions = {}

    def __repr__(self):
        return f"Model({self.name!r}, nx={self.nx}, nu={self.nu}, linear={self.linear})"

    def discrete(self, dt: float, substeps: int = 1) -> ca.Function:
        """Discrete dynamics F(x, u) -> x⁺ over one step dt with u held constant (zero-order hold).

        Linear models use the exact matrix exponential; others RK4 with ``substeps`` sub-steps.
        """
        return self._cached(_discrete, dt, substeps)

    def affine(self, dt: float, substeps: int = 1) -> ca.Function:
        """Affine model about (x̄, ū): x⁺ ≈ A_d x + B_d u + w_d, as one Function (x̄, ū) -> (A_d, B_d, w_d)."""
        return self._cached(_affine, dt, substeps)

    @property
    def jacobian(self) -> ca.Function:
        """(x, u) -> (ẋ, ∂f/∂x, ∂f/∂u): the continuous dynamics and their Jacobians, one SX Function."""
        if "jacobian" not in self._functions:
            x, u, f = self.x, self.u, self.xdot
            self._functions["jacobian"] = ca.Function("f_jac", [x, u], [f, ca.jacobian(f, x), ca.jacobian(f, u)],
                                                      ["x", "u"], ["xdot", "f_x", "f_u"])
        return self._functions["jacobian"]

    def rk4(self, dt: float, substeps: int = 1) -> ca.Function:
        """RK4 discretization F(x, u) -> x⁺, whatever the model (used for plants integrated finely)."""
        return self._cached(_rk4, dt, substeps)

    def _cached(self, build, dt, substeps):
        key = (build.__name__, positive(dt, "dt"), _substeps(substeps))
        if key not in self._functions:
            self._functions[key] = build(self, *key[1:])
        return self._functions[key]


def _names(names, n, prefix, arg):
    if names is None:
        return [f"{prefix}{i}" for i in range(n)]
    names = list(names)
    if len(names) != n or not all(isinstance(s, str) for s in names):
        raise ValueError(f"{arg} must be {n} strings, got {names!r}")
    return names


def _substeps(substeps):
    if isinstance(substeps, bool) or not isinstance(substeps, (int, np.integer)) or substeps < 1:
        raise ValueError(f"substeps must be an integer >= 1, got {substeps!r}")
    return int(substeps)


def _rk4(model: Model, dt: float, substeps: int) -> ca.Function:
    x, u, h = model.x, model.u, dt / substeps
    f = model.f
    xk = x
    for _ in range(substeps):
        k1 = f(xk, u)
        k2 = f(xk + h / 2 * k1, u)
        k3 = f(xk + h / 2 * k2, u)
        k4 = f(xk + h * k3, u)
        xk = xk + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return ca.Function("F", [x, u], [xk], ["x", "u"], ["x_next"])


def _discrete(model: Model, dt: float, substeps: int) -> ca.Function:
    if not model.linear:
        return model.rk4(dt, substeps)
    Ad, Bd, wd = _zoh(model, dt)
    x, u = model.x, model.u
    return ca.Function("F", [x, u], [ca.mtimes(ca.DM(Ad), x) + ca.mtimes(ca.DM(Bd), u) + ca.DM(wd)],
                       ["x", "u"], ["x_next"])


def _zoh(model: Model, dt: float):
    """Exact zero-order-hold discretization of ẋ = A x + B u + w: expm of the augmented matrix."""
    from scipy.linalg import expm

    z = ca.vertcat(model.x, model.u)
    lin = ca.Function("linearization", [z], [ca.jacobian(model.xdot, z), ca.substitute(model.xdot, z, ca.DM.zeros(z.shape))])
    J, w = (np.asarray(v, dtype=float) for v in lin(np.zeros(z.shape[0])))
    n, m = model.nx, model.nu
    aug = np.zeros((n + m + 1, n + m + 1))
    aug[:n, : n + m] = J
    aug[:n, -1] = w.ravel()
    E = expm(aug * dt)
    return E[:n, :n], E[:n, n : n + m], E[:n, -1]


def _affine(model: Model, dt: float, substeps: int) -> ca.Function:
    """Linear models: the Jacobians of the exact discretization (constant). Others: RK4's forward sensitivities —
    each stage's ∂k/∂(x, u) = J(x_s, u)·∂x_s/∂(x, u) (+ ∂f/∂u) with J from :attr:`Model.jacobian` — as dense
    matrix products in an MX graph: the same derivative as the SX Jacobian of the unrolled RK4 (to 1e-15), at a
    fraction of its cost (nlink:13: 80 instead of 264 µs compiled, 213 instead of 561 µs on the VM, 2.4 s to
    compile instead of ~30)."""
    if model.linear:
        x, u = model.x, model.u
        x_next = model.discrete(dt, substeps)(x, u)
        Ad, Bd = ca.jacobian(x_next, x), ca.jacobian(x_next, u)
        return ca.Function("affine", [x, u], [Ad, Bd, x_next - ca.mtimes(Ad, x) - ca.mtimes(Bd, u)],
                           ["x", "u"], ["Ad", "Bd", "wd"])
    x, u = ca.MX.sym("x", model.nx), ca.MX.sym("u", model.nu)
    h, jac = dt / substeps, model.jacobian
    xk, Ad, Bd = x, ca.MX.eye(model.nx), ca.MX.zeros(model.nx, model.nu)
    for _ in range(substeps):
        ks, dxs, dus = [], [], []  # the stages k_i and their sensitivities
        for a in (0.0, h / 2, h / 2, h):
            xs, Xs, Us = (xk, Ad, Bd) if not ks else (xk + a * ks[-1], Ad + a * dxs[-1], Bd + a * dus[-1])
            k, J, G = jac(xs, u)
            ks.append(k)
            dxs.append(ca.mtimes(J, Xs))
            dus.append(ca.mtimes(J, Us) + G)
        xk, Ad, Bd = (v + h / 6 * (d[0] + 2 * d[1] + 2 * d[2] + d[3]) for v, d in ((xk, ks), (Ad, dxs), (Bd, dus)))
    return ca.Function("affine", [x, u], [Ad, Bd, xk - ca.mtimes(Ad, x) - ca.mtimes(Bd, u)],
                       ["x", "u"], ["Ad", "Bd", "wd"])

