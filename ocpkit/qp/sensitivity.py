"""The first stage's feedback gain K = ∂u₀/∂x₀ of a solved knot QP (``Solution.gains``): the derivative of the QP's
answer with respect to the measured state at its active set, the affine model it was built from held fixed.

The QP  min ½ zᵀPz + qᵀz  s.t.  A z = b,  l ≤ C z ≤ u  (:class:`ocpkit.qp.quadratic_program.QP`) depends on x₀ through
its data only, affinely for a fixed model: the sparse form through b's first rows (x_0 = x₀), the condensed form
through the free response v = Φ x₀ + … of its prediction [x_1; …; x_T] = S z + v, which enters q = SᵀQ̄(v − x̄_goal) + …
and the state-bound rows' bounds x_min − v, x_max − v. At the active set of the answer (the rows
:func:`ocpkit.qp.certificate.active` finds held at a bound) the derivative dz = ∂z/∂x₀ solves the KKT system of
the equality rows and the active rows, with the active simple bounds (the knots' input bounds, a slack at 0) fixing
their variables:

    [P_FF  G_Fᵀ] [dz_F]   [−∂q_F]
    [G_F    0  ] [ dμ ] = [ ∂g  ]      (F the free variables, G = [A; C_active], g their right-hand sides),

and K = (φ₀ ⊗ I) dU, u₀ = Σ_j φ_0j U_j. Exact where the active set is strictly complementary (a weakly active row,
its multiplier 0, is left free: the one-sided derivative into the feasible side).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ocpkit.qp.certificate import active
from ocpkit.qp.quadratic_program import QP
from ocpkit.qp.transcription import affine_stages


def derivative(qp: QP, z, w, dq, db, dl, du) -> np.ndarray:
    """dz (n, k) of the answer (z, w) of ``qp`` for its data moving by dq (n, k), db (rows of A, k) and the bounds
    of C's rows by dl, du (rows of C, k), at the answer's active set."""
    upper, lower = active(qp, z, w)
    held = upper | lower
    moved = np.where(upper[:, None], du, dl)
    nb = 0 if qp.box is None else len(qp.box)
    fixed = np.asarray(qp.box[held[:nb]], dtype=int) if nb else np.zeros(0, dtype=int)
    rows = nb + np.flatnonzero(held[nb:])
    free = np.setdiff1d(np.arange(qp.n), fixed)
    dz = np.zeros((qp.n, dq.shape[1]))
    dz[fixed] = moved[:nb][held[:nb]]
    sparse = sp.issparse(qp.P)
    G = sp.vstack([qp.A, qp.C[rows]], format="csr") if sparse else np.vstack([qp.A, qp.C[rows]])
    P = qp.P.tocsr() if sparse else qp.P
    rhs_z = -dq[free] - (P[free][:, fixed] @ dz[fixed] if fixed.size else 0.0)
    rhs_g = np.vstack([db, moved[rows]]) - (G[:, fixed] @ dz[fixed] if fixed.size else 0.0)
    GF = G[:, free]
    rhs = np.vstack([rhs_z, rhs_g])
    if sparse:
        kkt = sp.bmat([[P[free][:, free], GF.T], [GF, None]], format="csc")
        try:
            sol = spla.splu(kkt).solve(rhs)
        except RuntimeError:  # singular: dependent active rows
            sol = la.lstsq(kkt.toarray(), rhs)[0]
    else:
        kkt = np.block([[P[np.ix_(free, free)], GF.T], [GF, np.zeros((GF.shape[0], GF.shape[0]))]])
        try:
            sol = la.solve(kkt, rhs, assume_a="sym")
        except la.LinAlgError:
            sol = la.lstsq(kkt, rhs)[0]
    dz[free] = sol[: free.size]
    return dz


def data_derivative(tr, qp: QP, model):
    """(dq, db, dl, du): the derivatives of ``qp``'s data with respect to x₀, (·, n) each, for the QP ``tr`` (a
    CondensedQP or SparseQP) built last from the affine ``model`` (A_d, B_d, w_d), one or per stage (module
    docstring); None where a task's terms or obstacles enter the QP (their Gauss–Newton rows are not differentiated
    here)."""
    n, nc = tr.n, qp.l.size
    dq, db, dbound = np.zeros((qp.n, n)), np.zeros((qp.b.size, n)), np.zeros((nc, n))
    if tr.form == "sparse":
        db[:n] = -np.eye(n)  # the rows −x_0 = −x₀
        return dq, db, dbound, dbound
    if getattr(tr, "task", None) is not None:
        return None
    Ad, _, _, ltv = affine_stages(*model, n, tr.m, tr.T)
    Phi = np.empty((tr.T, n, n))  # ∂x_{k+1}/∂x₀: A_k ⋯ A_0, or A_d^{k+1} by doubling (A^{j+k} = A^j A^k)
    Phi[0] = Ad[0] if ltv else Ad
    k = 1
    while k < tr.T:
        h = 1 if ltv else min(k, tr.T - k)
        Phi[k : k + h] = (Ad[k] if ltv else Phi[:h]) @ Phi[k - 1]
        k += h
    S = tr._rows()[:, 1:]  # the last build's prediction [v S]
    dq[: tr.nz] = S.T @ np.matmul(tr.Qs, Phi).reshape(-1, n)
    # the state-bound rows are C's last rows (after the knots' and the slacks' simple bounds)
    dbound[nc - tr.x_rows.size :] = -Phi.reshape(-1, n)[tr.x_rows]
    return dq, db, dbound, dbound


def feedback_gain(tr, qp: QP, model, z, w) -> np.ndarray | None:
    """K = ∂u₀/∂x₀ (m, n) of the answer (z, w) of ``qp``, the QP ``tr`` built last from ``model``; None where
    :func:`data_derivative` has none or the derivative is not finite."""
    data = data_derivative(tr, qp, model)
    if data is None:
        return None
    dz = derivative(qp, z, w, *data)
    p, m = tr.p, tr.m
    K = np.tensordot(tr.phi[0], dz[tr._k0 : tr._k0 + p * m].reshape(p, m, -1), axes=1)
    return K if np.isfinite(K).all() else None
