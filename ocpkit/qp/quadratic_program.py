"""The convex QP every transcription produces and every backend solves:  min ½ zᵀPz + qᵀz  s.t.  A z = b,
l ≤ C z ≤ u  (the paper's  zᵀPz + 2qᵀz  form, Section V, scaled by ½), and the check that refuses a Hessian whose
rounding swamps its curvature."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ocpkit.status import Reason, Refusal

# A QP whose rounding in P (n·ε·max P_ii) exceeds this fraction of its exact-arithmetic curvature is refused.
ROUNDING_MARGIN = 0.01


@dataclass
class QP:
    """min ½ zᵀPz + qᵀz  s.t.  A z = b,  l ≤ C z ≤ u  (P, A, C dense arrays or scipy CSC matrices)."""

    P: object
    q: np.ndarray
    A: object
    b: np.ndarray
    C: object
    l: np.ndarray
    u: np.ndarray
    box: np.ndarray | None = None  # z indices of C's first rows when those are unit rows (simple bounds on z)
    # P positive semidefinite by construction (the sparse form's: Q, Q_T ⪰ 0 and R ≻ 0 checked by the OCP);
    # otherwise P depends on the model's numbers and :meth:`not_definite` tells whether it is numerically so.
    convex: bool = False
    # The curvature P has in exact arithmetic at least (the condensed P ⪰ φᵀφ⊗R): 0 where not known.
    curvature: float = 0.0

    @property
    def n(self) -> int:
        return self.q.shape[0]

    def stacked(self):
        """The paper's single-constraint form (P, q, [A; C], lb, ub) with lb = ub on equality rows."""
        stack = sp.vstack if sp.issparse(self.A) else np.vstack
        return self.P, self.q, stack([self.A, self.C]), np.r_[self.b, self.l], np.r_[self.b, self.u]

    def check(self) -> Refusal | None:
        """Why this QP must not reach a backend (non-finite data, l > u, asymmetric P), or None."""
        dense = [_values(M) for M in (self.P, self.A, self.C)] + [self.q, self.b]
        # A finite sum of sums has no inf or NaN entry below it (one would make it inf or NaN): the per-array test
        # only runs when it is not (or overflowed).
        with np.errstate(over="ignore", invalid="ignore"):
            finite = np.isfinite(sum(float(values.sum()) for values in dense))
        if not finite:
            for name, values in zip(("P", "A", "C", "q", "b"), dense):
                if not np.all(np.isfinite(values)):
                    return Refusal(f"non-finite entries in {name}", Reason.QP_DATA)
        if np.isnan(self.l).any() or np.isnan(self.u).any():
            return Refusal("NaN in the bounds l, u", Reason.QP_DATA)
        if (self.l > self.u).any():
            return Refusal(
                f"lower bound above upper bound in {int((self.l > self.u).sum())} constraint rows",
                Reason.BOUNDS_CROSSED,
            )
        P = self.P
        if not sp.issparse(P) and np.array_equal(P, P.T):
            return None
        asym = abs(P - P.T).max() if sp.issparse(P) else np.abs(P - P.T).max(initial=0.0)
        if asym > 1e-9 * max(1.0, abs(P).max() if sp.issparse(P) else np.abs(P).max(initial=0.0)):
            return Refusal("P is not symmetric", Reason.QP_DATA)
        return None

    # C twin: step.in.c ill_conditioned() (the rounding test); parity: tests/test_twins.py
    def not_definite(self, factorize: bool = True) -> Refusal | None:
        """Why P is not numerically positive definite, or None: rounding in P beyond ROUNDING_MARGIN × the
        curvature it has in exact arithmetic (``curvature``), or (``factorize``) a failed Cholesky factorization.

        The condensed P = SᵀQ̄S + φᵀφ⊗R is positive definite in exact arithmetic (R ≻ 0). Where the prediction model
        is so unstable that P's entries reach 1e18 and more (a 7-DoF arm whose model's RK4 step diverges: |eig A_d|
        = 4.9 a step), rounding — n·ε·max P_ii — exceeds the curvature R gives: P is indefinite or its small
        eigenvalues are noise, and the "optimum" is arbitrary (DAQP in C and in Python both reported optimal, with
        knots 1e4 apart, both KKT points to 1e-15). ProxQP reported indefinite ones "solved" at a saddle point."""
        P = self.P.toarray() if sp.issparse(self.P) else self.P
        if self.curvature > 0:
            rounding = self.n * np.finfo(float).eps * float(np.abs(np.diag(P)).max(initial=0.0))
            if not rounding <= ROUNDING_MARGIN * self.curvature:
                return Refusal(
                    f"Hessian ill-conditioned: its rounding {rounding:.3g} (n·ε·max P_ii) exceeds "
                    f"{ROUNDING_MARGIN:g} x the curvature {self.curvature:.3g} the input weight gives: "
                    f"the prediction model diverges over the horizon",
                    Reason.ILL_CONDITIONED,
                )
        if not factorize:
            return None
        try:
            np.linalg.cholesky(P)
        except np.linalg.LinAlgError:
            scale = float(np.abs(np.diag(P)).max(initial=0.0))
            return Refusal(
                f"Hessian not positive definite (Cholesky failed; largest diagonal entry {scale:.3g})",
                Reason.NOT_DEFINITE,
            )
        return None


def _values(M):
    return M.data if sp.issparse(M) else M
