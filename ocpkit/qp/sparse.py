"""The paper's "large matrix" transcription (:mod:`ocpkit.qp.transcription` describes both forms): z = [x_0, …, x_T,
U_0, …, U_{p−1}], the dynamics as equality rows, the sparsity pattern fixed at construction."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve_triangular

from ocpkit.qp.quadratic_program import QP
from ocpkit.model.ocp import OCP
from ocpkit.qp.transcription import Transcription, affine_stages


class SparseQP(Transcription):
    """The paper's large-matrix formulation with a fixed sparsity pattern (Section V-A and V-D)."""

    form = "sparse"

    def __init__(self, ocp: OCP, *, soft: bool = False, slack_weight: float = 1e3):
        super().__init__(ocp, soft=soft, slack_weight=slack_weight)
        n, m, T, p = self.n, self.m, self.T, self.p
        nX = n * (T + 1)
        self._k0 = nX
        self.nz = nX + m * p + self.ns
        # Cost: blkdiag(0 for x_0, Q … Q, Q_T, φᵀφ ⊗ R, 0 for the slacks) — constant, built once.
        self.P = sp.block_diag(
            [
                sp.csc_matrix((n, n)),
                *[sp.csc_matrix(Qk) for Qk in self.Qs],
                sp.csc_matrix(self.R_knots),
                self.slack_quad * sp.identity(self.ns),
            ],
            format="csc",
        )
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
        phi_nz, bd_stage = [], []  # φ_kj of every nonzero of the basis (and its k), in B_d block order
        for k in range(T):
            for j in np.flatnonzero(self.phi[k]):
                rows.append(n * (k + 1) + rb.ravel())
                cols.append(nX + m * j + cb.ravel())
                src.append(np.full(n * m, -2))  # −2: an entry of φ_kj B_d
                phi_nz.append(self.phi[k, j])
                bd_stage.append(k)
        rows, cols, src = map(np.concatenate, (rows, cols, src))
        # Build the CSC pattern once; `_order` maps each CSC slot to the COO entry that fills it.
        pattern = sp.coo_matrix((np.arange(1, rows.size + 1, dtype=float), (rows, cols)), shape=(nX, self.nz)).tocsc()
        self._order = pattern.data.astype(np.int64) - 1
        self.A = pattern
        self._phi_nz = np.array(phi_nz)
        self._bd_stage = np.array(bd_stage, dtype=np.int64)
        self._values = np.where(src == -1, -1.0, 0.0)
        self._ad_slots = np.flatnonzero(src >= 0)
        self._bd_slots = np.flatnonzero(src == -2)
        # Bounds on z: knots (input bounds) and x_1 … x_T (state bounds), as selector rows.
        sel_u = nX + self.u_rows
        sel_x = n + self.x_rows
        if self.soft:  # knot rows; x ± s rows; s ≥ 0
            nzs = self.nz - self.ns
            Cu = sp.csc_matrix((np.ones(sel_u.size), (np.arange(sel_u.size), sel_u)), shape=(sel_u.size, nzs))
            Cx = sp.csc_matrix((np.ones(sel_x.size), (np.arange(sel_x.size), sel_x)), shape=(sel_x.size, nzs))
            Cs, ls, us = self._soft_rows(Cx, self.x_lo, self.x_hi)
            pos = sp.hstack([sp.csc_matrix((self.ns, nzs)), sp.identity(self.ns)])
            self.C = sp.vstack([sp.hstack([Cu, sp.csc_matrix((sel_u.size, self.ns))]), Cs, pos], format="csc")
            self.l = np.r_[self.u_lo, ls, np.zeros(self.ns)]
            self.u = np.r_[self.u_hi, us, np.full(self.ns, np.inf)]
        else:
            sel = np.r_[sel_u, sel_x]
            self.C = sp.csc_matrix((np.ones(sel.size), (np.arange(sel.size), sel)), shape=(sel.size, self.nz))
            self.l = np.r_[self.u_lo, self.x_lo]
            self.u = np.r_[self.u_hi, self.x_hi]

    def build(self, Ad, Bd, wd, x0, x_goal) -> QP:
        """The QP for the affine model (A_d, B_d, w_d) — one for all stages or one per stage (T, ·, ·) —,
        measured state x0 and goal state, held (n,) or per stage (T+1, n) (:meth:`Transcription.goals`)."""
        n, m, T = self.n, self.m, self.T
        Ad, Bd, wd, ltv = affine_stages(Ad, Bd, wd, n, m, T)
        x_goal = self.goals(x_goal)
        v = self._values
        if ltv:
            v[self._ad_slots] = Ad.ravel()
            v[self._bd_slots] = (self._phi_nz[:, None] * Bd.reshape(T, n * m)[self._bd_stage]).ravel()
        else:
            v[self._ad_slots] = np.tile(Ad.ravel(), T)
            v[self._bd_slots] = (self._phi_nz[:, None] * Bd.ravel()[None]).ravel()
        A = self.A.copy()
        A.data = v[self._order]
        q = np.zeros(self.nz)
        stages = "kab,kb->ka" if x_goal.ndim == 2 else "kab,b->ka"
        q[n : n * (T + 1)] = -np.einsum(stages, self.Qs, x_goal[1:] if x_goal.ndim == 2 else x_goal).ravel()
        q[n * (T + 1) : self.nz - self.ns] = self.q_knots(x_goal)
        q[self.nz - self.ns :] = self.slack_weight
        b = np.r_[-np.asarray(x0, dtype=float), -wd.ravel() if ltv else np.tile(-wd, T)]
        return QP(self.P, q, A, b, self.C, self.l, self.u, convex=True)

    def primal(self, qp: QP, knots) -> np.ndarray:
        """A start z for ``qp`` at ``knots`` (p, m): with the states x_0 … x_T they imply through its dynamics rows
        (lower triangular in the states), the slacks zero."""
        z, nX = super().primal(qp, knots), self._k0
        z[:nX] = spsolve_triangular(qp.A[:, :nX].tocsr(), qp.b - qp.A[:, nX:] @ z[nX:], lower=True)
        return z

    def states(self, z: np.ndarray) -> np.ndarray:
        """Predicted states x_0 … x_T (T+1, n) from a solution vector."""
        return z[: self.n * (self.T + 1)].reshape(self.T + 1, self.n)
