"""The OCP's cost as a sum of named terms, built once and read by every solver and measure.

In the style of Crocoddyl's ``CostModelSum``, the cost is a list of terms, each a stage part ℓ_i(x, u, goal) and
optionally a terminal part ℓ_i^T(x, goal):

    J = Σ_{k=0}^{T−1} Σ_i ℓ_i(x_k, u_k, goal) + Σ_i ℓ_i^T(x_T, goal)

The two built-in terms are ordinary terms of this sum: "state", (x − x_goal)ᵀQ(x − x_goal) (terminal: Q_T), and
"input", (u − u_g)ᵀR(u − u_g) with u_g the OCP's input goal for x_goal (:meth:`ocpkit.model.ocp.OCP.input_goal`).
A task adds its active least-squares terms r_iᵀW_ir_i (:mod:`ocpkit.model.task`). x_0 is measured, so its stage
terms that do not depend on u are constants of the optimization.

Who reads what: the NLP (:mod:`ocpkit.solvers.shooting`) its objective from :attr:`Cost.stage` and
:attr:`Cost.terminal` and its Gauss–Newton Hessian from the built-in terms (:attr:`Cost.quadratic_stage`,
constant) and the task's residuals; the sampling kernels (:mod:`ocpkit.codegen.kernels.rollout`) their fitness from
:attr:`Cost.stage` and :attr:`Cost.terminal`; the closed-loop measures (:mod:`ocpkit.sim.metrics`) the cost per term
from :attr:`Cost.stage_terms`. The QPs take the built-in terms through their weights Q, Q_T, R (exact: they are
quadratic) and the task's terms through the Gauss–Newton model of the same residuals
(:class:`ocpkit.model.task.CompiledTask`).
"""

from __future__ import annotations

import casadi as ca


class Cost:
    """The cost of an OCP of nx states, nu inputs and a goal of ng entries ([x_goal; the task's targets]).

    Functions (CasADi, SX):

    * ``stage`` (x, u, goal) -> ℓ and ``terminal`` (x, goal) -> ℓ_T: every term summed;
    * ``stage_terms`` (x, u, goal) -> one value per term and ``terminal_terms`` (x, goal), in :attr:`names`' order
      (zero where a term has no terminal part);
    * ``quadratic_stage`` and ``quadratic_terminal``: the built-in terms "state" and "input" alone (a constant
      Hessian in (x, u)).
    """

    def __init__(self, ocp):
        n, m, ng = ocp.nx, ocp.nu, ocp.ng
        x, u, g = ca.SX.sym("x", n), ca.SX.sym("u", m), ca.SX.sym("goal", ng)
        xg = g if ng == n else g[:n]
        ex, eu = x - xg, ocp.input_error(u, xg)
        stage = {"state": ca.bilin(ca.DM(ocp.Q), ex, ex), "input": ca.bilin(ca.DM(ocp.R), eu, eu)}
        terminal = {"state": ca.bilin(ca.DM(ocp.Q_terminal), ex, ex)}
        quadratic, quadratic_T = stage["state"] + stage["input"], terminal["state"]
        total, total_T = quadratic, quadratic_T
        tf = ocp.task_functions
        if tf is not None:
            targets = g[n:]
            r = tf.stage_residual(x, u, targets)[0]
            rT = tf.terminal_residual(x, targets)[0]
            total = total + ca.dot(r, ca.DM(tf.stage_weight) * r)
            total_T = total_T + ca.dot(rT, ca.DM(tf.terminal_weight) * rT)
            for name in tf.names:
                stage[name] = tf.term_cost(name, r, "stage")
                terminal[name] = tf.term_cost(name, rT, "terminal")
        self.names = list(stage)
        self.nx, self.nu, self.ng = n, m, ng

        def function(name, inputs, labels, value):
            return ca.Function(name, inputs, [value], labels, ["l"])

        self.stage = function("stage_cost", [x, u, g], ["x", "u", "goal"], total)
        self.terminal = function("terminal_cost", [x, g], ["x", "goal"], total_T)
        self.quadratic_stage = function("quadratic_stage_cost", [x, u, g], ["x", "u", "goal"], quadratic)
        self.quadratic_terminal = function("quadratic_terminal_cost", [x, g], ["x", "goal"], quadratic_T)
        self.stage_terms = function(
            "stage_terms", [x, u, g], ["x", "u", "goal"], ca.vertcat(*(stage[name] for name in self.names))
        )
        self.terminal_terms = function(
            "terminal_terms", [x, g], ["x", "goal"], ca.vertcat(*(terminal.get(name, ca.SX(0)) for name in self.names))
        )

    def __repr__(self):
        return f"Cost({' + '.join(self.names)})"
