"""Continuous dynamics ẋ = f(x, u) declared once in CasADi, its discretization and affine model.

The paper's linear(ized) model is ẋ = A x + B u + w, discretized to x_{k+1} = A_d x_k + B_d u_k + w_d
(Section III-A, eq. first_order_integration). Here the discrete model is built first (the exact zero-order hold
for linear dynamics; RK4 or Euler, see :data:`INTEGRATORS`, for others) and the affine model is its first-order
expansion about a point, so the QPs, IPOPT, generated C and the Taichi kernels all see the same discrete dynamics.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ocpkit._checks import choice, positive

# How a nonlinear model's step is integrated (``Model.discrete``). "rk4": classic Runge–Kutta, four evaluations of f
# (and, for the affine model, of its Jacobians) per sub-step. "euler": one per sub-step — semi-implicit (symplectic)
# Euler q̇⁺ = q̇ + h q̈(q, q̇, u), q⁺ = q + h q̇⁺ for a mechanical state x = [q, q̇] (Crocoddyl's default integrator),
# explicit Euler x⁺ = x + h f(x, u) for any other.
INTEGRATORS = ("rk4", "euler")


class Model:
    """Continuous dynamics ẋ = f(x, u) with named states and inputs.

    ``x`` and ``u`` are CasADi SX column symbols and ``xdot`` an SX expression in them; model parameters
    (masses, lengths, the error multiplier) are already numbers inside ``xdot``. ``second_order`` is nq where the
    state is x = [q, q̇] — ẋ's first nq entries are, as expressions, the symbols x[nq:] — and None otherwise.
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
        self.second_order = _second_order(x, xdot)
        self._functions = {}

    def __repr__(self):
        return f"Model({self.name!r}, nx={self.nx}, nu={self.nu}, linear={self.linear})"

    def discrete(self, dt: float, substeps: int = 1, integrator: str = "rk4") -> ca.Function:
        """Discrete dynamics F(x, u) -> x⁺ over one step dt with u held constant (zero-order hold).

        Linear models use the exact matrix exponential, whatever ``substeps`` and ``integrator``; others
        ``integrator`` ("rk4" or "euler", see :data:`INTEGRATORS`) over ``substeps`` sub-steps.
        """
        return self._cached(_discrete, dt, substeps, choice(integrator, INTEGRATORS, "integrator"))

    def affine(self, dt: float, substeps: int = 1, integrator: str = "rk4") -> ca.Function:
        """Affine model of :meth:`discrete` about (x̄, ū): x⁺ ≈ A_d x + B_d u + w_d, as one Function
        (x̄, ū) -> (A_d, B_d, w_d)."""
        return self._cached(_affine, dt, substeps, choice(integrator, INTEGRATORS, "integrator"))

    @property
    def jacobian(self) -> ca.Function:
        """(x, u) -> (ẋ, ∂f/∂x, ∂f/∂u): the continuous dynamics and their Jacobians, one SX Function."""
        if "jacobian" not in self._functions:
            x, u, f = self.x, self.u, self.xdot
            self._functions["jacobian"] = ca.Function(
                "f_jac", [x, u], [f, ca.jacobian(f, x), ca.jacobian(f, u)], ["x", "u"], ["xdot", "f_x", "f_u"]
            )
        return self._functions["jacobian"]

    def rk4(self, dt: float, substeps: int = 1) -> ca.Function:
        """RK4 discretization F(x, u) -> x⁺, whatever the model (used for plants integrated finely)."""
        return self._cached(_rk4, dt, substeps)

    def _cached(self, build, dt, substeps, *options):
        key = (build.__name__, positive(dt, "dt"), _substeps(substeps), *options)
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


def _second_order(x: ca.SX, xdot: ca.SX) -> int | None:
    """nq where x = [q, q̇] with ẋ[:nq] the very symbols x[nq:] (how every shipped robot declares it), else None."""
    nq, odd = divmod(x.numel(), 2)
    if odd or not nq or not all(ca.is_equal(xdot[i], x[nq + i]) for i in range(nq)):
        return None
    return nq


def _rk4_step(x, h: float, f):
    """One classic Runge–Kutta step of ẋ = f(x)."""
    k1 = f(x)
    k2 = f(x + h / 2 * k1)
    k3 = f(x + h / 2 * k2)
    k4 = f(x + h * k3)
    return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def _euler_step(x, h: float, f, shift: ca.DM | None):
    """One Euler step x⁺ = x + h k. Explicit (``shift`` None): k = f(x). Semi-implicit for x = [q, q̇], ``shift`` =
    [0 I; 0 0]: k = f + h·shift·f = [q̇ + h q̈; q̈], i.e. q̇⁺ = q̇ + h q̈, then q⁺ = q + h q̇⁺ with the new velocity."""
    k = f(x)
    if shift is not None:
        k = k + h * (shift @ k)
    return x + h * k


def _integrate(model: Model, x, dt: float, substeps: int, integrator: str, f):
    """``substeps`` steps of ``integrator`` from x; ``x`` and ``f``'s values plain SX or :class:`_Tangent`."""
    h, nq = dt / substeps, model.second_order
    if integrator == "rk4":

        def step(z):
            return _rk4_step(z, h, f)
    else:
        shift = (
            None
            if nq is None
            else ca.DM(ca.Sparsity.triplet(2 * nq, 2 * nq, list(range(nq)), list(range(nq, 2 * nq))), 1.0)
        )

        def step(z):
            return _euler_step(z, h, f, shift)

    for _ in range(substeps):
        x = step(x)
    return x


def _rk4(model: Model, dt: float, substeps: int) -> ca.Function:
    x, u = model.x, model.u
    xk = _integrate(model, x, dt, substeps, "rk4", lambda z: model.f(z, u))
    return ca.Function("F", [x, u], [xk], ["x", "u"], ["x_next"])


def _discrete(model: Model, dt: float, substeps: int, integrator: str) -> ca.Function:
    x, u = model.x, model.u
    if model.linear:
        Ad, Bd, wd = _zoh(model, dt)
        return ca.Function(
            "F", [x, u], [ca.mtimes(ca.DM(Ad), x) + ca.mtimes(ca.DM(Bd), u) + ca.DM(wd)], ["x", "u"], ["x_next"]
        )
    if integrator == "rk4":
        return model.rk4(dt, substeps)
    xk = _integrate(model, x, dt, substeps, integrator, lambda z: model.f(z, u))
    return ca.Function("F", [x, u], [xk], ["x", "u"], ["x_next"])


def _zoh(model: Model, dt: float):
    """Exact zero-order-hold discretization of ẋ = A x + B u + w: expm of the augmented matrix."""
    from scipy.linalg import expm

    z = ca.vertcat(model.x, model.u)
    lin = ca.Function(
        "linearization", [z], [ca.jacobian(model.xdot, z), ca.substitute(model.xdot, z, ca.DM.zeros(z.shape))]
    )
    J, w = (np.asarray(v, dtype=float) for v in lin(np.zeros(z.shape[0])))
    n, m = model.nx, model.nu
    aug = np.zeros((n + m + 1, n + m + 1))
    aug[:n, : n + m] = J
    aug[:n, -1] = w.ravel()
    E = expm(aug * dt)
    return E[:n, :n], E[:n, n : n + m], E[:n, -1]


class _Tangent:
    """A point of the step with its forward sensitivities to the step's start x̄ and input ū: (value, ∂/∂x̄, ∂/∂ū),
    CasADi MX or SX. The integrators act on it as on a plain state, so the affine model is the chain rule of the
    very step that makes the discrete model."""

    __slots__ = ("value", "dx", "du")

    def __init__(self, value, dx, du):
        self.value, self.dx, self.du = value, dx, du

    def __add__(self, other):
        return _Tangent(self.value + other.value, self.dx + other.dx, self.du + other.du)

    def __rmul__(self, c: float):
        return _Tangent(c * self.value, c * self.dx, c * self.du)

    def __rmatmul__(self, M: ca.DM):
        return _Tangent(ca.mtimes(M, self.value), ca.mtimes(M, self.dx), ca.mtimes(M, self.du))


# C twin: step.in.c affine_model() and sensitivity_rate(); parity: tests/test_twins.py
def _affine(model: Model, dt: float, substeps: int, integrator: str) -> ca.Function:
    """Linear models: the Jacobians of the exact discretization (constant). Others: the integrator's forward
    sensitivities (:class:`_Tangent`): each evaluation of f at a stage x_s(x̄, ū) gives ∂f/∂(x̄, ū) = J·∂x_s/∂(x̄, ū)
    (+ ∂f/∂u) with J from :attr:`Model.jacobian`, the same derivative as the SX Jacobian of the unrolled step (to
    1e-15) at a fraction of its cost (RK4, nlink:13: 80 instead of 264 µs compiled, 2.4 s to compile instead of
    ~30). The products are sparse, so the rows [0 I] of ∂f/∂x of a model x = [q, q̇] cost their nq nonzeros only:
    taking q̈'s rows apart (J·S = [S_q̇; ∂q̈/∂x S]) saves 1/(nx + 1) of the flops and measured within ±6 % of this
    (puma560, baxter, nlink:13; the row blocks' copies cost what the flops save)."""
    if model.linear:
        x, u = model.x, model.u
        x_next = model.discrete(dt, substeps)(x, u)
        Ad, Bd = ca.jacobian(x_next, x), ca.jacobian(x_next, u)
        return ca.Function(
            "affine", [x, u], [Ad, Bd, x_next - ca.mtimes(Ad, x) - ca.mtimes(Bd, u)], ["x", "u"], ["Ad", "Bd", "wd"]
        )
    # RK4 evaluates the Jacobians four times a sub-step: called from an MX graph they are generated once (nlink:13:
    # 24k instructions each). Euler's one a sub-step is inlined in SX, where the step's algebra (I + h² ∂q̈/∂q, …)
    # folds into the Jacobian's own code instead of sparse matrix operations on work vectors (nlink:13, compiled:
    # 12.8 instead of 20 µs, the Jacobian alone 11.4).
    sym = ca.MX if integrator == "rk4" else ca.SX
    x, u = sym.sym("x", model.nx), sym.sym("u", model.nu)

    def f(z: _Tangent) -> _Tangent:
        k, J, G = model.jacobian(z.value, u)
        if z is start:  # ∂x̄/∂x̄ = I, ∂x̄/∂ū = 0: no product
            return _Tangent(k, J, G)
        return _Tangent(k, ca.mtimes(J, z.dx), ca.mtimes(J, z.du) + G)

    start = _Tangent(x, sym.eye(model.nx), sym(model.nx, model.nu))
    end = _integrate(model, start, dt, substeps, integrator, f)
    Ad, Bd = end.dx, end.du
    return ca.Function(
        "affine", [x, u], [Ad, Bd, end.value - ca.mtimes(Ad, x) - ca.mtimes(Bd, u)], ["x", "u"], ["Ad", "Bd", "wd"]
    )
