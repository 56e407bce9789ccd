"""What a QP solver behind :class:`~ocpkit.solvers.qp.LinearMPC` offers (:class:`QPBackend`) and answers
(:class:`Result`), and the time budget's arithmetic they share; the backends themselves by name:
:mod:`ocpkit.qp.backends`."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ocpkit.qp.quadratic_program import QP
from ocpkit.status import INFEASIBLE, LIMITED, OperationCosts, Reason


@dataclass
class Result:
    """A backend's answer: z, its warm start (``duals``, backend-specific), status, and the multipliers in the
    convention of :mod:`ocpkit.qp.certificate` (y of the equality rows, w of the bound rows; None: not returned).
    ``reason`` says why it is not a success (an "infeasible" answer is an infeasible QP unless said otherwise)."""

    z: np.ndarray
    duals: tuple
    status: str
    raw_status: str
    iterations: int
    y: np.ndarray | None = None
    w: np.ndarray | None = None
    reason: Reason | None = None

    def __post_init__(self):
        if self.reason is None and self.status == INFEASIBLE:
            self.reason = Reason.QP_INFEASIBLE


def time_left(deadline: float | None) -> float | None:
    """Seconds left until ``deadline`` (a perf_counter value; None: no deadline)."""
    return None if deadline is None else deadline - time.perf_counter()


def skipped(
    op: str, costs: OperationCosts, deadline: float, n: int, iterations: int = 0, name: str | None = None
) -> Result:
    """The LIMITED result of a step whose budget cannot pay for ``op`` (said as ``name``, default ``op``)."""
    left = max(0.0, deadline - time.perf_counter())
    return Result(
        np.full(n, np.nan),
        (),
        LIMITED,
        f"time budget: {1e3 * left:.3g} ms left, {name or op} measured at {1e3 * costs.predict(op):.3g} ms",
        iterations,
        reason=Reason.TIME_BUDGET,
    )


class QPBackend:
    """What every backend offers LinearMPC. ``max_iter`` (settable; :meth:`reset` after changing it) and ``eps``
    are its iteration limit and tolerance, ``costs`` the measured times of its operations, ``factorizes`` whether
    it refuses a Hessian that is not positive definite itself (LinearMPC checks for the others)."""

    factorizes = False
    max_iter: int
    eps: float
    costs: OperationCosts

    def solve(self, qp: QP, warm: tuple | None, deadline: float | None) -> Result:
        """The answer to ``qp``, warm-started from ``warm`` (a previous :attr:`Result.duals`; ``(z,)``: a primal point
        alone, a user's plan, that ProxQP and OSQP start from and the others ignore; None: cold) and stopped at
        ``deadline`` (a ``time.perf_counter()`` value; None: no deadline) with status "limited"."""
        raise NotImplementedError

    def reset(self) -> None:
        """Forget the set-up, the iterate and the warm start: the next solve starts cold."""
        raise NotImplementedError
