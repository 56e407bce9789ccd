"""A task's cost terms and obstacles in the condensed QP (:class:`ocpkit.transcription.CondensedQP`), Gauss–Newton
about the plan: the rows and terms that :mod:`ocpkit.task` adds to the paper's small-matrix QP."""
from __future__ import annotations

import numpy as np

from ocpkit.compiled import SwitchingFunction
from ocpkit.ocp import OCP
from ocpkit.quadratic_program import QP


class TaskRows:
    """A task's terms and obstacles in the condensed QP, Gauss–Newton about a plan (ocpkit.task).

    With the plan's knots z̄, states x̄_k = S_k z̄ + v_k (the QP's own prediction, x̄_0 = x_0) and inputs ū_k = Φ_k z̄
    (Φ_k = φ_k ⊗ I), each residual is replaced by its linearization r_k + G_k (z − z̄), G_k = ∂r/∂x S_k + ∂r/∂u Φ_k,
    whose weighted squares add G_kᵀWG_k to P and G_kᵀW(r_k − G_k z̄) to q (P and q are those of the cost J itself;
    the QP's objective is ½J). An obstacle clearance d_k − margin ≥ 0 at x_k becomes the row
    d_k + D_k S_k (z − z̄) ≥ 0 for every pair within ``ACTIVATION`` of its margin at the plan: a hard row, or with
    ``soft`` the row d_k + D_k S_k (z − z̄) + s_k ≥ 0 with one slack s_k ≥ 0 per such stage costing
    obstacle_weight·(s_k + ½s_k²) in J (an exact penalty, like the sampling planners' fitness). The functions are
    the OCP's :meth:`~ocpkit.ocp.OCP.task_maps`."""

    def __init__(self, ocp: OCP, obstacles: bool, soft: bool = True):
        from ocpkit.task import ACTIVATION

        tf = ocp.task_functions
        self.T, self.n, self.m, self.p = ocp.horizon, ocp.nx, ocp.nu, ocp.knots
        self.phi = ocp.parameterization.basis
        self._maps = ocp.task_maps()
        self.stage, self.terminal = self._maps["stage"], self._maps["terminal"]
        self.ws, self.wt = tf.stage_weight, tf.terminal_weight
        self.clearance = self._maps["clearance"] if obstacles else None
        self.pairs, self.weight, self.activation, self.soft = tf.pairs, ocp.task.obstacle_weight, ACTIVATION, soft

    def wait(self, timeout: float | None = None) -> None:
        """Block until the background compiles of the task's functions have finished (tests, benchmarks)."""
        for fn in self._maps.values():
            if fn is not None and isinstance(fn.fn, SwitchingFunction):
                fn.fn.wait(timeout)

    def add(self, P, q, SV, x0, targets, knots):
        """Add the terms' Gauss–Newton model to P and q (in place); the obstacle rows (C, lower bound, stage)."""
        T, n, m, p = self.T, self.n, self.m, self.p
        zbar = knots.ravel()
        S = SV[:, :, 1:]
        X = np.vstack([x0, SV @ np.r_[1.0, zbar]])  # x̄_0 … x̄_T
        U = self.phi @ knots
        if self.stage is not None:
            r, rx, ru = (np.asarray(a) for a in self.stage(X[:-1].T, U.T, np.repeat(targets[:, None], T, axis=1)))
            nr = r.shape[0]
            Jx, Ju = rx.reshape(nr, T, n).transpose(1, 0, 2), ru.reshape(nr, T, m).transpose(1, 0, 2)
            G = np.einsum("kj,kra->krja", self.phi, Ju).reshape(T, nr, p * m)
            G[1:] += Jx[1:] @ S[:-1]
            self._accumulate(P, q, G.reshape(T * nr, -1), r.T.ravel(), np.tile(self.ws, T), zbar)
        if self.terminal is not None:
            r, rx = (np.asarray(a) for a in self.terminal(X[-1], targets))
            self._accumulate(P, q, rx @ S[-1], r.ravel(), self.wt, zbar)
        if self.clearance is None:
            return None
        d, dx = (np.asarray(a) for a in self.clearance(X[1:].T))
        D = dx.reshape(self.pairs, T, n).transpose(1, 0, 2)  # (T, pairs, n)
        near = d.T < self.activation  # (T, pairs)
        if not near.any():
            return None
        k, i = np.nonzero(near)
        C = np.einsum("ra,raj->rj", D[k, i], S[k])
        return C, C @ zbar - d.T[k, i], k

    @staticmethod
    def _accumulate(P, q, G, r, w, zbar):
        WG = w[:, None] * G
        P += G.T @ WG
        q += WG.T @ (r - G @ zbar)

    def constrain(self, qp: QP, rows) -> QP:
        """``qp`` with the obstacle rows, hard or (``soft``) with their stages' slacks appended after every other
        variable."""
        if rows is None:
            return qp
        C_rows, lo, stage = rows
        if not self.soft:
            C = np.vstack([qp.C, np.hstack([C_rows, np.zeros((C_rows.shape[0], qp.n - C_rows.shape[1]))])])
            return QP(qp.P, qp.q, qp.A, qp.b, C, np.r_[qp.l, lo], np.r_[qp.u, np.full(lo.size, np.inf)], box=qp.box,
                      curvature=qp.curvature)
        stages, slack_of = np.unique(stage, return_inverse=True)
        ne, n0 = stages.size, qp.n
        w = 0.5 * self.weight  # J's weight·(s + ½s²) in the QP's ½J
        P = np.pad(qp.P, ((0, ne), (0, ne)))
        P[n0:, n0:] += w * np.eye(ne)
        q = np.r_[qp.q, np.full(ne, w)]
        E = np.zeros((C_rows.shape[0], ne))
        E[np.arange(C_rows.shape[0]), slack_of] = 1.0
        rows = np.hstack([C_rows, np.zeros((C_rows.shape[0], n0 - C_rows.shape[1])), E])
        C = np.vstack([np.pad(qp.C, ((0, 0), (0, ne))), rows, np.hstack([np.zeros((ne, n0)), np.eye(ne)])])
        l = np.r_[qp.l, lo, np.zeros(ne)]
        u = np.r_[qp.u, np.full(lo.size + ne, np.inf)]
        A = np.pad(qp.A, ((0, 0), (0, ne)))
        return QP(P, q, A, qp.b, C, l, u, box=qp.box, curvature=min(qp.curvature, w))
