"""Optimality certificates: a QP "success" is accepted only where the KKT conditions hold at the answer.

For the QP  min ½ zᵀPz + qᵀz  s.t.  A z = b,  l ≤ C z ≤ u  (:class:`ocpkit.qp.transcription.QP`) with multipliers y
(equality rows) and w (bound rows; w_i > 0 where the upper bound is active, w_i < 0 where the lower one is), the
four tests, each relative to the data's scale, are

* **stationarity**: ‖Pz + q + Aᵀy + Cᵀw‖∞ / s_d,  s_d = 1 + max(‖Pz‖∞, ‖q‖∞, ‖Aᵀy‖∞, ‖Cᵀw‖∞);
* **primal feasibility**: max(|Az − b|, l − Cz, Cz − u)₊ / s_p,  s_p = 1 + max(‖Az‖∞, ‖Cz‖∞, finite |b|, |l|, |u|);
* **complementarity**: max_i w_i⁺ (u_i − C_i z) and |w_i⁻| (C_i z − l_i), over s_d · s_p;
* **dual sign**: a multiplier pushing against an infinite bound (w_i > 0 with u_i = +∞, w_i < 0 with l_i = −∞),
  over s_d.

Each must be at most :data:`TOL`. Finite-and-within-bounds is necessary, not sufficient: a stale or zero answer
passes it (the C step once reported success with u = 0 after DAQP's set-up had failed) and fails stationarity.
The same tests run in the generated C step (``ocpkit.export``), with the same tolerance. They do not test
convexity: a QP whose Hessian is not positive definite is refused before (DAQP's factorization, :meth:`QP.check`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Relative tolerance of every test. The backends stop at 1e-9 (DAQP exact up to rounding, ProxQP and OSQP
# eps_abs = eps_rel = 1e-9) or 1e-6 (HPIPM's residuals); 1e-6 relative leaves room for the rounding of
# ill-conditioned robot QPs (Hessian condition up to 1e11) and catches any answer that is not a solution.
TOL = 1e-6

TESTS = ("stationarity", "primal feasibility", "complementarity", "dual sign")


@dataclass(frozen=True)
class Certificate:
    """The four relative KKT residuals of one answer (see the module docstring)."""

    stationarity: float
    primal: float
    complementarity: float
    dual_sign: float

    @property
    def residuals(self) -> tuple[float, float, float, float]:
        return self.stationarity, self.primal, self.complementarity, self.dual_sign

    def failed(self, tol: float = TOL) -> str | None:
        """The first test whose residual exceeds ``tol`` (or is NaN), as "name residual > tol"; None if all hold."""
        for name, value in zip(TESTS, self.residuals):
            if not value <= tol:
                return f"{name} residual {value:.3g} > {tol:.0e}"
        return None

    @property
    def holds(self) -> bool:
        return self.failed() is None


def _norm(v) -> float:
    v = np.asarray(v, dtype=float)
    return float(np.abs(v).max(initial=0.0))


def _finite_norm(*arrays) -> float:
    v = np.abs(np.concatenate([np.asarray(a, dtype=float).ravel() for a in arrays]))
    return float(v[np.isfinite(v)].max(initial=0.0))


# C twin: step.in.c certify() and bound_row(); parity: tests/test_twins.py
def certify(qp, z, y, w) -> Certificate:
    """The certificate of (z, y, w) for ``qp`` (a :class:`ocpkit.qp.transcription.QP`): y the equality rows'
    multipliers, w the bound rows' (positive at an active upper bound). Missing multipliers (None) count as zero."""
    z = np.asarray(z, dtype=float)
    y = np.zeros(qp.b.size) if y is None else np.asarray(y, dtype=float)
    w = np.zeros(qp.l.size) if w is None else np.asarray(w, dtype=float)
    Pz = qp.P @ z
    Aty = qp.A.T @ y if qp.b.size else np.zeros_like(z)
    Ctw = qp.C.T @ w if qp.l.size else np.zeros_like(z)
    s_d = 1.0 + max(_norm(Pz), _norm(qp.q), _norm(Aty), _norm(Ctw))
    stationarity = _norm(Pz + qp.q + Aty + Ctw) / s_d
    Az = qp.A @ z if qp.b.size else np.zeros(0)
    Cz = qp.C @ z if qp.l.size else np.zeros(0)
    s_p = 1.0 + max(_norm(Az), _norm(Cz), _finite_norm(qp.b, qp.l, qp.u))
    with np.errstate(invalid="ignore"):
        below, above = qp.l - Cz, Cz - qp.u  # -inf where a bound is infinite
        primal = max(_norm(Az - qp.b), float(np.max(below, initial=0.0)), float(np.max(above, initial=0.0))) / s_p
    up, lo = np.maximum(w, 0.0), np.maximum(-w, 0.0)
    # |slack| on a finite bound: a multiplier on an infinite one is the dual-sign test's
    gap = np.concatenate(
        [
            up[np.isfinite(qp.u)] * np.abs(above[np.isfinite(qp.u)]),
            lo[np.isfinite(qp.l)] * np.abs(below[np.isfinite(qp.l)]),
        ]
    )
    complementarity = float(np.max(gap, initial=0.0)) / (s_d * s_p)
    sign = np.concatenate([up[np.isposinf(qp.u)], lo[np.isneginf(qp.l)]])
    dual_sign = float(sign.max(initial=0.0)) / s_d
    return Certificate(stationarity, primal, complementarity, dual_sign)


# A multiplier at most this, relative to 1 + max |w|, leaves its row out of the active set (weakly active: the answer
# does not move with its bound); DAQP's inactive multipliers are exactly 0, the iterative backends' near their eps.
WEAK = 1e-9


def active(qp, z, w, tol: float = TOL) -> tuple[np.ndarray, np.ndarray]:
    """The bound rows of C held at their upper and at their lower bound by the answer (z, w): a multiplier pushing
    against the bound (w_i > 0 at u_i, w_i < 0 at l_i, beyond WEAK) and the row within ``tol`` of it (relative to s_p
    of the primal-feasibility test). Two boolean arrays over C's rows."""
    z = np.asarray(z, dtype=float)
    w = np.zeros(qp.l.size) if w is None else np.asarray(w, dtype=float)
    Cz = qp.C @ z if qp.l.size else np.zeros(0)
    near = tol * (1.0 + max(_norm(Cz), _finite_norm(qp.l, qp.u)))
    strong = WEAK * (1.0 + _norm(w))
    with np.errstate(invalid="ignore"):
        return (w > strong) & (qp.u - Cz <= near), (w < -strong) & (Cz - qp.l <= near)
