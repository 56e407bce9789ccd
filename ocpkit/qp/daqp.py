"""DAQP behind the QP backend interface (:class:`~ocpkit.qp.interface.QPBackend`), and DAQP's exit flags in words
and as ocpkit statuses and reasons (for the Python step and the exported C step alike)."""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from ocpkit.qp.interface import QPBackend, Result, time_left
from ocpkit.qp.quadratic_program import QP
from ocpkit.status import EXCEPTION, INFEASIBLE, LIMITED, SUCCESS, OperationCosts, Reason

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
