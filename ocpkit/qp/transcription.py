"""The paper's two convex transcriptions of the MPC problem, each with any input parameterization.

Both produce a QP  min ½ zᵀ P z + qᵀ z  s.t.  A z = b,  l ≤ C z ≤ u, the paper's  zᵀPz + 2qᵀz  form
(Section V, eq. convex_solver_form) scaled by ½, which has the same minimizer.

* :class:`~ocpkit.qp.sparse.SparseQP` (in its own module), the "large matrix" formulation: z = [x_0, …, x_T,
  U_0, …, U_{p−1}]. The dynamics are equality rows  A_d x_k − x_{k+1} + B_d Σ_j φ_kj U_j = −w_d  (the paper's A
  with its w_d column moved to the right-hand side instead of carrying a variable fixed to 1). The sparsity
  pattern is fixed at construction; each step only the numbers are refreshed.
* :class:`CondensedQP`, the "small matrix" formulation: z = [U_0, …, U_{p−1}], the states eliminated as
  [x_1; …; x_T] = S z + v (eq. small_matrix_sz_v with the parameterized S of Section V-E).

Both build from an affine model, one (A_d, B_d, w_d) for the whole horizon (the paper's linearization at the
current state, LTI) or one per stage, (T, n, n), (T, n, m), (T, n) arrays: the model linearized along a
trajectory (LTV), as real-time iteration and ``LinearMPC(linearization="trajectory")`` need.

Input bounds apply to the knots: for piecewise-linear, zero-order-hold and B-spline bases (and a user basis
whose rows are convex combinations, ``Parameterization.convex``; the OCP refuses input bounds with any other)
every u_k is a convex combination of knots, so bounded knots bound the whole input trajectory.

State bounds are hard constraints by default; with ``soft=True`` they become an exact L1 penalty: one slack
s ≥ 0 per bounded state component and step, appended after the other variables, rows x + s ≥ x_min and
x − s ≤ x_max, and cost ``slack_weight``·Σ (s + ½ s²). With a weight above the hard problem's bound
multipliers the soft problem has the hard one's solution whenever that exists (the quadratic part has zero
slope at s = 0, so exactness is kept; it makes the QP strictly convex in s, which the sparse solvers needed:
pure L1 slacks left sparse OSQP at its iteration limit and ProxQP reporting a feasible problem infeasible).
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import scipy.sparse as sp

from ocpkit._checks import positive
from ocpkit.numeric import BufferedFunction
from ocpkit.model.ocp import OCP
from ocpkit.qp.quadratic_program import QP
from ocpkit.qp.task_rows import TaskRows


class Transcription:
    """Shared data of both forms (this module's CondensedQP, :class:`ocpkit.qp.sparse.SparseQP`): the
    parameterization basis and the bound rows on knots and states."""

    def __init__(self, ocp: OCP, *, soft: bool = False, slack_weight: float = 1e3):
        if not isinstance(ocp, OCP):
            raise TypeError(f"ocp must be an ocpkit OCP, got {type(ocp).__name__}")
        self.ocp = ocp
        self.slack_weight = positive(slack_weight, "slack_weight")
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
        lo, hi = (np.broadcast_to(np.asarray(b, dtype=float), (p, m)) for b in (ocp.u_min, ocp.u_max))
        self._snap = (lo, hi, *(np.where(np.isfinite(b), 1e-13 * np.maximum(1.0, np.abs(b)), -1.0) for b in (lo, hi)))
        # State bounds on x_1 … x_T.
        self.x_rows = np.flatnonzero(np.tile(np.isfinite(ocp.x_min) | np.isfinite(ocp.x_max), T))
        self.x_lo = np.tile(ocp.x_min, T)[self.x_rows]
        self.x_hi = np.tile(ocp.x_max, T)[self.x_rows]
        self.soft = bool(soft) and self.x_rows.size > 0
        self.ns = 2 * self.x_rows.size if self.soft else 0  # slacks s⁺, s⁻: the last ns entries of z
        self.slack_quad = self.slack_weight  # the ½·w·s² of the cost (see the module docstring)
        self._k0 = 0  # index of the first knot in z (the sparse form overrides)
        # Per-step state weights Q (k = 1 … T−1) and Q_T (k = T).
        self.Qs = np.concatenate([np.broadcast_to(ocp.Q, (T - 1, n, n)), ocp.Q_terminal[None]])
        self._input_goals = None  # the input goal mapped over the stages (per-stage goals), once made

    def q_knots(self, x_goal) -> np.ndarray:
        """Linear cost term of the knots, −(φᵀ1 ⊗ R u_g) with u_g the OCP's input goal; for per-stage goals
        (T+1, n) (:meth:`goals`) −Σ_k φ_kᵀ ⊗ R u_g,k, u_g,k the input goal of x_goal,k (k = 0 … T−1)."""
        ocp = self.ocp
        if x_goal.ndim == 1:
            return np.multiply.outer(-self._phi_sum, ocp.R @ ocp.input_goal(x_goal)).ravel()
        if self._input_goals is None:  # u_g(x_goal) = −(the "input" residual at u = 0), mapped over the stages
            xg = ca.MX.sym("x_goal", self.n)
            fn = ca.Function("input_goal", [xg], [-ocp.input_error(ca.MX.zeros(self.m), xg)])
            self._input_goals = BufferedFunction(fn.map(self.T))
        (Ug,) = self._input_goals(x_goal[: self.T].T)
        return -(self.phi.T @ (ocp.R @ Ug).T).ravel()

    def goals(self, x_goal) -> np.ndarray:
        """The goal state as a float array: held (n,), or per stage k = 0 … T, (T+1, n), a goal window's x_goal
        columns (:meth:`ocpkit.model.ocp.OCP.goal_window`): stage k's state term pulls x_k towards row k (k ≥ 1),
        its input term u_k towards row k's input goal (k ≤ T−1)."""
        x_goal = np.asarray(x_goal, dtype=float)
        if x_goal.ndim == 2 and x_goal.shape != (self.T + 1, self.n):
            raise ValueError(f"per-stage goals must be (T+1, n) = {(self.T + 1, self.n)}, got {x_goal.shape}")
        return x_goal

    def knots(self, z: np.ndarray) -> np.ndarray:
        """Knots (p, m) from a solution vector, put on the input bounds where they are within rounding (1e-13
        relative) of them or beyond: a solver's active bound comes back a few ulps either side of it."""
        lo, hi, tol_lo, tol_hi = self._snap
        U = np.clip(z[self._k0 : self._k0 + self.p * self.m].reshape(self.p, self.m), lo, hi)
        np.copyto(U, lo, where=U - lo <= tol_lo)
        np.copyto(U, hi, where=hi - U <= tol_hi)
        return U

    def primal(self, qp: QP, knots) -> np.ndarray:
        """A start z for ``qp`` at ``knots`` (p, m) (:meth:`knots`' inverse), its other entries zero."""
        return np.r_[np.zeros(self._k0), np.ravel(knots), np.zeros(qp.n - self._k0 - self.p * self.m)]

    def slacks(self, z: np.ndarray) -> np.ndarray:
        """State-bound slacks (ns,) from a solution vector (empty with hard bounds)."""
        return z[z.size - self.ns :]

    def _soft_rows(self, X, lo, hi):
        """Rows [X, −I, I] with bounds [lo, hi]: X the state-bound rows over the other variables, x − s⁺ + s⁻."""
        nr = self.ns // 2
        if sp.issparse(X):
            C = sp.hstack([X, -sp.identity(nr), sp.identity(nr)])
        else:
            C = np.hstack([X, -np.eye(nr), np.eye(nr)])
        return C, lo, hi


class CondensedQP(Transcription):
    """The paper's small-matrix formulation: states eliminated, [x_1; …; x_T] = S z + v (Section V-B and V-E).

    The build exploits the structure of S and never forms it. The horizon splits into *pieces*, runs of inputs
    u_a … u_{a+L−1} along which φ_i = φ_a + (i − a) Δ is affine in i (one piece per knot interval for
    piecewise-linear and zero-order-hold bases; two steps for a cubic B-spline or a dense user basis). In
    deviation coordinates x̃ = x − x_goal (w̃_d = w_d + (A_d − I) x_goal), inside a piece with y = [x̃_a; α; β; 1],
    α = (φ_a ⊗ I) z and β = (Δ ⊗ I) z,

        x̃_{a+s} = Λ_s y,   Λ_s = [A_d^s  E_s  F_s  e_s],
        E_s = Σ_{t<s} A_d^t B_d,  F_s = Σ_{t<s} (s−1−t) A_d^t B_d,  e_s = Σ_{t<s} A_d^t w̃_d.

    Λ_1 … Λ_L are the same for every piece and double: Λ_{s+k} = A_d^s Λ_k + [0, E_s, F_s + k E_s, e_s] (one
    GEMM per doubling). A piece's state cost is yᵀ Γ_L y with Γ_L = Σ_{s≤L} Λ_sᵀ Q Λ_s (one GEMM). The cost to go
    from piece i, x̃_aᵀ H x̃_a + 2 x̃_aᵀ G ẑ + ẑᵀ Z ẑ in ẑ = [1, z], then runs backwards over the pieces
    (H starts as Q_T − Q, the terminal weight's difference): with Ĝ = Γ_L + Λ_Lᵀ H Λ_L and y's rows α, β, 1 a
    constant E ẑ,

        H ← Ĝ_xx,   G ← Ĝ_xu E + Λ_xᵀ G,   Z ← Z + Eᵀ Ĝ_uu E + Eᵀ Λ_uᵀ G + Gᵀ Λ_u E,

    and x̃_0 = x_0 − x_goal closes it: P = Z_zz (+ the input cost), q = Z_z1 + G_zᵀ x̃_0. G's columns only reach
    the knots of the pieces after it, so ẑ is kept internally as [1, z reversed] and G and Z grow from the
    top-left corner. Rows of S (state bounds, :meth:`prediction`) run forward piece by piece when asked.
    """

    form = "condensed"

    def __init__(
        self,
        ocp: OCP,
        *,
        soft: bool = False,
        slack_weight: float = 1e3,
        obstacles: bool = True,
        task: bool = True,
        soft_obstacles: bool | None = None,
    ):
        super().__init__(ocp, soft=soft, slack_weight=slack_weight)
        n, m, p = self.n, self.m, self.p
        # task=False: the joint-space QP alone (the C step generates the task's terms itself); obstacles=False: the
        # task's terms without its obstacle rows (the sampling planners' preconditioner); soft_obstacles: the
        # obstacle rows with their slacks (default: as the state bounds, ``soft``)
        soft_obstacles = soft if soft_obstacles is None else soft_obstacles
        self.task = (
            None if ocp.task_functions is None or not task else TaskRows(ocp, obstacles, soft=bool(soft_obstacles))
        )
        self.nz = m * p  # the knots; the slacks (if any) follow them in z
        self.A = np.zeros((0, self.nz + self.ns))
        self.b = np.zeros(0)
        Q, QT = self.Qs[0], self.Qs[-1]
        self.diagonal_Q = all(np.count_nonzero(M - np.diag(np.diag(M))) == 0 for M in (Q, QT))
        # Q^½ with (Q^½)ᵀQ^½ = Q (Q ⪰ 0): a diagonal or a matrix; the terminal step adds Q_T − Q.
        if self.diagonal_Q:
            self._qh, self._dQT = np.sqrt(np.diag(Q)), np.diag(QT - Q)
        else:
            w, V = np.linalg.eigh(Q)
            self._qh, self._dQT = np.sqrt(np.clip(w, 0.0, None))[:, None] * V.T, QT - Q
        self.R_knots = 0.5 * (self.R_knots + self.R_knots.T)  # exactly symmetric: P is returned as built
        # P ⪰ φᵀφ⊗R (and the slacks' weight): its curvature in exact arithmetic (QP.not_definite)
        self.curvature = float(np.linalg.eigvalsh(self.R_knots).min())
        if self.ns:
            self.curvature = min(self.curvature, self.slack_quad)
        self._pieces = _pieces(self.phi, n, m)
        self._lengths = sorted({piece[1] for piece in self._pieces})
        # Simple bounds on z (ProxQP's box): the knots' input bounds, then s ≥ 0.
        self._box = np.r_[self.u_rows, self.nz + np.arange(self.ns)]
        self._box_C = np.eye(self.nz + self.ns)[self._box]
        # For per-stage models: the z columns in use up to x_{k+1} and the basis' nonzeros (k, j, φ_kj).
        used = np.abs(self.phi) > 0
        last = np.maximum.accumulate(np.where(used.any(axis=1), p - 1 - np.argmax(used[:, ::-1], axis=1), -1))
        self._stage_cols = m * (last + 1)
        ks, js = np.nonzero(used)
        self._stage_nz = (ks, js, self.phi[ks, js])
        self._SV = None  # [v S] by stage (T, n, 1 + p·m) of the last per-stage (LTV) prediction
        self._plan()

    def _plan(self):
        """Buffers of the one-model build and each piece's rows α, β, 1 of y as E (2m+1, width) over the internal
        ẑ = [1, z_{nz−1}, …, z_0], cut to the width its cost-to-go term G reaches."""
        n, m, nz = self.n, self.m, self.nz
        self._K = K = n + 2 * m + 1
        L = self._lengths[-1]
        # M^s = [[Λ_s], [0, T_s]] (K, K) side by side for s = 1 … L: the rows of Λ_s are filled at each build, the
        # constant rows T_s (α + sβ, β, 1 from α, β, 1) here, so one GEMM Λ_k [M^1 … M^h] doubles Λ.
        self._M = np.zeros((K, L, K))
        for s in range(1, L + 1):
            T = self._M[n:, s - 1, n:]
            T[:] = np.eye(2 * m + 1)
            T[:m, m : 2 * m] = s * np.eye(m)
        # With Q diagonal and positive the build runs in x̂ = Q^½ x̃ (Â = Q^½ A Q^-½, …): Γ_L is then the Gram
        # matrix of the Λ̂_s themselves, with no scaled copy; otherwise W = Q^½ Λ_s.
        self._hat = self.diagonal_Q and bool(np.all(self._qh > 0))
        self._W = None if self._hat else np.empty((n, L * K))
        self._G = np.zeros((n, nz + 1))  # the cost-to-go term G of the backward pass
        self._H_end = (
            np.diag(self._dQT / self._qh**2 if self._hat else self._dQT) if self.diagonal_Q else np.array(self._dQT)
        )
        E, width = [], 1
        for _, _, c, rhs in reversed(self._pieces):
            Ei = np.zeros((2 * m + 1, nz + 1))
            Ei[:, 0] = rhs[n:, 0]
            Ei[:, nz + 1 - c :] = rhs[n:, c:0:-1]  # z_t is internal column nz − t
            cols = np.flatnonzero(Ei.any(axis=0))
            width = max(width, int(cols[-1]) + 1 if cols.size else 1)
            E.append(np.ascontiguousarray(Ei[:, :width]))
        self._E = E[::-1]
        self._g = np.zeros(n)
        self._x0t = np.zeros(n)
        self._SVc = None  # [v S] rows of the last one-model build, computed when asked

    def build_flops(self) -> int:
        """Floating-point operations of one one-model :meth:`build` as implemented (a multiply-add counts 2): the
        doubling of Λ, the Gram matrix Γ_L and the backward pass over the pieces."""
        n, m, K, L = self.n, self.m, self._K, self._lengths[-1]
        flops = 2 * n * K * K * (L - 1) + 2 * n * L * K * K
        if not self._hat:
            flops += (1 if self.diagonal_Q else 2 * n) * n * L * K  # W = Q^½ Λ
        wp = 0
        for E in reversed(self._E):
            w = E.shape[1]
            flops += 2 * n * n * K + 2 * n * K * K + 2 * K * (2 * m + 1) * w + 2 * w * (2 * m + 1) * w
            flops += 2 * K * n * w if wp else 0
            wp = w
        return int(flops)

    def prediction(self, Ad, Bd, wd, x0):
        """S (T·n, p·m) and v (T·n,) with [x_1; …; x_T] = S z + v (the paper's recipe below its T=5, p=3
        example, evaluated piece by piece as in the class docstring; stage by stage for per-stage models)."""
        Ad, Bd, wd, ltv = affine_stages(Ad, Bd, wd, self.n, self.m, self.T)
        if ltv:
            self._predict_ltv(Ad, Bd, wd, x0)
        else:
            self._SV = None
            self._predict(Ad, Bd, wd, x0, np.zeros(self.n))
        SV = self._rows()
        return SV[:, 1:], SV[:, 0]

    def _predict_ltv(self, Ad, Bd, wd, x0):
        """[v S] by stage for per-stage models: [v S]_{k+1} = A_k [v S]_k + [w_k, B_k (φ_k ⊗ I)].

        Row block k only has nonzeros in the columns of the knots that inputs u_0 … u_k shape (S is
        block-lower-triangular in knot columns), so each stage multiplies A_k by that prefix only."""
        n, m, T, p = self.n, self.m, self.T, self.p
        # SV starts as each stage's own term [w_k, B_k (φ_k ⊗ I)], written for all stages in one scatter.
        SV = np.zeros((T, n, 1 + self.nz))
        SV[:, :, 0] = wd
        ks, js, fs = self._stage_nz
        SV[:, :, 1:].reshape(T, n, p, m)[ks, :, js, :] = fs[:, None, None] * Bd[ks]
        c = 0
        SV[0, :, 0] += Ad[0] @ x0
        for k in range(1, T):  # then the recursion adds A_k [v S]_k on the columns in use
            c = self._stage_cols[k - 1]
            SV[k, :, : c + 1] += Ad[k] @ SV[k - 1, :, : c + 1]
        self._SV = SV

    def _predict(self, Ad, Bd, wd, x0, x_goal):
        """Λ_1 … Λ_L of the affine model in deviation coordinates x − x_goal, by doubling (class docstring)."""
        n, m, K, M = self.n, self.m, self._K, self._M
        L = M.shape[1]
        x0t = np.asarray(x0, dtype=float) - x_goal
        wt = wd + Ad @ x_goal - x_goal
        if self._hat:
            qh = self._qh
            np.multiply(Ad, np.outer(qh, 1.0 / qh), out=M[:n, 0, :n])
            np.multiply(Bd, qh[:, None], out=M[:n, 0, n : n + m])
            M[:n, 0, -1] = qh * wt
            x0t = qh * x0t
        else:
            M[:n, 0, :n] = Ad
            M[:n, 0, n : n + m] = Bd
            M[:n, 0, -1] = wt
        k = 1
        while k < L:  # Λ_{k+s} = Λ_k M^s, s = 1 … h: one GEMM
            h = min(k, L - k)
            np.matmul(M[:n, k - 1], M[:, :h].reshape(K, h * K), out=M[:n, k : k + h].reshape(n, h * K))
            k += h
        self._g, self._x0t, self._SVc = x_goal, x0t, None

    def _rows(self) -> np.ndarray:
        """[v S] (T·n, 1 + p·m) of the last prediction, one GEMM per piece."""
        if self._SV is not None:
            return self._SV.reshape(self.T * self.n, -1)
        if self._SVc is None:
            n, K, M = self.n, self._K, self._M
            L = M.shape[1]
            Lam = M[:n].reshape(n * L, K)  # Λ_1 … Λ_L, rows by (state, s)
            SV = np.zeros((self.T, n, 1 + self.nz))
            prev = SV[0].copy()
            prev[:, 0] = self._x0t
            for a, Lp, c, rhs in self._pieces:
                rhs[:n] = prev[:, : c + 1]
                SV[a : a + Lp, :, : c + 1] = (Lam @ rhs).reshape(n, L, c + 1)[:, :Lp].transpose(1, 0, 2)
                prev = SV[a + Lp - 1]
            if self._hat:
                SV /= self._qh[:, None]
            SV[:, :, 0] += self._g
            self._SVc = SV.reshape(self.T * n, -1)
        return self._SVc

    def build(self, Ad, Bd, wd, x0, x_goal, *, targets=None, knots=None, obstacles=None) -> QP:
        """P = SᵀQ̄S + φᵀφ⊗R and q = SᵀQ̄(v − x̄_goal) − (φᵀ1 ⊗ R u_goal); knot bounds (``box``), state bound rows.

        (A_d, B_d, w_d) is one affine model for all stages (the piece-wise build of the class docstring) or one
        per stage, (T, n, n), (T, n, m), (T, n) (LTV: [v S] stage by stage, then one Gram product). ``x_goal`` is
        held (n,) or per stage (T+1, n) (:meth:`goals`).
        With a task (``ocp.task``) its terms and obstacles are linearized about the plan ``knots`` (p, m) and
        its predicted states, towards ``targets`` (the goal's entries after x_goal; held, or per stage (T+1, ·)),
        the obstacles where the task declares them or at each stage, ``obstacles`` (T+1, N, 4): see
        :class:`~ocpkit.qp.task_rows.TaskRows`."""
        Ad, Bd, wd, ltv = affine_stages(Ad, Bd, wd, self.n, self.m, self.T)
        x_goal = self.goals(x_goal)
        if ltv:
            self._predict_ltv(Ad, Bd, wd, x0)
            P, q = self._cost_ltv(x_goal)
        else:
            self._SV = None
            self._predict(Ad, Bd, wd, x0, x_goal[0] if x_goal.ndim == 2 else x_goal)
            P, q = self._cost_lti(x_goal)
        if self.task is None:
            return self._qp(P, q)
        if knots is None or targets is None:
            raise ValueError("this OCP has a task: build(...) needs targets= and knots= (the plan to linearize about)")
        SV = self._rows().reshape(self.T, self.n, -1)
        x0, targets, knots = (np.asarray(a, dtype=float) for a in (x0, targets, knots))
        rows = self.task.add(P, q, SV, x0, targets, knots, obstacles)
        return self.task.constrain(self._qp(P, q), rows)

    # C twin: step.in.c condense_ltv() (with _predict_ltv); parity: tests/test_twins.py
    def _cost_ltv(self, x_goal):
        """P, q from the stage rows [v S]: the Gram matrix of Q^½ [v − x_goal, S], Q_T's difference at x_T."""
        E = self._SV.copy()
        E[:, :, 0] -= x_goal[1:] if x_goal.ndim == 2 else x_goal
        W = self._qh[None, :, None] * E if self.diagonal_Q else np.matmul(self._qh, E)
        W = W.reshape(self.T * self.n, -1)
        Pq = W.T @ W
        end = E[-1]
        Pq += end.T @ (self._dQT[:, None] * end if self.diagonal_Q else self._dQT @ end)
        P = Pq[1:, 1:] + self.R_knots
        P += P.T
        P *= 0.5
        return P, Pq[1:, 0] + self.q_knots(x_goal)

    # C twin: step.in.c condense() (forward over the pieces, Γ_L by grams' doubling); parity: tests/test_twins.py
    def _cost_lti(self, x_goal):
        """P, q of the last (one-model) prediction: Γ_L, then the backward pass over the pieces (class docstring).
        Per-stage goals x_goal,k: the prediction's deviation coordinates are about x_goal,0 (``_predict``), and
        the state terms' pull towards x_goal,k − x_goal,0 adds −Σ_k S_kᵀ Q_k (x_goal,k − x_goal,0) to q."""
        n, nz, K, M, W = self.n, self.nz, self._K, self._M, self._W
        L = M.shape[1]
        if self._hat:
            W = M[:n].reshape(n, L * K)
        elif self.diagonal_Q:
            np.multiply(M[:n].reshape(n, L * K), self._qh[:, None], out=W)
        else:
            np.matmul(self._qh, M[:n].reshape(n, L * K), out=W)
        Gam, s0 = {}, 0
        for Lp in self._lengths:  # Γ_L for each piece length, accumulated over s (rows of W by (state, s))
            Ws = W.reshape(n * L, K) if Lp - s0 == L else W.reshape(n, L, K)[:, s0:Lp].reshape(-1, K)
            G = Ws.T @ Ws
            if s0:
                G += Gam[s0]
            Gam[Lp], s0 = G, Lp
        G, Zh = self._G, np.zeros((nz + 1, nz + 1))  # Z = Zh + Zhᵀ
        G.fill(0.0)
        H, wp = self._H_end, 0
        for i in range(len(self._pieces) - 1, -1, -1):
            Lp, E = self._pieces[i][1], self._E[i]
            w, LamL = E.shape[1], M[:n, Lp - 1]
            Gh = LamL.T @ (H @ LamL)
            Gh += Gam[Lp]  # Ĝ = Γ_L + Λ_Lᵀ H Λ_L
            Y = Gh[:, n:] @ E
            Y[n:] *= 0.5  # Ĝ_uu enters Zh halved
            if wp:
                Y += LamL.T @ G[:, :w]  # rows :n the new G, rows n: ½ Ĝ_uu E + Λ_uᵀ G
            Zh[:w, :w] += E.T @ Y[n:]
            H = Gh[:n, :n]
            G[:, :w] = Y[:n]
            wp = w
        Zh[0, :wp] += self._x0t @ G[:, :wp]
        S = Zh[1:, 1:]
        P = (S + S.T)[::-1, ::-1] + self.R_knots
        q = (Zh[1:, 0] + Zh[0, 1:])[::-1] + self.q_knots(x_goal)
        if x_goal.ndim == 2:
            pull = np.einsum("kab,kb->ka", self.Qs, x_goal[1:] - self._g)
            q -= self._rows()[:, 1:].T @ pull.ravel()
        return P, q

    def _qp(self, P, q) -> QP:
        """The QP with cost (P, q): knot bounds as ProxQP's box, the state bound rows of the last prediction."""
        if self.soft:
            ns = self.ns
            P = np.pad(P, ((0, ns), (0, ns)))
            P[self.nz :, self.nz :] += self.slack_quad * np.eye(ns)
            q = np.concatenate([q, np.full(ns, self.slack_weight)])
            SV = self._rows()[self.x_rows]
            vr = SV[:, 0]
            Cs, ls, us = self._soft_rows(SV[:, 1:], self.x_lo - vr, self.x_hi - vr)
            C = np.vstack([self._box_C, Cs])
            l = np.concatenate([self.u_lo, np.zeros(ns), ls])
            u = np.concatenate([self.u_hi, np.full(ns, np.inf), us])
            return QP(P, q, self.A, self.b, C, l, u, box=self._box, curvature=self.curvature)
        if self.x_rows.size:
            SV = self._rows()[self.x_rows]
            vr = SV[:, 0]
            C = np.vstack([self._box_C, SV[:, 1:]])
            l = np.concatenate([self.u_lo, self.x_lo - vr])
            u = np.concatenate([self.u_hi, self.x_hi - vr])
        else:
            C, l, u = self._box_C, self.u_lo.copy(), self.u_hi.copy()
        return QP(P, q, self.A, self.b, C, l, u, box=self.u_rows, curvature=self.curvature)

    def states(self, z: np.ndarray, x0) -> np.ndarray:
        """Predicted states x_0 … x_T (T+1, n) of the last built QP."""
        n, X = self.n, np.empty((self.T + 1, self.n))
        X[0] = x0
        z1 = np.concatenate([[1.0], z[: self.nz]])
        if self._SV is not None:
            X[1:] = self._SV @ z1
            return X
        K, M, pieces = self._K, self._M, self._pieces
        L = M.shape[1]
        Y = np.empty((K, len(pieces)))  # each piece's y = [x̃_a; α; β; 1], x̃_a from Λ_L of the piece before
        xa = X[0] - self._g
        if self._hat:
            xa = xa * self._qh
        for i, (_, Lp, c, rhs) in enumerate(pieces):
            Y[:n, i] = xa
            Y[n:, i] = rhs[n:] @ z1[: c + 1]
            xa = M[:n, Lp - 1] @ Y[:, i]
        Xs = (M[:n].reshape(n * L, K) @ Y).reshape(n, L, len(pieces))  # x̃_{a+s} = Λ_s y, all pieces in one GEMM
        for i, (a, Lp, _, _) in enumerate(pieces):
            X[a + 1 : a + Lp + 1] = Xs[:, :Lp, i].T
        if self._hat:
            X[1:] /= self._qh
        X[1:] += self._g
        return X


def affine_stages(Ad, Bd, wd, n: int, m: int, T: int):
    """(A_d, B_d, w_d, ltv): float arrays, per stage ((T, n, n), (T, n, m), (T, n)) when ``Ad`` is 3-D."""
    Ad, Bd, wd = (np.asarray(M, dtype=float) for M in (Ad, Bd, wd))
    if Ad.ndim != 3:
        return Ad, Bd, wd.ravel(), False
    if Ad.shape != (T, n, n) or Bd.shape != (T, n, m) or wd.size != T * n:
        raise ValueError(
            f"a per-stage affine model needs Ad (T, n, n) = {(T, n, n)}, Bd {(T, n, m)} and wd {(T, n)}, "
            f"got {Ad.shape}, {Bd.shape} and {wd.shape}"
        )
    return Ad, Bd, wd.reshape(T, n), True


def _pieces(phi: np.ndarray, n: int, m: int) -> list:
    """Runs of inputs a … a+L−1 with φ_i = φ_a + (i − a) Δ, as (a, L, c, rhs).

    c = m·(1 + last knot any input up to a+L−1 shapes) is the column prefix of S nonzero on the piece's rows;
    rhs (n+2m+1, 1+c) is the piece's right-hand factor with its constant rows filled: φ_a ⊗ I, Δ ⊗ I and the
    offset's 1 (the first n rows take [x_a, S's row at x_a] at each build).
    """
    T, p = phi.shape
    tol = 1e-12 * max(1.0, np.abs(phi).max())
    used = np.abs(phi) > 0
    last_knot = np.maximum.accumulate(np.where(used.any(axis=1), p - 1 - np.argmax(used[:, ::-1], axis=1), -1))
    pieces, a = [], 0
    while a < T:
        delta = phi[a + 1] - phi[a] if a + 1 < T else np.zeros(p)
        L = 1
        while a + L < T and np.abs(phi[a + L] - phi[a] - L * delta).max() <= tol:
            L += 1
        if L == 1:
            delta = np.zeros(p)
        c = m * (last_knot[a + L - 1] + 1)
        rhs = np.zeros((n + 2 * m + 1, 1 + c))
        rhs[n : n + m, 1:] = np.kron(phi[a], np.eye(m))[:, :c]
        rhs[n + m : n + 2 * m, 1:] = np.kron(delta, np.eye(m))[:, :c]
        rhs[-1, 0] = 1.0
        pieces.append((a, L, c, rhs))
        a += L
    return pieces
