"""What every layer may say about a solve: the statuses and failure reasons, the Solution of one MPC step and the
measured costs of a backend's operations (:class:`OperationCosts`). The QP backends, the controllers, the exported C
step's wrapper and the simulator all speak these; :mod:`ocpkit.controller` builds the Controller interface on them.
"""

from __future__ import annotations

import statistics
from collections import deque
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np


class Status(StrEnum):
    """A step's status. Each member is its string ("success", …): it equals, prints and stores as that string."""

    SUCCESS = "success"
    LIMITED = "limited"
    INFEASIBLE = "infeasible"
    NAN = "nan"
    EXCEPTION = "exception"
    # A step the solver answered whose plan, rolled out on the controller's nonlinear model, breaks an obstacle
    # clearance or a hard state bound (a softened constraint, a linearization that mispredicted): its input is
    # applied (it is the solver's best answer, often the way out of a collision), but it is not a success. Last: the
    # exported C step numbers the others 0-4 (its status code indexes STATUSES).
    SOFT = "soft"


SUCCESS, LIMITED, INFEASIBLE, NAN, EXCEPTION, SOFT = Status
STATUSES = tuple(Status)


class Reason(StrEnum):
    """Why a step is not a success, for code to decide on (``Solution.reason``; its ``raw_status`` says it in words
    for people). Each member is a few words, as it is tallied and printed."""

    TIME_BUDGET = "time budget"  # the step's budget could not pay for an operation, or was overrun
    ITERATION_LIMIT = "iteration limit"  # the QP solver stopped at its iteration limit
    STATE_BEYOND_LIMIT = "state beyond limit"  # |x| or |goal| beyond the controller's state_limit: no solve
    OUTSIDE_TRUST_REGION = "outside trust region"  # a joint velocity beyond the model's trust region: no solve
    NON_FINITE_MODEL = "non-finite model"  # the affine model (A_d, B_d, w_d) is not finite
    QP_DATA = "QP data"  # the QP's data refused before a solve: not finite, or P not symmetric
    BOUNDS_CROSSED = "bounds crossed"  # a lower bound above its upper bound in the QP
    ILL_CONDITIONED = "ill-conditioned"  # the Hessian's rounding swamps its curvature (QP.not_definite)
    NOT_DEFINITE = "not positive definite"  # the Hessian failed its factorization
    QP_INFEASIBLE = "QP infeasible"  # the QP solver found the QP infeasible (or unbounded)
    NLP_INFEASIBLE = "NLP infeasible"  # the NLP solver found no feasible point (or its restoration failed)
    NOT_CONVERGED = "not converged"  # the NLP solver stopped short of an optimum (a too-small step, a feasible point)
    SOLVER_ERROR = "solver error"  # the QP solver raised or failed to update
    NON_FINITE_SOLUTION = "non-finite solution"  # the solver's answer is not finite
    CERTIFICATE_FAILED = "certificate failed"  # the answer failed the KKT certificate
    INPUT_BOUND = "input bound"  # the answer breaks an input bound beyond BOUND_TOL
    # the plan rolled out on the nonlinear model (ocpkit.safety.PlanCheck): the kind of its worst violation
    CLEARANCE = "clearance"
    STATE_BOUND = "state bound"
    COLLISION = "collision"
    NON_FINITE_PREDICTION = "non-finite"


REASONS = tuple(Reason)  # the exported C step's reason codes: 1 + the index here (0: none)


class Refusal(str):
    """Why a QP or a step is refused: the words (this str, for people) and their :class:`Reason` (``reason``)."""

    reason: Reason

    def __new__(cls, text: str, reason: Reason):
        self = super().__new__(cls, text)
        self.reason = reason
        return self

    def __getnewargs__(self):  # pickled with its reason
        return str(self), self.reason


class OperationCosts:
    """Measured wall times of a backend's uninterruptible operations (a factorization, one chunk of
    iterations), the median of the last five of each. With a step budget an operation starts only if its
    predicted time fits in what is left; one never measured is predicted free, so the first step of a new
    controller calibrates (it is not bounded: documented in LinearMPC). ``like`` names a measured operation that
    stands in for one not yet measured (a backend's update for its init: 10 ms of sparse ProxQP update ran
    into a 5 ms budget when it was predicted free).

    An operation that does not fit is not run, so it is not measured again: slow measurements (a first call,
    a moment of load) would lock it out for good (nlink:13 at a 5 ms budget: every step "limited" after a 5.2 ms
    first build, against 1.5 ms later). Each refusal therefore lowers its prediction by SKIP_DECAY, down to
    SKIP_FLOOR of the measured time, until it is tried and measured again: an operation is retried only where at
    least half its measured time is left, so a retry overruns the time left by at most that much again."""

    SKIP_DECAY, SKIP_FLOOR = 0.99, 0.5

    def __init__(self, like: dict | None = None):
        self._seen: dict[str, deque] = {}
        self._like = dict(like or {})  # op -> a measured op that bounds it until it is measured itself
        self._decay: dict[str, float] = {}  # op -> max(SKIP_FLOOR, SKIP_DECAY ** refusals since last measured)
        self._twice: dict[str, str] = {}  # op -> an op of half its size, until it is measured itself

    def add(self, op: str, seconds: float) -> None:
        self._seen.setdefault(op, deque(maxlen=5)).append(seconds)
        self._decay.pop(op, None)

    def double_of(self, op: str, smaller: str) -> None:
        """Until ``op`` is measured, predict it at twice ``smaller`` (an operation of twice its size)."""
        if op not in self._seen:
            self._twice[op] = smaller

    def predict(self, op: str) -> float:
        if op not in self._seen and op in self._twice:
            return 2.0 * self.predict(self._twice[op])
        seen = self._seen.get(op) or self._seen.get(self._like.get(op))
        # statistics.median, not np.median: numpy's first median call in a process took 1-2 ms (lazy set-up),
        # which the first budgeted step paid (a 1 ms budget overran to 2.4 ms).
        return self._decay.get(op, 1.0) * statistics.median(seen) if seen else 0.0

    def fits(self, op: str, left: float | None) -> bool:
        if left is None:
            return True
        if left > 0.0 and self.predict(op) <= left:
            return True
        self._decay[op] = max(self.SKIP_FLOOR, self._decay.get(op, 1.0) * self.SKIP_DECAY)
        return False


@dataclass
class Solution:
    """One MPC step: the input to apply, the knots and predicted states behind it, status and timings (s)."""

    u: np.ndarray
    knots: np.ndarray
    status: Status
    raw_status: str = ""  # the status in words, for people
    iterations: int = 0
    x_pred: np.ndarray | None = None
    times: dict = field(default_factory=lambda: {"model": 0.0, "build": 0.0, "solve": 0.0, "total": 0.0})
    fallback: bool = False  # the input is the fallback's (a refused step), not the solver's
    # the KKT certificate of a QP step's answer (an ocpkit.qp.certificate.Certificate; None: no QP solved)
    certificate: object | None = None
    path: str = ""  # what answered: the controller's ``path`` ("C step", "Python step", …) or "fallback (plan)",
    # "fallback (brake)", "fallback (hold)"
    violation: object | None = None  # a "soft" step's worst broken constraint (an ocpkit.safety.Violation: kind, stage,
    # amount, which)
    reason: Reason | None = None  # why the step is not a success, for code (None: a success, or not said)
    # The first input's feedback gain K = ∂u₀/∂x₀ (nu, nx), for u = u₀ + K (x − x₀) between steps: LinearMPC's and
    # RealTimeIteration's with gains=True, exact, the derivative of the solved QP's answer at its active set with the
    # model's linearization held fixed (ocpkit.qp.sensitivity; a row is zero where u₀ is at an input bound). None:
    # not asked for, a fallback, a task's terms or obstacles in the QP, and every other controller (NonlinearMPC, the
    # sampling planners, ExportedMPC and LinearMPC's C step: none is computed, no estimate stands in).
    gains: np.ndarray | None = None

    @property
    def ok(self) -> bool:
        """A success: the optimizer's answer certified, and its plan keeps the task's clearances and state bounds."""
        return self.status == SUCCESS

    @property
    def applied(self) -> bool:
        """Whether ``u`` is the solver's own answer (a success or "soft"), not a fallback."""
        return not self.fallback

    def to_dict(self) -> dict:
        """JSON-ready summary (first input, knots, status, reason, iterations, times)."""
        return {
            "u": self.u.tolist(),
            "knots": self.knots.tolist(),
            "status": self.status,
            "raw_status": self.raw_status,
            "reason": self.reason,
            "iterations": int(self.iterations),
            "fallback": self.fallback,
            "path": self.path,
            "times": {k: float(v) for k, v in self.times.items()},
        }
