"""acados as a peer of ocpkit's nonlinear MPC: the same OCP solved by SQP-RTI (or SQP to convergence) with
partial-condensing HPIPM (installed by :mod:`ocpkit.benchmarks.acados_install`).

:func:`acados_ocp` writes ocpkit's OCP (``ocpkit.model.ocp``) as an ``AcadosOcp``:

* dynamics: ocpkit's CasADi model, either as acados' own explicit RK4 (``dynamics="erk"``: ERK, 4 stages, its
  generated forward sensitivities; the OCP's integrator must be "rk4") or as ``DISCRETE`` dynamics, the OCP's own
  discrete step (``ocp.discrete()``, any integrator: semi-implicit Euler too) with its CasADi Jacobian, both
  generated into C by acados. Both step exactly as ocpkit's discrete model.
* or, for the linear case (``ocpkit bench step``), ``dynamics="affine"``: x⁺ = A x + B u + w with (A, B, w) given at
  every solve as acados parameters, the same at every stage (:class:`AcadosAffine`): ocpkit's affine model, as
  LinearMPC and affine_mpc get it; one SQP-RTI iteration is then exactly the QP.
* cost: ocpkit's Σ_k (x_k − x_g)ᵀQ(x_k − x_g) + (u_k − u_g)ᵀR(u_k − u_g) + (x_N − x_g)ᵀQ_T(x_N − x_g) as acados'
  LINEAR_LS ½‖y − y_ref‖²_W, which acados multiplies by the interval's length h, with W = 2 diag(Q, R) / dt,
  W_e = 2 Q_T, y_ref = (x_g, u_g(x_g)) (the input goal: gravity compensation on URDF robots); the x_0 term is a
  constant. Gauss–Newton is then the exact Hessian, as in RTI.
* bounds: the finite input bounds on every stage, the finite state bounds (hard, as IPOPT's) on stages 1 … N.
* grid: traditional MPC (p = T, the OCP's identity parameterization) shoots at every step, N = T. A zero-order-hold
  knot OCP (``parameterization="zoh"``, T/p steps per block) is acados' coarse grid: N = p shooting intervals of
  T/p steps each, the integrator taking T/p steps per interval, the input held over each (move blocking). acados
  sees the state only at its nodes, so the stage term of node k stands for its interval's T/p steps (h = T/p dt):
  the nearest analogue of ocpkit's knots, not the same OCP (ocpkit's cost sums every step).

:class:`AcadosMPC` is an ocpkit Controller over it.
"""

from __future__ import annotations

import contextlib
import ctypes
import hashlib
import io
import time

import casadi as ca
import numpy as np

from ocpkit._checks import choice, positive
from ocpkit.benchmarks.acados_install import require
from ocpkit.controller import Controller
from ocpkit.model.ocp import OCP
from ocpkit.status import EXCEPTION, LIMITED, NAN, SUCCESS, Solution

DYNAMICS = ("erk", "discrete")
# The faster of the two: on the Puma 560 at N = 50, SQP-RTI in closed loop (3 seeds x 50 steps x 3, interleaved, load
# 6.5-6.9 on 2 CPUs) took 8.1 ms a step with ERK against 11.3 ms with DISCRETE (whose CasADi Jacobian of the whole RK4
# step also compiled 6x longer: 124 s against 20 s). ERK's sensitivities are 8.3 of its 11.3 ms, the QP 0.9 ms, so
# partial condensing (qp_solver_cond_N 25, 10, 5 against acados' default N: no condensing) made no step faster.
DEFAULT_DYNAMICS = "erk"
AFFINE = "affine"  # DYNAMICS of the linear case (AcadosAffine)
NLP = ("rti", "sqp")


def grid(ocp: OCP) -> tuple[int, int]:
    """(N shooting intervals, integrator steps per interval) of ``ocp``: (T, 1) for p = T, (p, T/p) for a
    zero-order hold of equal blocks; a ValueError for anything else."""
    par = ocp.parameterization
    if par.kind == "identity":
        return ocp.horizon, 1
    block = ocp.horizon // ocp.knots
    if par.kind != "zoh" or block * ocp.knots != ocp.horizon:
        raise ValueError(
            f"acados shoots on a grid of equal intervals: ocp must be p = T (knots=None) or a zero-order hold whose "
            f"{ocp.knots} knots divide the horizon {ocp.horizon}, got {par.kind!r}"
        )
    return ocp.knots, block


def acados_ocp(ocp: OCP, *, dynamics: str = DEFAULT_DYNAMICS, nlp: str = "rti", tol: float = 1e-8):
    """ocpkit's ``ocp`` as an ``AcadosOcp`` (see the module docstring); ``nlp`` "rti" (SQP_RTI, one Gauss–Newton
    iteration a solve) or "sqp" (SQP to ``tol`` on every KKT residual)."""
    at = require()
    choice(dynamics, (*DYNAMICS, AFFINE), "dynamics")
    choice(nlp, NLP, "nlp")
    if ocp.task is not None or (ocp.model.linear and dynamics != AFFINE):
        raise ValueError("the acados peer builds the state and input terms of a nonlinear model only")
    if dynamics == "erk" and ocp.integrator != "rk4":
        raise ValueError(f'dynamics "erk" is acados\' RK4; ocp predicts with {ocp.integrator!r}: use "discrete"')
    N, block = grid(ocp)
    nx, nu = ocp.nx, ocp.nu
    model = at.AcadosModel()
    model.name = "ocpkit"
    # One discrete step is inlined (SX); the T/p steps of a coarse interval are a loop (MX over mapaccum): their
    # inlined Jacobian took 361 s to compile for the Puma's 10 Euler steps.
    sym = ca.MX.sym if dynamics == "discrete" and block > 1 else ca.SX.sym
    x, u = sym("x", nx), sym("u", nu)
    model.x, model.u = x, u
    if dynamics == "erk":
        xdot = ca.SX.sym("xdot", nx)
        f = ocp.model.f(x, u)
        model.xdot, model.f_expl_expr, model.f_impl_expr = xdot, f, xdot - f
    elif dynamics == AFFINE:  # one interval's (A, B, w), column-major, as parameters (AcadosAffine.load)
        model.p = p = ca.SX.sym("p", nx * nx + nx * nu + nx)
        A, B = ca.reshape(p[: nx * nx], nx, nx), ca.reshape(p[nx * nx : nx * (nx + nu)], nx, nu)
        model.disc_dyn_expr = A @ x + B @ u + p[nx * (nx + nu) :]
        parameters = np.zeros(p.numel())
    elif block == 1:
        model.disc_dyn_expr = ocp.discrete()(x, u)
    else:
        model.disc_dyn_expr = ocp.discrete().mapaccum(block)(x, ca.repmat(u, 1, block))[:, -1]
    out = at.AcadosOcp()
    out.model = model
    out.dims.N = N
    if dynamics == AFFINE:
        out.parameter_values = parameters
    cost = out.cost
    W = 2.0 / ocp.dt * np.block([[ocp.Q, np.zeros((nx, nu))], [np.zeros((nu, nx)), ocp.R]])
    Vx, Vu = np.vstack([np.eye(nx), np.zeros((nu, nx))]), np.vstack([np.zeros((nx, nu)), np.eye(nu)])
    cost.cost_type = cost.cost_type_0 = cost.cost_type_e = "LINEAR_LS"
    cost.W = cost.W_0 = W
    cost.Vx = cost.Vx_0 = Vx
    cost.Vu = cost.Vu_0 = Vu
    cost.yref = cost.yref_0 = np.zeros(nx + nu)
    cost.W_e, cost.Vx_e, cost.yref_e = 2.0 * ocp.Q_terminal, np.eye(nx), np.zeros(nx)
    con = out.constraints
    con.x0 = np.zeros(nx)
    bounded = np.flatnonzero(np.isfinite(ocp.u_min) | np.isfinite(ocp.u_max))
    if bounded.size:
        con.idxbu, con.lbu, con.ubu = bounded, _finite(ocp.u_min[bounded]), _finite(ocp.u_max[bounded])
    bounded = np.flatnonzero(np.isfinite(ocp.x_min) | np.isfinite(ocp.x_max))
    if bounded.size:
        lower, upper = _finite(ocp.x_min[bounded]), _finite(ocp.x_max[bounded])
        con.idxbx, con.lbx, con.ubx = bounded, lower, upper
        con.idxbx_e, con.lbx_e, con.ubx_e = bounded, lower, upper
    opts = out.solver_options
    opts.tf = ocp.horizon * ocp.dt
    opts.qp_solver = "PARTIAL_CONDENSING_HPIPM"
    opts.hessian_approx = "GAUSS_NEWTON"
    opts.print_level = 0
    if dynamics == "erk":
        opts.integrator_type, opts.sim_method_num_stages, opts.sim_method_num_steps = "ERK", 4, block * ocp.substeps
    else:
        opts.integrator_type = "DISCRETE"
    opts.nlp_solver_type = "SQP_RTI" if nlp == "rti" else "SQP"
    if nlp == "sqp":
        opts.nlp_solver_max_iter, opts.qp_solver_iter_max = 200, 200
        opts.nlp_solver_tol_stat = opts.nlp_solver_tol_eq = opts.nlp_solver_tol_ineq = tol
        opts.nlp_solver_tol_comp = tol
    return out


def _finite(bound):
    return np.clip(bound, -1e9, 1e9)  # acados' stand-in for an infinite bound


def solver(ocp: OCP, *, dynamics: str = DEFAULT_DYNAMICS, nlp: str = "rti", tol: float = 1e-8):
    """An ``AcadosOcpSolver`` of :func:`acados_ocp`, generated and compiled into the cache (``acados/<key>``, the
    key a digest of the whole ``AcadosOcp``) and loaded from there when built before."""
    from ocpkit.codegen.cache import cache_dir

    at = require()
    description = acados_ocp(ocp, dynamics=dynamics, nlp=nlp, tol=tol)
    key = _digest(description)
    description.model.name = name = f"ocpkit_{key}"
    where = cache_dir("acados") / key
    built = (where / "c_generated_code" / f"libacados_ocp_solver_{name}.so").exists()
    description.code_export_directory = str(where / "c_generated_code")
    with contextlib.redirect_stdout(io.StringIO()):  # acados_template's notes on CasADi's version and OpenMP
        return at.AcadosOcpSolver(
            description, json_file=str(where / f"{name}.json"), generate=not built, build=not built, verbose=False
        )


def _digest(description) -> str:
    """12 hex digits of sha256 over an AcadosOcp's dynamics expression, cost, bounds, dimensions and options."""
    model = description.model
    digest = hashlib.sha256(str((model.f_expl_expr, model.disc_dyn_expr, model.p)).encode())
    for part in (description.dims, description.cost, description.constraints, description.solver_options):
        for field, value in sorted(vars(part).items()):
            digest.update(field.encode())
            digest.update(value.tobytes() if isinstance(value, np.ndarray) else repr(value).encode())
    return digest.hexdigest()[:12]


class _Iterate:
    """acados' iterate x_0 … x_N, u_0 … u_{N−1} and the bound x_0 = x, read and written as whole arrays through the
    solver's C interface (acados_template's ``get``/``set`` resolve their arguments anew on every call: 4-5 µs
    each, 1 ms a step at N = 50)."""

    def __init__(self, acados, N: int, nx: int, nu: int):
        lib = acados.shared_lib
        self._get, self._set, self._bound = lib.ocp_nlp_out_get, lib.ocp_nlp_out_set, lib.ocp_nlp_constraints_model_set
        for function in (self._get, self._set, self._bound):
            function.argtypes = [ctypes.c_void_p] * 3 + [ctypes.c_int, ctypes.c_char_p, ctypes.c_void_p]
        self._out = (acados.nlp_config, acados.nlp_dims, acados.nlp_out)
        self._in = (acados.nlp_config, acados.nlp_dims, acados.nlp_in)
        self.N, self.nx, self.nu = N, nx, nu

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """(X (N+1, nx), U (N, nu)) of the solver's iterate."""
        X, U = np.empty((self.N + 1, self.nx)), np.empty((self.N, self.nu))
        for k in range(self.N + 1):
            self._get(*self._out, k, b"x", X[k].ctypes.data)
        for k in range(self.N):
            self._get(*self._out, k, b"u", U[k].ctypes.data)
        return X, U

    def write(self, X: np.ndarray, U: np.ndarray) -> None:
        """Make (X, U) (C-contiguous float64) the solver's iterate."""
        for k in range(self.N + 1):
            self._set(*self._out, k, b"x", X[k].ctypes.data)
        for k in range(self.N):
            self._set(*self._out, k, b"u", U[k].ctypes.data)

    def first_input(self, out: np.ndarray) -> None:
        """u_0 of the solver's iterate into ``out`` (C-contiguous float64)."""
        self._get(*self._out, 0, b"u", out.ctypes.data)

    def start(self, x: np.ndarray) -> None:
        """The initial-state constraint x_0 = x."""
        for field in (b"lbx", b"ubx"):
            self._bound(*self._in, 0, field, x.ctypes.data)


class AcadosMPC(Controller):
    """MPC by acados on :func:`acados_ocp` of ``ocp`` (p = T, or a zero-order hold: the coarse grid), an ocpkit
    Controller.

    ``nlp`` "rti": one SQP-RTI iteration (preparation and feedback in one call) a control step; "sqp": SQP until
    every KKT residual is below ``tol``. Each starts from the previous iterate shifted one step where the grid is
    the step's (p = T), as ocpkit's RTI shifts its plan; on the coarse grid, whose intervals are T/p steps long,
    from the previous iterate as it is. A cold step starts from the states held at x and the input goal. acados' nonzero
    status (QP failure, SQP iteration limit) is the fallback with status "limited"; non-finite output, "nan".
    ``times["acados"]`` is acados' own time of the solve (its ``time_tot``), within ``times["solve"]``.
    """

    def __init__(
        self,
        ocp: OCP,
        *,
        dynamics: str = DEFAULT_DYNAMICS,
        nlp: str = "rti",
        tol: float = 1e-8,
        raise_on_fail: bool = False,
    ):
        self.intervals, self.block = grid(ocp)
        self.dynamics, self.nlp, self.tol = dynamics, nlp, positive(tol, "tol")
        self.acados = solver(ocp, dynamics=dynamics, nlp=nlp, tol=self.tol)
        self._iterate = _Iterate(self.acados, self.intervals, ocp.nx, ocp.nu)
        super().__init__(ocp, raise_on_fail=raise_on_fail)

    def __repr__(self):
        return f"AcadosMPC({self.nlp}, {self.dynamics}, N={self.intervals}, {self.ocp!r})"

    def reset(self) -> None:
        super().reset()
        self._last, self._goal_set = None, None  # the last solve's (X, U); the goal the cost's y_ref holds

    def _discard(self) -> None:
        self._last = None

    def _set_goal(self, goal):
        ocp, a = self.ocp, self.acados
        if self._goal_set is not None and np.array_equal(goal, self._goal_set):
            return
        ref = np.r_[goal[: ocp.nx], ocp.input_goal(goal)]
        for k in range(self.intervals):
            a.cost_set(k, "yref", ref)
        a.cost_set(self.intervals, "yref", ref[: ocp.nx])
        self._goal_set = np.array(goal, dtype=float)

    def _guess(self, x, goal):
        N = self.intervals
        if self._last is None:
            ug = np.clip(self.ocp.input_goal(goal), self.ocp.u_min, self.ocp.u_max)
            self._iterate.write(np.tile(x, (N + 1, 1)), np.tile(ug, (N, 1)))
        elif self.block == 1:
            X, U = self._last
            self._iterate.write(np.vstack([X[1:], X[-1:]]), np.vstack([U[1:], U[-1:]]))

    def _solve(self, x: np.ndarray, goal: np.ndarray) -> Solution:
        a = self.acados
        t0 = time.perf_counter()
        self._set_goal(goal)
        self._guess(x, goal)
        self._iterate.start(np.ascontiguousarray(x, dtype=float))
        t1 = time.perf_counter()
        status = a.solve()
        X, U = self._iterate.read()
        t2 = time.perf_counter()
        iterations = int(np.ravel(a.get_stats("sqp_iter"))[0]) if self.nlp == "sqp" else 1
        times = {
            "model": 0.0,
            "build": t1 - t0,
            "solve": t2 - t1,
            "acados": float(np.ravel(a.get_stats("time_tot"))[0]),
        }
        if not (np.isfinite(U).all() and np.isfinite(X).all()):
            self._last = None
            return self.fallback(NAN, f"acados returned non-finite states or inputs (status {status})", times, 1)
        if status != 0:
            self._last = None
            kind = LIMITED if status in (2, 3, 4) else EXCEPTION
            return self.fallback(kind, f"acados status {status} after {iterations} iterations", times, iterations)
        self._last = X, U
        return Solution(
            u=U[0].copy(),
            knots=U,
            status=SUCCESS,
            iterations=iterations,
            x_pred=X if self.block == 1 else None,
            times=times,
            raw_status=f"acados {self.nlp} status 0 in {iterations} iterations",
        )


class AcadosAffine:
    """acados' QP on ocpkit's affine model, for ``ocpkit bench step`` beside LinearMPC and affine_mpc: SQP-RTI on
    :func:`acados_ocp` with ``dynamics="affine"`` (one iteration: the QP, partial-condensing HPIPM) over ``ocp``'s
    grid (p = T, or the coarse grid of a zero-order hold). :meth:`step` loads the model, x and the goal and solves;
    it returns u_0."""

    def __init__(self, ocp: OCP):
        self.ocp = ocp
        self.intervals, self.block = grid(ocp)
        self.acados = solver(ocp, dynamics=AFFINE)
        lib, name = self.acados.shared_lib, self.acados.model_name
        self._update = getattr(lib, f"{name}_acados_update_params")
        self._update.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_void_p, ctypes.c_int]
        self._iterate = _Iterate(self.acados, self.intervals, ocp.nx, ocp.nu)
        self._u0 = np.empty(ocp.nu)
        self._goal = None

    def load(self, A, B, w) -> None:
        """x⁺ = A x + B u + w at every stage (over a coarse interval of b steps its b-fold composition)."""
        A, B, w = (np.asarray(M, dtype=float) for M in (A, B, w))
        Ab, Bb, wb = A, B, w
        for _ in range(self.block - 1):
            Ab, Bb, wb = A @ Ab, A @ Bb + B, A @ wb + w
        p = np.concatenate([Ab.ravel(order="F"), Bb.ravel(order="F"), wb])
        for k in range(self.intervals):
            self._update(self.acados.capsule, k, p.ctypes.data, p.size)

    def step(self, x, goal, model) -> tuple[np.ndarray, int, int]:
        """(u_0, acados' status, QP iterations) of the QP at x, ``goal`` and the affine ``model`` (A, B, w)."""
        a = self.acados
        if self._goal is None or not np.array_equal(goal, self._goal):
            ref = np.r_[goal[: self.ocp.nx], self.ocp.input_goal(goal)]
            for k in range(self.intervals):
                a.cost_set(k, "yref", ref)
            a.cost_set(self.intervals, "yref", ref[: self.ocp.nx])
            self._goal = np.array(goal, dtype=float)
        self.load(*model)
        self._iterate.start(np.ascontiguousarray(x, dtype=float))
        status = a.solve()
        self._iterate.first_input(self._u0)
        return self._u0.copy(), status, int(np.sum(a.get_stats("qp_iter")))
