"""A task's CasADi Functions, compiled once per OCP from its declaration (:class:`ocpkit.model.task.Task`): the
residuals of its cost terms with their Jacobians (the Gauss–Newton model the QPs and the NLP take, and the terms of
the OCP's cost, :class:`ocpkit.model.cost.Cost`), the clearances between robot spheres and obstacles, and the
sampling planners' exact obstacle penalty."""

from __future__ import annotations

import casadi as ca
import numpy as np


class CompiledTask:
    """A task's CasADi Functions for an OCP of nx states and nu inputs (built once by the OCP).

    Goal-target vector g (``size`` entries, the targets in order). Functions:

    * ``stage_residual`` (x, u, g) -> (r, ∂r/∂x, ∂r/∂u) and ``terminal_residual`` (x, g) -> (r, ∂r/∂x) with the
      weights ``stage_weight``, ``terminal_weight``: the Gauss–Newton model of the QPs, and the task's terms of
      the OCP's cost (:class:`ocpkit.model.cost.Cost`, :meth:`term_cost`), in the order of ``names``;
    * ``clearance`` (x) -> (d − margin per pair, its Jacobian, pairs × nx; robot spheres outer: pair i·N + j is
      robot sphere i and obstacle j of N) and ``penalty`` (x) -> the sampling planners' exact penalty of one state
      (zero without obstacles), with obstacles ``penalty_at`` (x, O) -> the same against any table O (below);
    * with obstacles, ``spheres`` (x) -> (C, C_x): the robot spheres' centres (3 × k) and their Jacobians side by
      side (3 × k·nx), and ``clearance_at`` (x, O) -> ``clearance`` for any table O (4 × N: centre, radius) of N
      obstacles — moving obstacles need no new Function; :meth:`pair_clearances` gives every pair's d − margin
      from the centres in numpy (where all pairs' values but few Jacobians are needed: the QP's rows, a
      certificate).

    The clearances are one pair's Function mapped (``Function.map``) over the obstacles and then over the robot
    spheres, on the spheres' kinematics computed once: their expression and generated C grow with the robot's
    spheres, not with the pairs (written out pair by pair, the C file and its compile grew with the obstacles).
    """

    def __init__(self, task, nx: int, nu: int):
        self.task, self.nx, self.nu = task, nx, nu
        self.size = task.target_size
        x, u, g = ca.SX.sym("x", nx), ca.SX.sym("u", nu), ca.SX.sym("g", self.size)
        stage, terminal, ws, wt, offset = [], [], [], [], 0
        self.names, self._rows = [], {"stage": {}, "terminal": {}}  # a term's rows in the stacked residuals
        for term in task.terms:
            target = g[offset : offset + term.target_size]
            offset += term.target_size
            if not term.active:
                continue
            self.names.append(term.name)
            r, w, wT = term.expression(x, u, target)
            for part, rs, weights, weight, on in (
                ("stage", stage, ws, w, term.stage),
                ("terminal", terminal, wt, wT, term.terminal),
            ):
                if on:
                    start = sum(len(v) for v in weights)
                    self._rows[part][term.name] = slice(start, start + r.numel())
                    rs.append(r)
                    weights.append(weight)
        rs, rt = ca.vertcat(*stage) if stage else ca.SX(0, 1), ca.vertcat(*terminal) if terminal else ca.SX(0, 1)
        self.stage_weight = np.concatenate(ws) if ws else np.zeros(0)
        self.terminal_weight = np.concatenate(wt) if wt else np.zeros(0)
        self.stage_residual = ca.Function(
            "task_stage_residual",
            [x, u, g],
            [rs, ca.jacobian(rs, x), ca.jacobian(rs, u)],
            ["x", "u", "g"],
            ["r", "r_x", "r_u"],
        )
        self.terminal_residual = ca.Function(
            "task_terminal_residual", [x, g], [rt, ca.jacobian(rt, x)], ["x", "g"], ["r", "r_x"]
        )
        self.pairs = task.pairs
        # The obstacles (4 × N: centre, radius) and each robot sphere's radius plus the margin kept from them (k)
        self.table = np.array([[*o.center, o.radius] for o in task.obstacles], dtype=float).reshape(-1, 4).T
        self.radii = np.array([s.radius for s in task.robot], dtype=float) + task.margin
        if not self.pairs:
            self.clearance = ca.Function("clearance", [x], [ca.SX(0, 1), ca.SX(0, nx)], ["x"], ["d", "d_x"])
            self.penalty = ca.Function("obstacle_penalty", [x], [ca.SX(0)], ["x"], ["penalty"])
            return
        self.spheres = self._spheres(x)
        self.clearance_at, values = self._mapped()
        xm = ca.MX.sym("x", nx)
        d, d_x = self.clearance_at(xm, ca.DM(self.table))
        self.clearance = ca.Function("clearance", [xm], [d, d_x], ["x"], ["d", "d_x"])
        Om = ca.MX.sym("O", 4, self.table.shape[1])
        h = ca.fmax(0, -ca.mmin(values(xm, Om)))
        self.penalty_at = ca.Function(
            "obstacle_penalty_at", [xm, Om], [task.obstacle_weight * (h + 0.5 * h * h)], ["x", "O"], ["penalty"]
        )
        self.penalty = ca.Function(
            "obstacle_penalty", [xm], [self.penalty_at(xm, ca.DM(self.table))], ["x"], ["penalty"]
        )

    def term_cost(self, name: str, r, part: str):
        """Term ``name``'s r_iᵀW_ir_i from the stacked residuals ``r`` of ``part`` ("stage" or "terminal"); zero
        where the term has no such part."""
        rows = self._rows[part].get(name)
        if rows is None:
            return ca.SX(0)
        weight = (self.stage_weight if part == "stage" else self.terminal_weight)[rows]
        return ca.dot(r[rows], ca.DM(weight) * r[rows])

    def pair_clearances(self, C: np.ndarray, obstacles: np.ndarray | None = None) -> np.ndarray:
        """d − margin of every pair, (M, k, N), from the robot spheres' centres C (3, M, k) at M states; the
        obstacles the declared ones, or ``obstacles`` (M, N, 4) at each state (centre, radius: an obstacle window's
        rows, :meth:`ocpkit.model.ocp.OCP.obstacle_window`)."""
        table = self.table if obstacles is None else np.transpose(obstacles, (2, 0, 1))[:, :, None, :]
        d = np.sqrt(sum((C[a][:, :, None] - table[a]) ** 2 for a in range(3)))
        d -= self.radii[:, None] + table[3]
        return d

    def _spheres(self, x) -> ca.Function:
        """(x) -> (C, C_x): the robot spheres' centres (3 × k) and ∂c_i/∂x side by side (3 × k·nx, dense)."""
        from ocpkit.model.kinematics import sphere_centers

        kin, k = self.task.kinematics, len(self.task.robot)
        C = sphere_centers(kin, self.task.robot)(x[: kin.n])
        J = ca.densify(ca.jacobian(ca.vec(C), x))  # row 3i + a: ∂C[a, i]/∂x
        return ca.Function(
            "robot_spheres", [x], [C, ca.horzcat(*(J[3 * i : 3 * i + 3, :] for i in range(k)))], ["x"], ["C", "C_x"]
        )

    def _mapped(self) -> tuple[ca.Function, ca.Function]:
        """``clearance_at`` (x, O) -> (d, d_x), and the same without the Jacobian (x, O) -> d: one pair's clearance
        mapped over the N obstacles (the sphere's centre, Jacobian and radius shared), then over the k spheres."""
        nx, k, N = self.nx, len(self.task.robot), self.table.shape[1]
        c, c_x, r, o = ca.SX.sym("c", 3), ca.SX.sym("c_x", 3, nx), ca.SX.sym("r"), ca.SX.sym("o", 4)
        e = c - o[:3]
        dist = ca.norm_2(e)
        d = dist - r - o[3]
        both = ca.Function("pair_clearance", [c, c_x, r, o], [d, ca.mtimes((e / dist).T, c_x)])
        alone = ca.Function("pair_distance", [c, r, o], [d])
        # reduce_in: the inputs every call shares (the sphere's, over obstacles; the table, over spheres)
        both = both.map("obstacles", "serial", N, [0, 1, 2], []).map("spheres", "serial", k, [3], [])
        alone = alone.map("obstacles", "serial", N, [0, 1], []).map("spheres", "serial", k, [2], [])
        x, O = ca.MX.sym("x", nx), ca.MX.sym("O", 4, N)
        C, C_x = self.spheres(x)
        radii = ca.DM(self.radii).T
        d, d_x = both(C, C_x, radii, O)  # 1 × pairs and 1 × pairs·nx, pair i·N + j in block i·N + j
        at = ca.Function("clearance_at", [x, O], [d.T, ca.reshape(d_x, nx, self.pairs).T], ["x", "O"], ["d", "d_x"])
        return at, ca.Function("clearance_values", [x, O], [alone(C, radii, O).T], ["x", "O"], ["d"])
