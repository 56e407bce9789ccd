"""ProxQP (proxsuite) behind the QP backend interface (:class:`~ocpkit.qp.interface.QPBackend`), dense or sparse,
run in chunks of iterations that fit the deadline."""

from __future__ import annotations

import time

import numpy as np

from ocpkit.qp.interface import QPBackend, Result, skipped, time_left
from ocpkit.qp.quadratic_program import QP
from ocpkit.status import EXCEPTION, INFEASIBLE, LIMITED, SUCCESS, OperationCosts, Reason


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
    QP is solved again from a cold start with what is left of the iterations and the budget. A primal start
    ``(z,)`` (a user's plan) is ProxQP's WARM_START from z, its multipliers from zero.
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
        primal = warm is not None and len(warm) == 1  # z alone: (z, None, None) to ProxQP
        first = (warm[0], None, None) if primal else ()
        if reuse:
            s.initial_guess = px.InitialGuess.WARM_START if primal else px.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
            solver.update(H, g, A, b, C, l, u, **box)
        else:
            # A fresh box-constrained solver starts cold: ProxQP 0.8 rejects (or crashes on) warm box duals.
            warm_ok = warm is not None and (primal or not key[3])
            s.initial_guess = px.InitialGuess.WARM_START if warm_ok else px.InitialGuess.NO_INITIAL_GUESS
            solver.init(H, g, A, b, C, l, u, **box)
            self._key = key
            first = first or (warm if warm_ok else ())
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
