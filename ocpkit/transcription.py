"""The paper's two convex transcriptions of the MPC problem, each with any input parameterization.

Both produce a QP  min ½ zᵀ P z + qᵀ z  s.t.  A z = b,  l ≤ C z ≤ u, the paper's  zᵀPz + 2qᵀz  form
(Section V, eq. convex_solver_form) scaled by ½, which has the same minimizer.

* :class:`SparseQP`, the "large matrix" formulation: z = [x_0, …, x_T, U_0, …, U_{p−1}]. The dynamics are
  equality rows  A_d x_k − x_{k+1} + B_d Σ_j φ_kj U_j = −w_d  (the paper's A with its w_d column moved to
  the right-hand side instead of carrying a variable fixed to 1). The sparsity pattern is fixed at
  construction; each step only the numbers are refreshed.
* :class:`CondensedQP`, the "small matrix" formulation: z = [U_0, …, U_{p−1}], the states eliminated as
  [x_1; …; x_T] = S z + v (eq. small_matrix_sz_v with the parameterized S of Section V-E).

Input bounds apply to the knots: for piecewise-linear and zero-order-hold bases every u_k is a convex
combination of knots, so bounded knots bound the whole input trajectory.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ocpkit.ocp import OCP


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

    @property
    def n(self) -> int:
        return self.q.shape[0]

    def stacked(self):
        """The paper's single-constraint form (P, q, [A; C], lb, ub) with lb = ub on equality rows."""
        stack = sp.vstack if sp.issparse(self.A) else np.vstack
        return self.P, self.q, stack([self.A, self.C]), np.r_[self.b, self.l], np.r_[self.b, self.u]

    def check(self) -> str | None:
        """Why this QP must not reach a backend (non-finite data, l > u, asymmetric P), or None."""
        dense = [_values(M) for M in (self.P, self.A, self.C)] + [self.q, self.b]
        for name, values in zip(("P", "A", "C", "q", "b"), dense):
            if not np.all(np.isfinite(values)):
                return f"non-finite entries in {name}"
        if np.isnan(self.l).any() or np.isnan(self.u).any():
            return "NaN in the bounds l, u"
        if (self.l > self.u).any():
            return f"lower bound above upper bound in {int((self.l > self.u).sum())} constraint rows"
        P = self.P
        asym = abs(P - P.T).max() if sp.issparse(P) else np.abs(P - P.T).max(initial=0.0)
        if asym > 1e-9 * max(1.0, abs(P).max() if sp.issparse(P) else np.abs(P).max(initial=0.0)):
            return "P is not symmetric"
        return None


def _values(M):
    return M.data if sp.issparse(M) else M


class _Transcription:
    """Shared data of both forms: the parameterization basis and the bound rows on knots and states."""

    def __init__(self, ocp: OCP):
        if not isinstance(ocp, OCP):
            raise TypeError(f"ocp must be an ocpkit OCP, got {type(ocp).__name__}")
        self.ocp = ocp
        n, m, T, p = ocp.nx, ocp.nu, ocp.horizon, ocp.knots
        self.n, self.m, self.T, self.p = n, m, T, p
        self.phi = ocp.parameterization.basis
        # Cost on the inputs Σ_k (u_k − u_g)ᵀR(u_k − u_g) in knot coordinates: (φᵀφ ⊗ R) and its linear term.
        self.R_knots = np.kron(self.phi.T @ self.phi, ocp.R)
        self._phi_sum = self.phi.sum(axis=0)
        # Knot bounds, only for the input components with a finite bound.
        self.u_rows = np.flatnonzero(np.tile(np.isfinite(ocp.u_min) | np.isfinite(ocp.u_max), p))
        self.u_lo = np.tile(ocp.u_min, p)[self.u_rows]
        self.u_hi = np.tile(ocp.u_max, p)[self.u_rows]
        # State bounds on x_1 … x_T.
        self.x_rows = np.flatnonzero(np.tile(np.isfinite(ocp.x_min) | np.isfinite(ocp.x_max), T))
        self.x_lo = np.tile(ocp.x_min, T)[self.x_rows]
        self.x_hi = np.tile(ocp.x_max, T)[self.x_rows]
        # Per-step state weights Q (k = 1 … T−1) and Q_T (k = T).
        self.Qs = np.concatenate([np.broadcast_to(ocp.Q, (T - 1, n, n)), ocp.Q_terminal[None]])

    def q_knots(self, x_goal) -> np.ndarray:
        """Linear cost term of the knots, −(φᵀ1 ⊗ R u_g) with u_g the OCP's input goal."""
        return -np.kron(self._phi_sum, self.ocp.R @ self.ocp.input_goal(x_goal))

    def knots(self, z: np.ndarray) -> np.ndarray:
        """Knots (p, m) from a solution vector."""
        return z[-self.p * self.m:].reshape(self.p, self.m)


class SparseQP(_Transcription):
    """The paper's large-matrix formulation with a fixed sparsity pattern (Section V-A and V-D)."""

    form = "sparse"

    def __init__(self, ocp: OCP):
        super().__init__(ocp)
        n, m, T, p = self.n, self.m, self.T, self.p
        nX = n * (T + 1)
        self.nz = nX + m * p
        # Cost: blkdiag(0 for x_0, Q … Q, Q_T, φᵀφ ⊗ R) — constant, built once.
        self.P = sp.block_diag([sp.csc_matrix((n, n)), *[sp.csc_matrix(Qk) for Qk in self.Qs],
                                sp.csc_matrix(self.R_knots)], format="csc")
        self.P.eliminate_zeros()
        # Dynamics rows: −x_0 = −x0, then A_d x_k − x_{k+1} + B_d Σ_j φ_kj U_j = −w_d.
        rows, cols, src = [np.arange(n)], [np.arange(n)], [np.full(n, -1)]  # src −1: the constant −1
        r_blk, c_blk = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        for k in range(T):
            r0 = n * (k + 1)
            rows += [r0 + r_blk.ravel(), r0 + np.arange(n)]
            cols += [n * k + c_blk.ravel(), n * (k + 1) + np.arange(n)]
            src += [np.arange(n * n), np.full(n, -1)]  # A_d entries, then −I
        rb, cb = np.meshgrid(np.arange(n), np.arange(m), indexing="ij")
        phi_nz = []  # φ_kj of every nonzero of the basis, in the order its B_d block is inserted
        for k in range(T):
            for j in np.flatnonzero(self.phi[k]):
                rows.append(n * (k + 1) + rb.ravel())
                cols.append(nX + m * j + cb.ravel())
                src.append(np.full(n * m, -2))  # −2: an entry of φ_kj B_d
                phi_nz.append(self.phi[k, j])
        rows, cols, src = map(np.concatenate, (rows, cols, src))
        # Build the CSC pattern once; `_order` maps each CSC slot to the COO entry that fills it.
        pattern = sp.coo_matrix((np.arange(1, rows.size + 1, dtype=float), (rows, cols)),
                                shape=(nX, self.nz)).tocsc()
        self._order = pattern.data.astype(np.int64) - 1
        self.A = pattern
        self._phi_nz = np.array(phi_nz)
        self._values = np.where(src == -1, -1.0, 0.0)
        self._ad_slots = np.flatnonzero(src >= 0)
        self._bd_slots = np.flatnonzero(src == -2)
        # Bounds on z: knots (input bounds) and x_1 … x_T (state bounds), as selector rows.
        sel_u = nX + self.u_rows
        sel_x = n + self.x_rows
        sel = np.r_[sel_u, sel_x]
        self.C = sp.csc_matrix((np.ones(sel.size), (np.arange(sel.size), sel)), shape=(sel.size, self.nz))
        self.l = np.r_[self.u_lo, self.x_lo]
        self.u = np.r_[self.u_hi, self.x_hi]

    def build(self, Ad, Bd, wd, x0, x_goal) -> QP:
        """The QP for the affine model (A_d, B_d, w_d), measured state x0 and goal state."""
        n, T = self.n, self.T
        v = self._values
        v[self._ad_slots] = np.tile(np.asarray(Ad, dtype=float).ravel(), T)
        v[self._bd_slots] = (self._phi_nz[:, None] * np.asarray(Bd, dtype=float).ravel()[None]).ravel()
        A = self.A.copy()
        A.data = v[self._order]
        q = np.zeros(self.nz)
        q[n:n * (T + 1)] = -np.einsum("kab,b->ka", self.Qs, x_goal).ravel()
        q[n * (T + 1):] = self.q_knots(x_goal)
        b = np.r_[-np.asarray(x0, dtype=float), np.tile(-np.asarray(wd, dtype=float).ravel(), T)]
        return QP(self.P, q, A, b, self.C, self.l, self.u)

    def states(self, z: np.ndarray) -> np.ndarray:
        """Predicted states x_0 … x_T (T+1, n) from a solution vector."""
        return z[: self.n * (self.T + 1)].reshape(self.T + 1, self.n)


class CondensedQP(_Transcription):
    """The paper's small-matrix formulation: states eliminated, [x_1; …; x_T] = S z + v (Section V-B and V-E)."""

    form = "condensed"

    def __init__(self, ocp: OCP):
        super().__init__(ocp)
        self.nz = self.m * self.p
        self.A = np.zeros((0, self.nz))
        self.b = np.zeros(0)
        self.diagonal_Q = all(np.count_nonzero(Qk - np.diag(np.diag(Qk))) == 0 for Qk in self.Qs)

    def prediction(self, Ad, Bd, wd, x0):
        """S (T·n, p·m) and v (T·n,) with [x_1; …; x_T] = S z + v.

        Row block k is the previous one pre-multiplied by A_d plus B_d in the basis proportions φ_k
        (the paper's recipe below its T=5, p=3 example).
        """
        n, m, T, p = self.n, self.m, self.T, self.p
        Ad = np.asarray(Ad, dtype=float)
        Bd = np.asarray(Bd, dtype=float)
        wd = np.asarray(wd, dtype=float).ravel()
        S = np.empty((T, n, p, m))
        v = np.empty((T, n))
        # φ_k ⊗ B_d for all k at once: (T, n, p, m).
        phiB = np.einsum("kj,am->kajm", self.phi, Bd)
        S[0] = phiB[0]
        v[0] = Ad @ x0 + wd
        for k in range(1, T):
            S[k] = (Ad @ S[k - 1].reshape(n, p * m)).reshape(n, p, m) + phiB[k]
            v[k] = Ad @ v[k - 1] + wd
        return S.reshape(T * n, p * m), v.ravel()

    def build(self, Ad, Bd, wd, x0, x_goal) -> QP:
        """P = SᵀQ̄S + φᵀφ⊗R and q = SᵀQ̄(v − x̄_goal) − (φᵀ1 ⊗ R u_goal); knot and state bound rows."""
        S, v = self.prediction(Ad, Bd, wd, np.asarray(x0, dtype=float))
        T, n = self.T, self.n
        S3 = S.reshape(T, n, -1)
        if self.diagonal_Q:
            QS = np.diagonal(self.Qs, axis1=1, axis2=2)[:, :, None] * S3
        else:
            QS = np.einsum("kab,kbc->kac", self.Qs, S3)
        QS = QS.reshape(T * n, -1)
        P = S.T @ QS + self.R_knots
        P = 0.5 * (P + P.T)
        err = v - np.tile(np.asarray(x_goal, dtype=float), T)
        q = QS.T @ err + self.q_knots(x_goal)
        C = np.vstack([np.eye(self.nz)[self.u_rows], S[self.x_rows]])
        l = np.r_[self.u_lo, self.x_lo - v[self.x_rows]]
        u = np.r_[self.u_hi, self.x_hi - v[self.x_rows]]
        self._last_v, self._last_S = v, S
        return QP(P, q, self.A, self.b, C, l, u)

    def states(self, z: np.ndarray, x0) -> np.ndarray:
        """Predicted states x_0 … x_T (T+1, n) of the last built QP."""
        return np.vstack([np.asarray(x0, dtype=float), (self._last_S @ z + self._last_v).reshape(self.T, self.n)])


TRANSCRIPTIONS = {"sparse": SparseQP, "condensed": CondensedQP}
