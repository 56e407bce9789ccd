"""A task's cost terms and obstacles in the condensed QP (:class:`ocpkit.qp.transcription.CondensedQP`), Gauss–Newton
about the plan: the rows and terms that :mod:`ocpkit.model.task` adds to the paper's small-matrix QP."""

from __future__ import annotations

import numpy as np

from ocpkit.codegen.compiled import SwitchingFunction
from ocpkit.model.ocp import OCP
from ocpkit.qp.quadratic_program import QP


class TaskRows:
    """A task's terms and obstacles in the condensed QP, Gauss–Newton about a plan (ocpkit.model.task).

    With the plan's knots z̄, states x̄_k = S_k z̄ + v_k (the QP's own prediction, x̄_0 = x_0) and inputs ū_k = Φ_k z̄
    (Φ_k = φ_k ⊗ I), each residual is replaced by its linearization r_k + G_k (z − z̄), G_k = ∂r/∂x S_k + ∂r/∂u Φ_k,
    whose weighted squares add G_kᵀWG_k to P and G_kᵀW(r_k − G_k z̄) to q (P and q are those of the cost J itself;
    the QP's objective is ½J). An obstacle clearance d_k − margin ≥ 0 at x_k becomes the row
    d_k + D_k S_k (z − z̄) ≥ 0 for the pairs :meth:`select` picks: a hard row, or with ``soft`` the row
    d_k + D_k S_k (z − z̄) + s_k ≥ 0 with one slack s_k ≥ 0 per such stage costing obstacle_weight·(s_k + ½s_k²) in
    J (an exact penalty, like the sampling planners' fitness). The terms' functions are the OCP's
    :meth:`~ocpkit.model.ocp.OCP.task_maps`. The clearances and their gradients come from the robot spheres' centres
    and Jacobians (``spheres`` of :class:`ocpkit.model.task.CompiledTask`, one mapped call over the horizon) and the
    obstacle table, in numpy: the kinematics once per stage, a pair's gradient only for a row kept (every pair's
    Jacobian, as ``clearance`` gives it, is 128 MB a step for 1,000 obstacles around the Panda over 50 stages)."""

    def __init__(self, ocp: OCP, obstacles: bool, soft: bool = True):
        from ocpkit.model.task import ACTIVATION, ROWS_PER_SPHERE, ROWS_PER_STAGE

        self.tf = tf = ocp.task_functions
        self.T, self.n, self.m, self.p = ocp.horizon, ocp.nx, ocp.nu, ocp.knots
        self.phi = ocp.parameterization.basis
        self._maps = ocp.task_maps()
        self.stage, self.terminal = self._maps["stage"], self._maps["terminal"]
        self.ws, self.wt = tf.stage_weight, tf.terminal_weight
        self.obstacles = obstacles and tf.pairs > 0  # whether this QP has obstacle rows
        self.spheres = self._maps["spheres"] if self.obstacles else None
        self.weight, self.activation, self.soft = ocp.task.obstacle_weight, ACTIVATION, soft
        self.per_sphere, self.per_stage = ROWS_PER_SPHERE, ROWS_PER_STAGE

    def wait(self, timeout: float | None = None) -> None:
        """Block until the background compiles of the task's functions have finished (tests, benchmarks)."""
        for fn in self._maps.values():
            if fn is not None and isinstance(fn.fn, SwitchingFunction):
                fn.fn.wait(timeout)

    def add(self, P, q, SV, x0, targets, knots, obstacles=None):
        """Add the terms' Gauss–Newton model to P and q (in place); the obstacle rows (C, lower bound, stage).

        ``targets``: held, or per stage (T+1, ·), row k stage k's (row T the terminal terms'); ``obstacles``: None
        (where the task declares them) or each obstacle's centre and radius at each stage, (T+1, N, 4), the
        clearance at x_k taken against row k."""
        T, n, m, p = self.T, self.n, self.m, self.p
        held = targets.ndim == 1
        stage_targets = np.repeat(targets[:, None], T, axis=1) if held else targets[:T].T
        end_targets = targets if held else targets[T]
        zbar = knots.ravel()
        S = SV[:, :, 1:]
        X = np.vstack([x0, SV @ np.r_[1.0, zbar]])  # x̄_0 … x̄_T
        U = self.phi @ knots
        if self.stage is not None:
            r, rx, ru = (np.asarray(a) for a in self.stage(X[:-1].T, U.T, stage_targets))
            nr = r.shape[0]
            Jx, Ju = rx.reshape(nr, T, n).transpose(1, 0, 2), ru.reshape(nr, T, m).transpose(1, 0, 2)
            G = np.einsum("kj,kra->krja", self.phi, Ju).reshape(T, nr, p * m)
            G[1:] += Jx[1:] @ S[:-1]
            self._accumulate(P, q, G.reshape(T * nr, -1), r.T.ravel(), np.tile(self.ws, T), zbar)
        if self.terminal is not None:
            r, rx = (np.asarray(a) for a in self.terminal(X[-1], end_targets))
            self._accumulate(P, q, rx @ S[-1], r.ravel(), self.wt, zbar)
        if not self.obstacles:
            return None
        centres, jacobians = self.spheres(X[1:].T)
        spheres = self.tf.radii.size
        centres = centres.reshape(3, T, spheres)  # column t·k + i of the mapped call: sphere i at x_{t+1}
        moved = None if obstacles is None else obstacles[1:]  # the obstacles at x_1 … x_T
        d = self.tf.pair_clearances(centres, moved)  # (T, k, N)
        k, i, j = self.select(d)
        if not k.size:
            return None
        # (3, rows): from the obstacle's centre to the sphere's
        e = centres[:, k, i] - (self.tf.table[:3, j] if moved is None else moved[k, j, :3].T)
        # a sphere centred on the obstacle's centre (a fixed base sphere inside a huge ball): no direction, ∂d = 0
        grad = np.einsum(
            "ar,raj->rj",
            e / np.maximum(np.linalg.norm(e, axis=0), 1e-12),
            jacobians.reshape(3, T, spheres, n)[:, k, i].transpose(1, 0, 2),
        )  # ∂d/∂x (rows, n)
        # D S_k stage by stage (the rows come by stage): gathering S[k] row by row copied 47 MB a step at 1,200 rows
        C = np.empty((k.size, S.shape[2]))
        edges = np.searchsorted(k, np.arange(T + 1))
        for t in np.flatnonzero(np.diff(edges)):
            C[edges[t] : edges[t + 1]] = grad[edges[t] : edges[t + 1]] @ S[t]
        return C, C @ zbar - d[k, i, j], k

    def select(self, d: np.ndarray):
        """The pairs that become rows, as (stage, robot sphere, obstacle) index arrays ordered by stage, then pair,
        from d − margin (T, k, N) at the plan: those within ``activation`` of the margin; of them each sphere's
        ``per_sphere`` closest obstacles; of those the ``per_stage`` closest pairs of each stage.

        The bound keeps a step's QP small where many obstacles are near (100 obstacles about the Panda's path: up to
        111 rows a stage, 5,500 a step, against at most 2 per sphere and 24 a stage) and keeps the rows that bind
        first: a sphere's nearest obstacle, and its next nearest for a sphere between two. With one obstacle every
        sphere near it keeps its row, as without the bound (a bound per link instead dropped the row of a sphere
        that the plan then drove 7 cm into the obstacle). A pair left out is not forgotten: the next step,
        re-linearized, keeps it once it has come closer, and a plan that breaks it meanwhile is caught by the
        controller's certificate on the nonlinear rollout (status "soft", not "success")."""
        nearest = min(self.per_sphere, d.shape[2])
        closest = np.argpartition(d, nearest - 1, axis=2)[:, :, :nearest]  # each sphere's closest obstacles
        dist = np.take_along_axis(d, closest, axis=2)
        k, i, c = np.nonzero(dist < self.activation)
        j, dist = closest[k, i, c], dist[k, i, c]
        order = np.lexsort((dist, k))  # by stage, the closest pair first
        k, i, j = k[order], i[order], j[order]
        keep = np.arange(k.size) - np.searchsorted(k, k) < self.per_stage  # its place among its stage's rows
        k, i, j = k[keep], i[keep], j[keep]
        order = np.lexsort((i * d.shape[2] + j, k))
        return k[order], i[order], j[order]

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
            return QP(
                qp.P,
                qp.q,
                qp.A,
                qp.b,
                C,
                np.r_[qp.l, lo],
                np.r_[qp.u, np.full(lo.size, np.inf)],
                box=qp.box,
                curvature=qp.curvature,
            )
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
