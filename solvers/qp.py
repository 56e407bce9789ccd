"""LinearMPC: re-linearized convex MPC, sparse or condensed, with any input parameterization (paper Section V).

Each control step linearizes the model about the current state and the input the previous plan
expected now, builds the chosen transcription from the affine model (A_d, B_d, w_d), and solves the QP
with ProxQP (dense backend for the condensed form, sparse for the sparse form) or OSQP, the paper's own
solver. Input bounds are imposed on the knots, which keeps the whole piecewise-linear (or
zero-order-hold) input trajectory within bounds because every u_k is a convex combination of knots.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ocpkit._checks import choice, integer, positive
from ocpkit.controller import (EXCEPTION, INFEASIBLE, LIMITED, NAN, SUCCESS, Controller, Solution,
                               check_linearization)
from ocpkit.ocp import OCP
from ocpkit.transcription import QP, TRANSCRIPTIONS

QP_SOLVERS = ("proxqp", "osqp", "hpipm")


@dataclass
class _Result:
    z: np.ndarray
    duals: tuple
    status: str
    raw_status: str
    iterations: int


class _ProxQP:
    """ProxQP, dense or sparse backend. One solver object is kept across steps and refreshed with ``update``
    (warm-started from its previous result); knot bounds go to the dense backend as box constraints."""

    CHUNK = 5  # iterations between wall-clock checks when a time limit is set

    def __init__(self, sparse: bool, max_iter: int, eps: float):
        import proxsuite

        self._sparse = sparse
        self._module = proxsuite.proxqp.sparse if sparse else proxsuite.proxqp.dense
        self._proxqp = proxsuite.proxqp
        self.max_iter, self.eps = max_iter, eps
        self.reset()

    def reset(self):
        self.solver, self._key = None, None

    def _data(self, qp: QP):
        """(H, g, A, b, C, l, u, l_box, u_box) for ProxQP: simple bounds on z as a box where the QP marks them."""
        k = 0 if self._sparse or qp.box is None else len(qp.box)
        if not k:
            return (qp.P, qp.q, qp.A, qp.b, qp.C, qp.l, qp.u, None, None), (qp.n, qp.b.size, qp.l.size, False)
        lo, hi = np.full(qp.n, -np.inf), np.full(qp.n, np.inf)
        lo[qp.box], hi[qp.box] = qp.l[:k], qp.u[:k]
        return (qp.P, qp.q, qp.A, qp.b, qp.C[k:], qp.l[k:], qp.u[k:], lo, hi), (qp.n, qp.b.size, qp.l.size - k, True)

    def solve(self, qp: QP, warm: tuple | None, time_limit: float | None) -> _Result:
        """Solve; with a time limit, iterate in chunks (continuing from the previous iterate) up to it."""
        px = self._proxqp
        start = time.perf_counter()
        data, key = self._data(qp)
        H, g, A, b, C, l, u, lo, hi = data
        box = {"l_box": lo, "u_box": hi} if key[3] else {}
        reuse = warm is not None and self._key == key
        if not reuse:
            n, n_eq, n_in, has_box = key
            self.solver = (self._module.QP(n, n_eq, n_in, box_constraints=True) if has_box
                           else self._module.QP(n, n_eq, n_in))
            self._key = key
        solver = self.solver
        s = solver.settings
        s.eps_abs, s.eps_rel, s.verbose = self.eps, 0.0, False
        # Primal and dual residuals alone let a warm-started solve stop early with a wrong active set
        # (5.8e-4 off in u on the pendulum); the duality gap closes that.
        s.check_duality_gap, s.eps_duality_gap_abs, s.eps_duality_gap_rel = True, self.eps, 0.0
        s.max_iter = self.max_iter if time_limit is None else min(self.max_iter, self.CHUNK)
        if reuse:
            s.initial_guess = px.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
            solver.update(H, g, A, b, C, l, u, **box)
            solver.solve()
        else:
            # A fresh box-constrained solver starts cold: ProxQP 0.8 rejects (or crashes on) warm box duals.
            s.initial_guess = (px.InitialGuess.WARM_START if warm is not None and not key[3]
                               else px.InitialGuess.NO_INITIAL_GUESS)
            solver.init(H, g, A, b, C, l, u, **box)
            solver.solve(*warm) if s.initial_guess == px.InitialGuess.WARM_START else solver.solve()
        out = px.QPSolverOutput
        iterations = solver.results.info.iter
        while (time_limit is not None and solver.results.info.status == out.PROXQP_MAX_ITER_REACHED
               and iterations < self.max_iter and time.perf_counter() - start < time_limit):
            s.max_iter = min(self.CHUNK, self.max_iter - iterations)
            s.initial_guess = px.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
            solver.solve()
            iterations += solver.results.info.iter
        r = solver.results
        status = {out.PROXQP_SOLVED: SUCCESS, out.PROXQP_MAX_ITER_REACHED: LIMITED,
                  out.PROXQP_PRIMAL_INFEASIBLE: INFEASIBLE, out.PROXQP_DUAL_INFEASIBLE: INFEASIBLE,
                  out.PROXQP_SOLVED_CLOSEST_PRIMAL_FEASIBLE: INFEASIBLE}.get(r.info.status, EXCEPTION)
        raw = str(r.info.status).rsplit(".", 1)[-1]
        if status == LIMITED and iterations < self.max_iter:
            raw = f"time limit {time_limit:g} s reached ({raw} after {iterations} iterations)"
        return _Result(np.array(r.x), (np.array(r.x), np.array(r.y), np.array(r.z)), status, raw, int(iterations))


class _OSQP:
    """OSQP on the stacked form (P, q, [A; C], lb, ub), set up once; each step updates its numbers."""

    def __init__(self, max_iter: int, eps: float):
        import osqp

        self._osqp = osqp
        self.max_iter, self.eps = max_iter, eps
        self.solver = None

    def reset(self):
        self.solver = None

    def solve(self, qp: QP, warm: tuple | None, time_limit: float | None) -> _Result:
        P, q, A, lb, ub = qp.stacked()
        P = _upper_csc(P)
        A = _full_csc(A)
        if self.solver is None or (P.nnz, A.nnz) != self._nnz:
            self.solver = self._osqp.OSQP()
            self.solver.setup(P=P, q=q, A=A, l=lb, u=ub, verbose=False, eps_abs=self.eps, eps_rel=self.eps,
                              max_iter=self.max_iter, polishing=False, warm_starting=True,
                              time_limit=1e10 if time_limit is None else time_limit)  # OSQP: 1e10 = none
            self._nnz = (P.nnz, A.nnz)
        else:
            self.solver.update(Px=P.data, Ax=A.data, q=q, l=lb, u=ub)
        if warm is not None:
            self.solver.warm_start(x=warm[0], y=warm[1])
        r = self.solver.solve(raise_error=False)
        S = self._osqp.SolverStatus
        status = {S.OSQP_SOLVED: SUCCESS, S.OSQP_MAX_ITER_REACHED: LIMITED, S.OSQP_TIME_LIMIT_REACHED: LIMITED,
                  S.OSQP_SOLVED_INACCURATE: LIMITED, S.OSQP_PRIMAL_INFEASIBLE: INFEASIBLE,
                  S.OSQP_PRIMAL_INFEASIBLE_INACCURATE: INFEASIBLE, S.OSQP_DUAL_INFEASIBLE: INFEASIBLE,
                  S.OSQP_DUAL_INFEASIBLE_INACCURATE: INFEASIBLE}.get(r.info.status_val, EXCEPTION)
        z = np.array(r.x, dtype=float) if r.x is not None else np.full(qp.n, np.nan)
        y = np.array(r.y, dtype=float) if r.y is not None else np.zeros(lb.size)
        return _Result(z, (z, y), status, r.info.status, int(r.info.iter))


class _HPIPM:
    """HPIPM (structure-exploiting interior point, through CasADi) on the sparse traditional form (p = T).

    Variables are reordered to HPIPM's stage order [x_0 u_0 x_1 u_1 … x_T]; x_0 = x0 and all bounds become
    box bounds, the dynamics rows its stage gaps. Its residual tolerance is max(eps, 1e-6): at nlink:13, T=100
    HPIPM reached 1e-6 in about 10 iterations and did not reach 1e-8 within 200 (measured here).
    """

    def __init__(self, tr, max_iter: int, eps: float):
        n, m, T = tr.n, tr.m, tr.T
        nX = n * (T + 1)
        self._perm = np.concatenate([np.r_[np.arange(k * n, (k + 1) * n), nX + np.arange(k * m, (k + 1) * m)]
                                     for k in range(T)] + [np.arange(T * n, nX)])
        self._n, self._T, self._m = n, T, m
        self.max_iter, self.eps = max_iter, eps
        self.reset()

    def reset(self):
        self.solver = None

    def _setup(self, H, A):
        import casadi as ca

        n, m, T = self._n, self._m, self._T
        tol = max(self.eps, 1e-6)
        opts = {"N": T, "nx": [n] * (T + 1), "nu": [m] * T + [0], "ng": [0] * (T + 1), "error_on_fail": False,
                "hpipm": {"mode": "balance", "iter_max": self.max_iter, "warm_start": 0, "res_g_max": tol,
                          "res_b_max": tol, "res_d_max": tol, "res_m_max": tol}}
        self._sp = {k: ca.Sparsity(*M.shape, M.indptr.tolist(), M.indices.tolist()) for k, M in (("h", H), ("a", A))}
        self.solver = ca.conic("hpipm", "hpipm", self._sp, opts)
        self._ca = ca

    def solve(self, qp: QP, warm: tuple | None, time_limit: float | None) -> _Result:
        start = time.perf_counter()
        perm, n = self._perm, self._n
        H = qp.P[perm][:, perm].tocsc()
        A = qp.A[n:][:, perm].tocsc()  # the dynamics gaps; the first n rows (x_0 = x0) become bounds
        if self.solver is None:
            self._setup(H, A)
        ca = self._ca
        lbx, ubx = np.full(qp.n, -np.inf), np.full(qp.n, np.inf)
        sel = sp.csr_matrix(qp.C).indices  # each row of C selects one variable
        lbx[sel], ubx[sel] = qp.l, qp.u
        lbx[:n] = ubx[:n] = -qp.b[:n]
        r = self.solver(h=ca.DM(self._sp["h"], H.data), g=qp.q[perm], a=ca.DM(self._sp["a"], A.data),
                        lba=qp.b[n:], uba=qp.b[n:], lbx=lbx[perm], ubx=ubx[perm])
        stats = self.solver.stats()
        code = stats.get("return_status", -1)
        status = {0: SUCCESS, 1: LIMITED, 2: LIMITED, 3: NAN}.get(code, EXCEPTION)
        raw = {0: "HPIPM success", 1: "HPIPM max iterations", 2: "HPIPM minimum step length",
               3: "HPIPM NaN"}.get(code, f"HPIPM status {code}")
        if status == SUCCESS and time_limit is not None and time.perf_counter() - start > time_limit:
            status, raw = LIMITED, f"time limit {time_limit:g} s exceeded ({raw})"
        z = np.empty(qp.n)
        z[perm] = np.asarray(r["x"]).ravel()
        return _Result(z, (z,), status, raw, int(stats.get("iter_count", 0)))


def _upper_csc(P):
    """Upper triangle of P as CSC with a pattern that depends only on the shape (dense) or on P's pattern."""
    if sp.issparse(P):
        return sp.triu(P, format="csc")
    n = P.shape[0]
    cols = np.arange(n)
    indptr = np.r_[0, np.cumsum(cols + 1)]
    indices = np.concatenate([np.arange(j + 1) for j in cols]) if n else np.zeros(0, int)
    # Column j of the upper triangle holds P[0..j, j] = P[j, 0..j] (P symmetric): the lower triangle row-major.
    return sp.csc_matrix((P[np.tril_indices(n)], indices, indptr), shape=P.shape)


def _full_csc(A):
    """A as CSC; dense matrices keep every entry (zeros included) so the pattern never changes."""
    if sp.issparse(A):
        return A.tocsc()
    r, c = A.shape
    indptr = np.arange(0, r * c + 1, r)
    indices = np.tile(np.arange(r), c)
    return sp.csc_matrix((A.ravel(order="F"), indices, indptr), shape=A.shape)


class LinearMPC(Controller):
    """Re-linearized MPC through a QP: ``form`` "sparse" (large matrix) or "condensed" (small matrix),
    ``qp`` "proxqp", "osqp" or "hpipm" (sparse traditional form only), any parameterization of the OCP. Warm-starts from the previous solution.

    ``max_iter`` caps the QP iterations and ``time_limit`` (seconds) the backend's wall-clock time; a
    step that hits either returns status "limited" with the fallback input.

    ``linearization`` picks the input ū of the expansion point (x, ū): "goal" (default) uses the input
    goal u_g (OCP.input_goal), "plan"
    the input the previous plan expects now. For robots the two differ: about a nonzero torque the
    linearized N-link dynamics are exponentially unstable (|eig A_d| ≈ 1.12 per 10 ms step at nlink:13),
    which over a 1 s horizon makes the condensed P ill-conditioned (eigenvalues 0.06…6e10) and both ProxQP
    and OSQP hit their iteration limits; about u_goal = 0 the same robot gives eigenvalues 0.06…6e4, and
    in closed loop on nlink:7 "goal" was never worse (3 seeded trials, 0 vs 118 fallbacks).
    """

    def __init__(self, ocp: OCP, *, form: str = "condensed", qp: str = "proxqp", max_iter: int = 10_000,
                 eps: float = 1e-9, time_limit: float | None = None, warm_start: bool = True,
                 raise_on_fail: bool = False, linearization: str = "goal"):
        self.linearization = check_linearization(linearization)
        choice(form, tuple(TRANSCRIPTIONS), "form")
        choice(qp, QP_SOLVERS, "qp")
        self.form, self.qp_name = form, qp
        self.warm_start = bool(warm_start)
        self.time_limit = None if time_limit is None else positive(time_limit, "time_limit")
        self.transcription = TRANSCRIPTIONS[form](ocp)
        if qp == "hpipm" and not (form == "sparse" and ocp.knots == ocp.horizon):
            raise ValueError(f"qp 'hpipm' needs form 'sparse' and the identity parameterization (knots = horizon, "
                             f"traditional MPC), got form {form!r} with {ocp.knots} knots over {ocp.horizon} steps")
        eps = positive(eps, "eps")
        self._backend = (_ProxQP(form == "sparse", 1, eps) if qp == "proxqp" else _OSQP(1, eps) if qp == "osqp"
                         else _HPIPM(self.transcription, 1, eps))
        self.max_iter = max_iter
        super().__init__(ocp, raise_on_fail=raise_on_fail)

    @property
    def max_iter(self) -> int:
        """The QP solver's iteration limit (settable between steps)."""
        return self._backend.max_iter

    @max_iter.setter
    def max_iter(self, value: int) -> None:
        self._backend.max_iter = integer(value, "max_iter", 1)
        self._backend.reset()

    def __repr__(self):
        return f"LinearMPC({self.form}, {self.qp_name}, {self.ocp!r})"

    def reset(self) -> None:
        super().reset()
        self._warm = None
        self._backend.reset()

    def _solve(self, x: np.ndarray, goal: np.ndarray) -> Solution:
        ocp, times = self.ocp, {"model": 0.0, "build": 0.0, "solve": 0.0}
        t0 = time.perf_counter()
        model = self.affine_model(x, goal, self.linearization)
        t1 = time.perf_counter()
        times["model"] = t1 - t0
        if model is None:
            return self._fail(NAN, f"non-finite affine model at x = {x.tolist()}", times)
        qp = self.transcription.build(*model, x, goal)
        t2 = time.perf_counter()
        times["build"] = t2 - t1
        problem = qp.check()
        if problem is not None:
            return self._fail(INFEASIBLE if "above" in problem else NAN, problem, times)
        try:
            res = self._backend.solve(qp, self._warm if self.warm_start else None, self.time_limit)
        except Exception as exc:  # a backend that throws must not stop the control loop
            times["solve"] = time.perf_counter() - t2
            return self._fail(EXCEPTION, f"{type(exc).__name__}: {exc}", times)
        times["solve"] = time.perf_counter() - t2
        if res.status == SUCCESS and not np.isfinite(res.z).all():
            res.status = NAN
        if res.status != SUCCESS:
            return self._fail(res.status, res.raw_status, times, res.iterations)
        self._warm = res.duals
        knots = self.transcription.knots(res.z).copy()
        x_pred = (self.transcription.states(res.z) if self.form == "sparse"
                  else self.transcription.states(res.z, x))
        u = ocp.parameterization.u_at(knots, 0)
        return Solution(u=u, knots=knots, status=SUCCESS, raw_status=res.raw_status, iterations=res.iterations,
                        x_pred=x_pred, times=times)

    def _fail(self, status, raw, times, iterations=0) -> Solution:
        """Fallback solution and a clean workspace for the next step (no stale warm start)."""
        self._warm = None
        self._backend.reset()
        return self.fallback(status, raw, times, iterations)


SOLVERS = {"qp": LinearMPC}
