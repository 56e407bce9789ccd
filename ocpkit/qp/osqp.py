"""OSQP behind the QP backend interface (:class:`~ocpkit.qp.interface.QPBackend`): the QP as CSC matrices whose
pattern stays fixed from step to step, so OSQP updates its numbers without a new factorization pattern."""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from ocpkit.qp.interface import QPBackend, Result, skipped, time_left
from ocpkit.qp.quadratic_program import QP
from ocpkit.status import EXCEPTION, INFEASIBLE, LIMITED, SUCCESS, OperationCosts, Reason


class OSQP(QPBackend):
    """OSQP on the stacked form (P, q, [A; C], lb, ub), set up once; each step updates its numbers.

    The update's return codes are checked (a failed update leaves the previous problem in place) and the
    time left of the step is OSQP's ``time_limit`` on every solve (OSQP counts its update time in it); the
    setup and the update (numeric refactorization), with the conversion of the data, start only if their measured
    time fits. A primal start ``(z,)`` starts the multipliers from zero.
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
        if warm is not None and warm[0].shape == (qp.n,) and (len(warm) == 1 or warm[1].shape == lb.shape):
            solver.warm_start(x=warm[0], y=warm[1] if len(warm) == 2 else np.zeros(lb.size))  # (z,): y from zero
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
