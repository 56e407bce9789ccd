"""HPIPM behind the QP backend interface (:class:`~ocpkit.qp.interface.QPBackend`): the sparse traditional QP in
HPIPM's stage order."""

from __future__ import annotations

import sys
import time

import numpy as np
import scipy.sparse as sp

from ocpkit.qp.interface import QPBackend, Result, skipped, time_left
from ocpkit.qp.quadratic_program import QP
from ocpkit.status import EXCEPTION, LIMITED, NAN, SUCCESS, OperationCosts, Reason


class HPIPM(QPBackend):
    """HPIPM (structure-exploiting interior point, through CasADi) on the sparse traditional form (p = T).

    Variables are reordered to HPIPM's stage order [x_0 u_0 x_1 u_1 … x_T]; x_0 = x0 and all bounds become
    box bounds, the dynamics rows its stage gaps. Its residual tolerance is max(eps, 1e-6), absolute: at nlink:13,
    T=100 HPIPM reached 1e-6 in about 10 iterations and did not reach 1e-8 within 200; at nlink:13, T = 50 (the
    RTI QPs of a closed loop) 1e-6 took 10-12 iterations and its answers held the certificate to 3e-9 relative,
    where 1e-8 ran into 200 iterations and left answers 0.6 off (measured here).

    The QP goes in and the answer comes out through a CasADi function buffer, the arrays' memory itself: the
    ``DM`` conversion of the 52,000 dynamics nonzeros alone took 1.4-2.5 ms at nlink:13, T = 50. Each solve takes
    a new buffer (0.1 ms), which matched CasADi's ordinary call on every QP tried: one buffer evaluated again and
    again answered wrongly in a test harness (states 2.0 off; not understood, so not risked). The interface keeps
    nothing between solves, so it is built once for a structure, iteration limit and tolerance and kept across
    :meth:`reset`.

    HPIPM starts from a primal guess (its ``warm_start`` 1): the warm start's z (the previous answer), else zero,
    each bounded variable moved WARM_INTERIOR of its range inside its bounds. RTI closed loops at T = 50, seeds 0-2
    and 3-5, CPU time at load 4.6-5 on 2 CPUs, against HPIPM's own cold start: median step nlink:13 12.3 and 11.1 ms
    (14.0, 13.0; HPIPM iterations 8 and 7 against 10), Puma 560 2.5 and 2.3 (3.0, 2.7), Panda 2.9 and 2.9 (3.4,
    3.4), no 90th percentile worse, every step certified; the previous answer as it is (its bounds active) took
    Panda up to 39 iterations where a cold start took 13.
    """

    factorizes = False
    # HPIPM's "balance" mode (its LQ factorization where the Riccati one is ill-conditioned); "speed" took 10 %
    # less per iteration at nlink:13 but up to 18 iterations where balance took 12.
    MODE = "balance"
    WARM_INTERIOR = 0.1

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
        self.solver = None

    def reset(self):
        """Forget the warm start, of which there is none: the interface built for this structure stays."""

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
                "mode": self.MODE,
                "iter_max": self.max_iter,
                "warm_start": 1,
                "res_g_max": tol,
                "res_b_max": tol,
                "res_d_max": tol,
                "res_m_max": tol,
            },
        }
        sparsity = {k: ca.Sparsity(*M.shape, M.indptr.tolist(), M.indices.tolist()) for k, M in (("h", H), ("a", A))}
        if "acados_template" in sys.modules:  # the acados peer's HPIPM and BLASFEO have these libraries' names
            raise RuntimeError(
                "CasADi's HPIPM cannot run in a process that has loaded the acados peer (their HPIPM and BLASFEO "
                "libraries share names, and the process crashes): run acados in a process of its own"
            )
        self.solver = ca.conic("hpipm", "hpipm", sparsity, opts)
        f = self.solver
        self._made = (self.max_iter, self.eps, H.indptr.copy(), H.indices.copy(), A.indptr.copy(), A.indices.copy())
        self._args = {f.name_in(i): np.zeros(f.nnz_in(i)) for i in range(f.n_in())}
        self._results = {f.name_out(i): np.zeros(f.nnz_out(i)) for i in range(f.n_out())}

    def _structure(self, H, A) -> bool:
        """Whether the interface built last fits this QP (structure, iteration limit, tolerance)."""
        if self.solver is None:
            return False
        max_iter, eps, *pattern = self._made
        now = (H.indptr, H.indices, A.indptr, A.indices)
        return (max_iter, eps) == (self.max_iter, self.eps) and all(map(np.array_equal, pattern, now))

    def solve(self, qp: QP, warm: tuple | None, deadline: float | None) -> Result:
        """HPIPM cannot be stopped from outside: with a deadline it starts only if its measured time fits."""
        if self.solver is not None and not self.costs.fits("solve", time_left(deadline)):
            return skipped("solve", self.costs, deadline, qp.n)
        start = time.perf_counter()
        perm, n = self._perm, self._n
        H = qp.P[perm][:, perm].tocsc()
        A = qp.A[n:][:, perm].tocsc()  # the dynamics gaps; the first n rows (x_0 = x0) become bounds
        if not self._structure(H, A):
            self._setup(H, A)
        args, results = self._args, self._results
        lbx, ubx = np.full(qp.n, -np.inf), np.full(qp.n, np.inf)
        sel = sp.csr_matrix(qp.C).indices  # each row of C selects one variable
        lbx[sel], ubx[sel] = qp.l, qp.u
        lbx[:n] = ubx[:n] = -qp.b[:n]
        args["h"][:], args["a"][:], args["g"][:] = H.data, A.data, qp.q[perm]
        args["lba"][:] = args["uba"][:] = qp.b[n:]
        args["lbx"][:], args["ubx"][:] = lbx[perm], ubx[perm]
        guess = np.array(warm[0], dtype=float) if warm is not None and np.size(warm[0]) == qp.n else np.zeros(qp.n)
        margin = self.WARM_INTERIOR * (qp.u - qp.l)
        inside = np.isfinite(margin)  # both bounds finite
        rows = sel[inside]
        guess[rows] = np.clip(guess[rows], qp.l[inside] + margin[inside], qp.u[inside] - margin[inside])
        args["x0"][:] = guess[perm]
        buffer, evaluate = self.solver.buffer()
        for i, name in enumerate(self.solver.name_in()):
            buffer.set_arg(i, memoryview(args[name]))
        for i, name in enumerate(self.solver.name_out()):
            results[name].fill(0.0)  # the interface adds the answer into its outputs
            buffer.set_res(i, memoryview(results[name]))
        evaluate()
        self.costs.add("solve", time.perf_counter() - start)
        stats = buffer.stats()
        code = stats.get("return_status", -1)
        status = {0: SUCCESS, 1: LIMITED, 2: LIMITED, 3: NAN}.get(code, EXCEPTION)
        raw = {0: "HPIPM success", 1: "HPIPM max iterations", 2: "HPIPM minimum step length", 3: "HPIPM NaN"}.get(
            code, f"HPIPM status {code}"
        )
        reason = Reason.ITERATION_LIMIT if code == 1 else None
        if status == SUCCESS and deadline is not None and time.perf_counter() > deadline:
            status, raw, reason = LIMITED, f"time budget exceeded ({raw})", Reason.TIME_BUDGET
        z, lam_x = np.empty(qp.n), np.empty(qp.n)
        z[perm] = results["x"]
        lam_x[perm] = results["lam_x"]
        # CasADi's convention Hz + g + Aᵀλ_a + λ_x = 0: the dynamics rows' λ_a, and x_0 = x0 (rows −I z = b) as bounds
        y = np.r_[-lam_x[:n], results["lam_a"]]
        return Result(z, (z,), status, raw, int(stats.get("iter_count", 0)), y=y, w=lam_x[sel], reason=reason)
