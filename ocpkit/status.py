"""What every layer may say about a solve: the statuses, the Solution of one MPC step and the measured costs of a
backend's operations (:class:`OperationCosts`). The QP backends, the controllers, the exported C step's wrapper and
the simulator all speak these; :mod:`ocpkit.controller` builds the Controller interface on them.
"""
from __future__ import annotations

import statistics
from collections import deque
from dataclasses import dataclass, field

import numpy as np

SUCCESS, LIMITED, INFEASIBLE, NAN, EXCEPTION = "success", "limited", "infeasible", "nan", "exception"
# A step the solver answered whose plan, rolled out on the controller's nonlinear model, breaks an obstacle clearance
# or a hard state bound (a softened constraint, a linearization that mispredicted): its input is applied (it is the
# solver's best answer, often the way out of a collision), but it is not a success. Last in STATUSES: the exported
# C step numbers the others 0-4.
SOFT = "soft"
STATUSES = (SUCCESS, LIMITED, INFEASIBLE, NAN, EXCEPTION, SOFT)



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
    status: str
    raw_status: str = ""
    iterations: int = 0
    x_pred: np.ndarray | None = None
    times: dict = field(default_factory=lambda: {"model": 0.0, "build": 0.0, "solve": 0.0, "total": 0.0})
    fallback: bool = False  # the input is the fallback's (a refused step), not the solver's
    certificate: object | None = None  # the KKT certificate of a QP step's answer (an ocpkit.qp.certificate.Certificate;
    # None: no QP solved)
    path: str = ""  # what answered: the controller's ``path`` ("C step", "Python step", …) or "fallback (plan)",
    # "fallback (brake)", "fallback (hold)"
    violation: object | None = None  # a "soft" step's worst broken constraint (an ocpkit.safety.Violation: kind, stage,
    # amount, which)

    @property
    def ok(self) -> bool:
        """A success: the optimizer's answer certified, and its plan keeps the task's clearances and state bounds."""
        return self.status == SUCCESS

    @property
    def applied(self) -> bool:
        """Whether ``u`` is the solver's own answer (a success or "soft"), not a fallback."""
        return not self.fallback

    def to_dict(self) -> dict:
        """JSON-ready summary (first input, knots, status, iterations, times)."""
        return {"u": self.u.tolist(), "knots": self.knots.tolist(), "status": self.status,
                "raw_status": self.raw_status, "iterations": int(self.iterations), "fallback": self.fallback,
                "path": self.path, "times": {k: float(v) for k, v in self.times.items()}}
