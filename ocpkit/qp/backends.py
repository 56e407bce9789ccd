"""The QP solvers behind :class:`~ocpkit.solvers.qp.LinearMPC` (and through it the real-time iteration and the sampling
planners' preconditioner): ProxQP, OSQP, HPIPM and DAQP behind one small interface,
:class:`~ocpkit.qp.interface.QPBackend`.

A backend is made once per controller (:func:`make_backend`) and then asked, step after step, to ``solve`` the
step's QP (:class:`ocpkit.qp.transcription.QP`) with a warm start (the previous answer's ``duals``) and a deadline. It
sets itself up on the first solve (and again when the QP's structure changes), updates its numbers on the later
ones, and forgets everything on ``reset``. Every operation that cannot be stopped from outside starts only if its
measured time (``costs``) fits in what is left of the deadline.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from ocpkit.status import EXCEPTION, INFEASIBLE, LIMITED, NAN, SUCCESS, OperationCosts, Reason
from ocpkit.qp.interface import QPBackend, Result, skipped, time_left
from ocpkit.qp.quadratic_program import QP
from ocpkit.qp.sparse import SparseQP

QP_SOLVERS = ("proxqp", "osqp", "hpipm", "daqp")
# DAQP's exit flags (daqp/include/constants.h): their names and ocpkit statuses, for the Python step and the C
# step's failures (ocpkit.export) alike.
DAQP_EXIT = {
    1: ("optimal", SUCCESS),
    2: ("soft optimal", SUCCESS),
    -1: ("infeasible", INFEASIBLE),
    -2: ("cycling", LIMITED),
    -3: ("unbounded", INFEASIBLE),
    -4: ("iteration limit", LIMITED),
    -5: ("nonconvex", EXCEPTION),
    -6: ("overdetermined initial working set", EXCEPTION),
    -7: ("time limit", LIMITED),
}
DAQP_REASON = {
    -1: Reason.QP_INFEASIBLE,
    -3: Reason.QP_INFEASIBLE,
    -4: Reason.ITERATION_LIMIT,
    -5: Reason.NOT_DEFINITE,
    -7: Reason.TIME_BUDGET,
}  # the failed flags' reasons, where one is said


def daqp_exit_name(flag: int) -> str:
    """DAQP's exit flag in words, as a raw status."""
    name = DAQP_EXIT[flag][0] if flag in DAQP_EXIT else f"exit flag {flag}"
    return f"DAQP {name}" + (" (Hessian not positive definite)" if flag == -5 else "")


class ProxQP(QPBackend):
    """ProxQP, dense or sparse backend. One solver object is kept across steps and refreshed with ``update``
    (warm-started from its previous result); knot bounds go to the dense backend as box constraints.

    ProxQP's own ``max_iter`` counts outer (BCL) iterations only, each allowing ``max_iter_in`` inner ones
    (15 M inner iterations at x = 1e20 on the pendulum), so it is run in chunks of outer × CHUNK_INNER inner
    iterations, continuing from the previous iterate: ``max_iter`` caps the total inner iterations, and with a
    deadline a chunk (or the init/update) starts only if its measured time fits. A chunk restarts ProxQP's
    BCL tolerances, so chunks of a fixed 5 outer iterations never converged on a QP that needs more (the
    pendulum with an active hard state bound: 10,000 iterations, where one solve takes 13): the outer count
    starts at CHUNK_OUTER and doubles after every chunk that ends at its limit, each size timed on its own
    (one not yet measured is predicted at twice the size below it).

    A warm start from the previous step can leave ProxQP stalled with zero residuals and an open duality gap
    (the pendulum driven against a soft state bound: 10,000 iterations on every later step, where a cold solve
    takes 34), so a warm-started solve gets WARM_INNER inner iterations; if it has not converged by then the
    QP is solved again from a cold start with what is left of the iterations and the budget.
    """

    CHUNK_OUTER, CHUNK_MAX_OUTER, CHUNK_INNER = 5, 640, 50
    WARM_INNER = 500
    GAP_REL = 1e-12

    factorizes = False

    def __init__(self, sparse: bool, max_iter: int, eps: float):
        import proxsuite

        self._sparse = sparse
        self._module = proxsuite.proxqp.sparse if sparse else proxsuite.proxqp.dense
        self._proxqp = proxsuite.proxqp
        self.max_iter, self.eps = max_iter, eps
        self.costs = OperationCosts(like={"update": "init", "init": "update"})
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

    def solve(self, qp: QP, warm: tuple | None, deadline: float | None) -> Result:
        """Solve in chunks up to ``max_iter`` inner iterations and, with a deadline (perf_counter), up to it."""
        return self._solve(qp, warm, deadline, self.max_iter)

    def _solve(self, qp: QP, warm: tuple | None, deadline: float | None, max_iter: int) -> Result:
        px, costs = self._proxqp, self.costs
        data, key = self._data(qp)
        H, g, A, b, C, l, u, lo, hi = data
        box = {"l_box": lo, "u_box": hi} if key[3] else {}
        reuse = warm is not None and self.solver is not None and self._key == key
        op = "update" if reuse else "init"
        if not costs.fits(op, time_left(deadline)):
            return skipped(op, costs, deadline, qp.n)
        t = time.perf_counter()
        if not reuse:
            n, n_eq, n_in, has_box = key
            self._key = None  # until init succeeds
            self.solver = (
                self._module.QP(n, n_eq, n_in, box_constraints=True) if has_box else self._module.QP(n, n_eq, n_in)
            )
        solver = self.solver
        s = solver.settings
        # Relative tolerances too: on a 7-DoF URDF arm with error multiplier 0.5 (Hessian condition 1e11, gradient
        # 1e8, objective 1e7) an absolute 1e-9 alone was never met: every step 10,000 iterations, then the fallback.
        s.eps_abs, s.eps_rel, s.verbose = self.eps, self.eps, False
        # Primal and dual residuals alone let a warm-started solve stop early with a wrong active set
        # (5.8e-4 off in u on the pendulum); the duality gap closes that (GAP_REL: its part relative to the
        # objective's terms, far below eps wherever they are of order one).
        s.check_duality_gap, s.eps_duality_gap_abs, s.eps_duality_gap_rel = True, self.eps, self.GAP_REL
        first = ()
        if reuse:
            s.initial_guess = px.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
            solver.update(H, g, A, b, C, l, u, **box)
        else:
            # A fresh box-constrained solver starts cold: ProxQP 0.8 rejects (or crashes on) warm box duals.
            warm_ok = warm is not None and not key[3]
            s.initial_guess = px.InitialGuess.WARM_START if warm_ok else px.InitialGuess.NO_INITIAL_GUESS
            solver.init(H, g, A, b, C, l, u, **box)
            self._key = key
            first = warm if warm_ok else ()
        warm_started = reuse or bool(first)
        costs.add(op, time.perf_counter() - t)
        out = px.QPSolverOutput
        iterations, chunks, why, reason, outer = 0, 0, None, None, self.CHUNK_OUTER
        while True:
            left_iter = max_iter - iterations
            if left_iter <= 0:
                why, reason = f"max_iter {self.max_iter} reached", Reason.ITERATION_LIMIT
                break
            if warm_started and iterations >= self.WARM_INNER:  # stalled from the warm start
                return self._cold_again(qp, deadline, left_iter, iterations)
            chunk = f"chunk x{outer}"
            if not costs.fits(chunk, time_left(deadline)):
                why = (
                    f"time budget reached after {iterations} iterations (a chunk measured at "
                    f"{1e3 * costs.predict(chunk):.3g} ms)"
                )
                reason = Reason.TIME_BUDGET
                break
            s.max_iter_in = min(self.CHUNK_INNER, left_iter)
            s.max_iter = max(1, min(outer, left_iter // (s.max_iter_in + 1)))
            t = time.perf_counter()
            solver.solve(*first) if first else solver.solve()
            costs.add(chunk, time.perf_counter() - t)
            first, chunks = (), chunks + 1
            if outer < self.CHUNK_MAX_OUTER:
                outer *= 2
                costs.double_of(f"chunk x{outer}", chunk)
            s.initial_guess = px.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
            iterations += solver.results.info.iter
            if solver.results.info.status != out.PROXQP_MAX_ITER_REACHED:
                break
        r = solver.results
        if warm_started and r.info.status in (out.PROXQP_PRIMAL_INFEASIBLE, out.PROXQP_DUAL_INFEASIBLE):
            # ProxQP's infeasibility test misfires from a warm start far from the new solution (a soft-bounded,
            # always feasible QP was reported infeasible): confirm it from a cold start.
            return self._cold_again(qp, deadline, max_iter - iterations, iterations)
        duals = (np.array(r.x), np.array(r.y), np.array(r.z))
        if not chunks:
            return Result(duals[0], duals, LIMITED, why, 0, reason=reason)
        status = {
            out.PROXQP_SOLVED: SUCCESS,
            out.PROXQP_MAX_ITER_REACHED: LIMITED,
            out.PROXQP_PRIMAL_INFEASIBLE: INFEASIBLE,
            out.PROXQP_DUAL_INFEASIBLE: INFEASIBLE,
            out.PROXQP_SOLVED_CLOSEST_PRIMAL_FEASIBLE: INFEASIBLE,
        }.get(r.info.status, EXCEPTION)
        raw = str(r.info.status).rsplit(".", 1)[-1]
        if status == LIMITED and why is not None:
            raw = f"{why} ({raw})"
        return Result(
            duals[0],
            duals,
            status,
            raw,
            int(iterations),
            y=duals[1],
            w=self._bound_duals(qp, duals[2], key[3]),
            reason=reason if status == LIMITED else None,
        )

    @staticmethod
    def _bound_duals(qp: QP, z_in: np.ndarray, has_box: bool) -> np.ndarray:
        """ProxQP's inequality multipliers as w of the QP's rows C: with a box, its rows are the box's (last n of
        ProxQP's z, picked at the boxed variables) and then the general rows (the first ones)."""
        if not has_box:
            return z_in
        k = len(qp.box)
        return np.r_[z_in[z_in.size - qp.n :][qp.box], z_in[: qp.l.size - k]]

    def _cold_again(self, qp: QP, deadline: float | None, max_iter: int, spent: int) -> Result:
        """The QP again from a cold start, with ``max_iter`` inner iterations left (``spent`` already used)."""
        self.reset()
        res = (
            self._solve(qp, None, deadline, max_iter)
            if max_iter > 0
            else Result(
                np.full(qp.n, np.nan),
                (),
                LIMITED,
                f"max_iter {self.max_iter} reached",
                0,
                reason=Reason.ITERATION_LIMIT,
            )
        )
        res.iterations += spent
        return res


class OSQP(QPBackend):
    """OSQP on the stacked form (P, q, [A; C], lb, ub), set up once; each step updates its numbers.

    The update's return codes are checked (a failed update leaves the previous problem in place) and the
    time left of the step is OSQP's ``time_limit`` on every solve (OSQP counts its update time in it); the
    setup and the update (numeric refactorization), with the conversion of the data, start only if their measured
    time fits.
    """

    factorizes = False

    def __init__(self, max_iter: int, eps: float):
        import osqp

        self._osqp = osqp
        self.max_iter, self.eps = max_iter, eps
        self.costs = OperationCosts(like={"update": "setup", "setup": "update"})
        self.solver, self._shape = None, None

    def reset(self):
        self.solver = None

    def solve(self, qp: QP, warm: tuple | None, deadline: float | None) -> Result:
        costs = self.costs
        # The setup or update includes the conversion to OSQP's data, checked against the time left before it: a
        # soft obstacle QP of 1,100 dense variables took 50 ms to convert before a refusal.
        shape = (qp.n, qp.b.size + qp.l.size)
        op = "setup" if self.solver is None or shape != self._shape else "update"
        if not costs.fits(op, time_left(deadline)):
            return skipped(op, costs, deadline, qp.n)
        t = time.perf_counter()
        P, q, A, lb, ub = qp.stacked()
        P = _upper_csc(P)
        A = _full_csc(A)
        if op == "update" and (P.nnz, A.nnz) != self._nnz:  # a sparse QP's pattern changed: a new setup
            op = "setup"
            if not costs.fits(op, time_left(deadline)):
                return skipped(op, costs, deadline, qp.n)
        left = time_left(deadline)
        limit = 1e10 if left is None else left  # OSQP: 1e10 = no limit
        if op == "setup":
            self.solver = None
            solver = self._osqp.OSQP()
            solver.setup(
                P=P,
                q=q,
                A=A,
                l=lb,
                u=ub,
                verbose=False,
                eps_abs=self.eps,
                eps_rel=self.eps,
                max_iter=self.max_iter,
                polishing=False,
                warm_starting=True,
                time_limit=limit,
            )
            self.solver, self._nnz, self._shape = solver, (P.nnz, A.nnz), shape
        else:
            solver = self.solver
            solver.update_settings(time_limit=limit, max_iter=self.max_iter)
            inf = solver.constant("OSQP_INFTY")
            raw = getattr(solver, "_solver", None)
            if raw is None:  # no access to the return codes: the wrapper's update (unchecked)
                solver.update(Px=P.data, Ax=A.data, q=q, l=lb, u=ub)
            else:
                codes = (
                    raw.update_data_vec(q=q, l=np.maximum(lb, -inf), u=np.minimum(ub, inf)),
                    raw.update_data_mat(P_x=P.data, P_i=None, A_x=A.data, A_i=None),
                )
                if any(codes):
                    self.solver = None  # the workspace still holds the previous problem
                    return Result(
                        np.full(qp.n, np.nan),
                        (),
                        EXCEPTION,
                        f"OSQP update failed (codes {codes[0]}, {codes[1]})",
                        0,
                        reason=Reason.SOLVER_ERROR,
                    )
        costs.add(op, time.perf_counter() - t)
        if warm is not None and len(warm) == 2 and warm[0].shape == (qp.n,) and warm[1].shape == lb.shape:
            solver.warm_start(x=warm[0], y=warm[1])
        r = solver.solve(raise_error=False)
        S = self._osqp.SolverStatus
        status = {
            S.OSQP_SOLVED: SUCCESS,
            S.OSQP_MAX_ITER_REACHED: LIMITED,
            S.OSQP_TIME_LIMIT_REACHED: LIMITED,
            S.OSQP_SOLVED_INACCURATE: LIMITED,
            S.OSQP_PRIMAL_INFEASIBLE: INFEASIBLE,
            S.OSQP_PRIMAL_INFEASIBLE_INACCURATE: INFEASIBLE,
            S.OSQP_DUAL_INFEASIBLE: INFEASIBLE,
            S.OSQP_DUAL_INFEASIBLE_INACCURATE: INFEASIBLE,
        }.get(r.info.status_val, EXCEPTION)
        reason = {S.OSQP_MAX_ITER_REACHED: Reason.ITERATION_LIMIT, S.OSQP_TIME_LIMIT_REACHED: Reason.TIME_BUDGET}.get(
            r.info.status_val
        )
        z = np.array(r.x, dtype=float) if r.x is not None else np.full(qp.n, np.nan)
        y = np.array(r.y, dtype=float) if r.y is not None else np.zeros(lb.size)
        return Result(
            z, (z, y), status, r.info.status, int(r.info.iter), y=y[: qp.b.size], w=y[qp.b.size :], reason=reason
        )


class HPIPM(QPBackend):
    """HPIPM (structure-exploiting interior point, through CasADi) on the sparse traditional form (p = T).

    Variables are reordered to HPIPM's stage order [x_0 u_0 x_1 u_1 … x_T]; x_0 = x0 and all bounds become
    box bounds, the dynamics rows its stage gaps. Its residual tolerance is max(eps, 1e-6): at nlink:13, T=100
    HPIPM reached 1e-6 in about 10 iterations and did not reach 1e-8 within 200 (measured here).
    """

    factorizes = False

    def __init__(self, tr, max_iter: int, eps: float):
        n, m, T = tr.n, tr.m, tr.T
        nX = n * (T + 1)
        self._perm = np.concatenate(
            [np.r_[np.arange(k * n, (k + 1) * n), nX + np.arange(k * m, (k + 1) * m)] for k in range(T)]
            + [np.arange(T * n, nX)]
        )
        self._n, self._T, self._m = n, T, m
        self.max_iter, self.eps = max_iter, eps
        self.costs = OperationCosts()
        self.reset()

    def reset(self):
        self.solver = None

    def _setup(self, H, A):
        import casadi as ca

        n, m, T = self._n, self._m, self._T
        tol = max(self.eps, 1e-6)
        opts = {
            "N": T,
            "nx": [n] * (T + 1),
            "nu": [m] * T + [0],
            "ng": [0] * (T + 1),
            "error_on_fail": False,
            "hpipm": {
                "mode": "balance",
                "iter_max": self.max_iter,
                "warm_start": 0,
                "res_g_max": tol,
                "res_b_max": tol,
                "res_d_max": tol,
                "res_m_max": tol,
            },
        }
        self._sp = {k: ca.Sparsity(*M.shape, M.indptr.tolist(), M.indices.tolist()) for k, M in (("h", H), ("a", A))}
        self.solver = ca.conic("hpipm", "hpipm", self._sp, opts)
        self._ca = ca

    def solve(self, qp: QP, warm: tuple | None, deadline: float | None) -> Result:
        """HPIPM cannot be stopped from outside: with a deadline it starts only if its measured time fits."""
        if self.solver is not None and not self.costs.fits("solve", time_left(deadline)):
            return skipped("solve", self.costs, deadline, qp.n)
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
        r = self.solver(
            h=ca.DM(self._sp["h"], H.data),
            g=qp.q[perm],
            a=ca.DM(self._sp["a"], A.data),
            lba=qp.b[n:],
            uba=qp.b[n:],
            lbx=lbx[perm],
            ubx=ubx[perm],
        )
        self.costs.add("solve", time.perf_counter() - start)
        stats = self.solver.stats()
        code = stats.get("return_status", -1)
        status = {0: SUCCESS, 1: LIMITED, 2: LIMITED, 3: NAN}.get(code, EXCEPTION)
        raw = {0: "HPIPM success", 1: "HPIPM max iterations", 2: "HPIPM minimum step length", 3: "HPIPM NaN"}.get(
            code, f"HPIPM status {code}"
        )
        reason = Reason.ITERATION_LIMIT if code == 1 else None
        if status == SUCCESS and deadline is not None and time.perf_counter() > deadline:
            status, raw, reason = LIMITED, f"time budget exceeded ({raw})", Reason.TIME_BUDGET
        z, lam_x = np.empty(qp.n), np.empty(qp.n)
        z[perm] = np.asarray(r["x"]).ravel()
        lam_x[perm] = np.asarray(r["lam_x"]).ravel()
        # CasADi's convention Hz + g + Aᵀλ_a + λ_x = 0: the dynamics rows' λ_a, and x_0 = x0 (rows −I z = b) as bounds
        y = np.r_[-lam_x[:n], np.asarray(r["lam_a"]).ravel()]
        return Result(z, (z,), status, raw, int(stats.get("iter_count", 0)), y=y, w=lam_x[sel], reason=reason)


class DAQP(QPBackend):
    """DAQP (dual active-set, dense; Arnström et al.) on the condensed form: simple bounds on every z (±1e30 where
    the QP has none), the remaining bound rows and any equality rows as general rows. Warm-started from the
    previous step's active set (the signs of its multipliers become DAQP's ``sense`` flags); a warm start DAQP
    rejects (an overdetermined initial working set) is retried cold.

    DAQP cannot be stopped from outside, so a deadline is kept in two parts (a ``daqp.Model``: set-up, then solve). Its
    set-up (the dense data, the factorizations, A R⁻¹) starts only if its measured time fits; the solve then gets the
    iterations that fit in the time left over the measured time of one (:meth:`iterations`), at most ``max_iter``,
    and that time as DAQP's own ``time_limit`` (checked every few dozen iterations: the bound for iterations slower
    than measured, or not measured yet). A step thus ends within about an iteration of its deadline, or of a set-up
    that ran longer than measured (an obstacle step of 754 variables had run 17-25 s past a 10 s ceiling).
    """

    INF = 1e30  # DAQP's "no bound"
    factorizes = True  # the backend itself refuses a P that is not positive definite (LinearMPC checks for the others)

    def __init__(self, max_iter: int, eps: float):
        import daqp

        self._daqp = daqp
        self.max_iter, self.eps = max_iter, eps
        self.costs = OperationCosts()
        self.reset()

    @property
    def tolerance(self) -> float:
        """DAQP's primal tolerance: eps within [1e-10, 1e-6]."""
        return min(1e-6, max(self.eps, 1e-10))

    def reset(self):
        self._measured = set()  # the ops timed since the last reset (an unmeasured one is not refused)

    def solve(self, qp: QP, warm: tuple | None, deadline: float | None) -> Result:
        n, k = qp.n, 0 if qp.box is None else len(qp.box)
        size = n + qp.l.size - k + qp.b.size  # DAQP's rows: the simple bounds and the general rows
        setup = f"set-up n={n}"
        left = time_left(deadline)
        # the set-up's time and each iteration's are measured per row and scaled to this QP's rows: both grow with
        # them (A R⁻¹, each iteration's constraint check), and an obstacle step's rows vary threefold step to step
        if left is not None and setup in self._measured and not self.costs.fits(setup, left / size):
            return Result(
                np.full(n, np.nan),
                (),
                LIMITED,
                f"time budget: {1e3 * max(left, 0.0):.3g} ms left, DAQP's "
                f"set-up measured at {1e3 * self.costs.predict(setup) * size:.3g} ms",
                0,
                reason=Reason.TIME_BUDGET,
            )
        start = time.perf_counter()
        lo, hi = np.full(n, -self.INF), np.full(n, self.INF)
        if k:
            lo[qp.box], hi[qp.box] = qp.l[:k], qp.u[:k]

        def dense(M):
            return M.toarray() if sp.issparse(M) else np.asarray(M, dtype=float)

        parts = [dense(qp.C)[k:]] + ([dense(qp.A)] if qp.b.size else [])
        A = np.ascontiguousarray(np.vstack(parts)) if size > n else np.zeros((0, n))
        bu = np.clip(np.concatenate([hi, qp.u[k:], qp.b]), -self.INF, self.INF)
        bl = np.clip(np.concatenate([lo, qp.l[k:], qp.b]), -self.INF, self.INF)
        sense = np.zeros(bu.size, dtype=np.int32)
        sense[bu.size - qp.b.size :] = 5  # equality: active and immutable
        if warm is not None and len(warm) == 2 and warm[1].shape == bu.shape:
            lam = warm[1][: bu.size - qp.b.size]
            free = sense[: lam.size]
            free[lam > 0] = 1  # active at the upper bound
            free[lam < 0] = 3  # active at the lower bound
        data = (np.ascontiguousarray(dense(qp.P)), np.asarray(qp.q, dtype=float), A, bu, bl)
        model = self._daqp.Model()
        flag, _ = model.setup(*data, sense)
        if flag == -6 and sense[: bu.size - qp.b.size].any():  # the warm working set is not usable: cold
            sense[: bu.size - qp.b.size] = 0
            flag, _ = model.setup(*data, sense)
        self.costs.add(setup, (time.perf_counter() - start) / size)
        self._measured.add(setup)
        if flag < 0:  # refused at the set-up (a Hessian not positive definite, an overdetermined equality set)
            return Result(
                np.full(n, np.nan),
                (),
                DAQP_EXIT.get(flag, ("", EXCEPTION))[1],
                daqp_exit_name(flag),
                0,
                reason=DAQP_REASON.get(flag),
            )
        limits = self.iterations(n, size, deadline)
        if isinstance(limits, str):
            return Result(np.full(n, np.nan), (), LIMITED, limits, 0, reason=Reason.TIME_BUDGET)
        model.settings = {"iter_limit": limits[0], "time_limit": limits[1], "primal_tol": self.tolerance}
        z, _, flag, info = model.solve()
        done = int(info.get("iterations", 0))
        if done:
            self.costs.add(f"iteration n={n}", float(info.get("solve_time", 0.0)) / done / size)
        status, raw, reason = DAQP_EXIT.get(flag, ("", EXCEPTION))[1], daqp_exit_name(flag), DAQP_REASON.get(flag)
        if flag == -7 or (flag == -4 and limits[0] < self.max_iter):
            raw = f"{raw} (time budget: {limits[0]} iterations in {1e3 * limits[1]:.3g} ms)"
            reason = Reason.TIME_BUDGET
        if status == SUCCESS and deadline is not None and time.perf_counter() > deadline:
            status, raw, reason = LIMITED, f"time budget exceeded ({raw})", Reason.TIME_BUDGET
        z = np.array(z, dtype=float)
        lam = np.array(info.get("lam", np.zeros(bu.size)), dtype=float)
        # λ = [simple bounds on z; the other bound rows; equality rows]: w of C's rows (box first), y of A's
        n_free = bu.size - qp.b.size
        w = np.r_[lam[:n][qp.box] if k else np.zeros(0), lam[n:n_free]]
        return Result(z, (z, lam), status, raw, done, y=lam[n_free:], w=w, reason=reason)

    def iterations(self, n: int, size: int, deadline: float | None) -> tuple[int, float] | str:
        """(iteration limit, DAQP's own time limit in s, 0: none) for a QP of ``n`` variables and ``size`` rows once it
        is set up, from the time left until ``deadline`` and the measured time of an iteration; why none fits."""
        left = time_left(deadline)
        if left is None:
            return self.max_iter, 0.0
        per = self.costs.predict(f"iteration n={n}") * size
        cap = self.max_iter if per <= 0.0 else min(self.max_iter, int(left / per))
        if cap < 1 or left <= 0.0:
            return (
                f"time budget: {1e3 * max(left, 0.0):.3g} ms left after DAQP's set-up, one iteration measured at "
                f"{1e3 * per:.3g} ms"
            )
        return cap, left


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


def make_backend(qp: str, transcription, max_iter: int, eps: float) -> QPBackend:
    """The backend ``qp`` (one of :data:`QP_SOLVERS`) for QPs of ``transcription`` (ProxQP: its sparse backend
    for the sparse form; HPIPM: the stage order of the sparse traditional form)."""
    if qp == "proxqp":
        return ProxQP(isinstance(transcription, SparseQP), max_iter, eps)
    if qp == "hpipm":
        return HPIPM(transcription, max_iter, eps)
    return {"osqp": OSQP, "daqp": DAQP}[qp](max_iter, eps)
