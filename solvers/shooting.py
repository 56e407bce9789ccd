"""The multiple-shooting NLP of NonlinearMPC (:mod:`ocpkit.solvers.nlp`): its transcription in IPOPT's and
sqpmethod's variable order [x_1 … x_T, U] and in fatrop's stage order, with the Gauss–Newton derivatives."""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from ocpkit.codegen.compiled import prebuild
from ocpkit.model.ocp import OCP


class _Deadline(ca.Callback):
    """sqpmethod's iteration callback: asks it to stop once ``deadline`` (perf_counter) has passed, so an SQP step
    keeps its budget (sqpmethod has no wall-time option). Checked after every SQP iteration."""

    def __init__(self, sizes: dict):
        ca.Callback.__init__(self)
        self.sizes, self.deadline = sizes, None
        self.construct("sqp_deadline", {})

    def get_n_in(self):
        return ca.nlpsol_n_out()

    def get_n_out(self):
        return 1

    def get_name_in(self, i):
        return ca.nlpsol_out(i)

    def get_name_out(self, i):
        return "stop"

    def get_sparsity_in(self, i):
        return ca.Sparsity.dense(self.sizes[ca.nlpsol_out(i)], 1)

    def eval(self, arg):
        return [int(self.deadline is not None and time.perf_counter() > self.deadline)]


class MultipleShooting:
    """The NLP over w = [x_1 … x_T, U_0 … U_{p−1}] NonlinearMPC solves, built once per OCP: a base of
    :class:`ocpkit.solvers.nlp.NonlinearMPC`, whose ``method``, ``dynamics`` and ``hessian`` it reads and whose
    ``_apply_limits`` makes the solver over it."""

    def _build(self, ocp: OCP) -> None:
        """The NLP over w = [x_1 … x_T, U_0 … U_{p−1}] with parameters (x_0, the goal window G[, the obstacle
        window O][, A_d, B_d, w_d]): G (ng, T+1), column k the goal of stage k's terms, column T the terminal terms';
        O (4, N·T), the N obstacles (centre, radius) x_k's clearances keep to, k = 1 … T side by side."""
        n, m, T, p = ocp.nx, ocp.nu, ocp.horizon, ocp.knots
        self._nX = n * T
        self._gaps, self._pairs = n * T, 0  # the gap rows, then the clearance rows (pairs per stage) of g
        self._order = None  # fatrop: positions of [x_1 … x_T, U] in its stage-ordered w
        self._stage_model = None  # Gauss–Newton: the affine model in the NLP's derivatives (rebuilt once compiled)
        if self.method == "fatrop":
            return self._build_fatrop(ocp)
        # MX graph over mapped calls of the SX step and cost Functions: derivatives are generated per step
        # Function, not for T inlined copies (inlining a 7-link RK4 step 50 times takes minutes to build).
        X = ca.MX.sym("X", n, T)  # columns x_1 … x_T
        U = ca.MX.sym("U", m, p)  # columns U_0 … U_{p−1}: vec(U) is the knots (p, m) row by row
        x0, goals = ca.MX.sym("x0", n), ca.MX.sym("goals", ocp.ng, T + 1)
        targets = goals[n:, :]
        params = [x0, ca.vec(goals)]
        tf = ocp.task_functions
        clearances = None
        if tf is not None and tf.pairs:  # clearances ≥ 0 at x_1 … x_T, against the obstacles of their stage
            obstacles = ca.MX.sym("obstacles", 4, tf.table.shape[1] * T)
            params.append(ca.vec(obstacles))
            clearances = tf.clearance_at.map(T)(X, obstacles)
            self._pairs = tf.pairs
        # u = φ U, column k is u_k; φ kept sparse so u_k depends structurally on its own knots only.
        inputs = ca.mtimes(U, ca.sparsify(ca.DM(ocp.parameterization.basis.T)))
        starts = ca.horzcat(x0, X[:, :-1])
        if self.dynamics == "affine":
            Ad, Bd, wd = ca.MX.sym("Ad", n, n), ca.MX.sym("Bd", n, m), ca.MX.sym("wd", n)
            params += [ca.vec(Ad), ca.vec(Bd), wd]
            predicted = ca.mtimes(Ad, starts) + ca.mtimes(Bd, inputs) + ca.repmat(wd, 1, T)
            stages = (ca.repmat(Ad, 1, T), ca.repmat(Bd, 1, T), ca.repmat(wd, 1, T))
        else:
            predicted = ocp.discrete().map(T)(starts, inputs)
            stages = None
        # The OCP's cost (every term at (x_k, u_k), k = 0 … T−1, and x_T; x_0's terms that do not depend on u are
        # constants) and its built-in quadratic terms alone, whose constant Hessian the Gauss–Newton one starts from.
        J, quadratic = _objective(ocp, starts, inputs, X[:, T - 1], goals)
        rows = [ca.vec(predicted - X)] + ([] if clearances is None else [ca.vec(clearances[0])])
        nlp = {"x": ca.vertcat(ca.vec(X), ca.vec(U)), "p": ca.vertcat(*params), "f": J, "g": ca.vertcat(*rows)}
        opts = self._solver_options(ocp)
        if self.hessian == "gauss-newton":
            opts.update(self._gauss_newton(ocp, nlp, quadratic, X, starts, inputs, targets, stages, clearances))
        self._lbg = np.zeros(self._gaps + self._pairs * T)
        self._ubg = np.r_[np.zeros(self._gaps), np.full(self._pairs * T, np.inf)]
        # Input bounds on the knots, as LinearMPC: with a convex-combination basis they bound every u_k.
        self._lbx = np.r_[np.tile(ocp.x_min, T), np.tile(ocp.u_min, p)]
        self._ubx = np.r_[np.tile(ocp.x_max, T), np.tile(ocp.u_max, p)]
        if self.method == "sqp":
            nw, ng, npar = nlp["x"].numel(), nlp["g"].numel(), nlp["p"].numel()
            self._deadline = _Deadline({"f": 1, "x": nw, "g": ng, "lam_x": nw, "lam_g": ng, "p": npar, "lam_p": npar})
            opts["iteration_callback"] = self._deadline
        self._nlp = ("ipopt" if self.method == "ipopt" else "sqpmethod", nlp, opts)
        self._apply_limits()

    def _gauss_newton(self, ocp: OCP, nlp: dict, quadratic, X, starts, inputs, targets, stages, clearances) -> dict:
        """nlpsol options that evaluate the NLP's derivatives from per-stage Jacobians instead of CasADi's AD of
        the mapped RK4 step (115 ms for the constraint Jacobian and 270 ms for the Hessian per call on the Puma
        560 at T = 50).

        The constraint Jacobian (and the rows it comes with): the gap rows' from the affine model (A_k, B_k, w_k) of
        every stage (``stages``, or the OCP's affine model mapped over the horizon: compiled C under its
        ``compiled`` policy), the clearances' from their own Jacobians (``clearances``: (d, ∂d/∂x) at x_1 … x_T, or
        None). The Hessian of the Lagrangian: Gauss–Newton, the quadratic cost's own (constant) plus 2 EᵀWE for the
        task's residuals with Jacobian E (stage k's towards the targets of column k of the goal window, x_T's of
        column T); the curvature of the dynamics, the clearances and the residuals is left out. A KKT point is the
        same; only the rate of convergence changes.

        Both derivatives are CasADi's of a model of the NLP that is linear in w — the gap rows A_k x_k + B_k u_k −
        x_{k+1}, the clearances' D_k x_k, the residuals' R_k (x_k, u_k) — with the per-stage Jacobians as symbols:
        no longer depending on w, they are evaluated at the Jacobians computed at the iterate."""
        n, m, T, tf = ocp.nx, ocp.nu, ocp.horizon, ocp.task_functions
        w, p = nlp["x"], nlp["p"]
        if stages is None:
            stages = self._stage(ocp).map(T)(starts, inputs)
        A, B = ca.MX.sym("A", n, n * T), ca.MX.sym("B", n, m * T)
        symbols, values = [A, B], list(stages[:2])
        linear = [
            ca.vec(
                ca.horzcat(
                    *[
                        ca.mtimes(_block(A, k, n), starts[:, k]) + ca.mtimes(_block(B, k, m), inputs[:, k]) - X[:, k]
                        for k in range(T)
                    ]
                )
            )
        ]
        residuals, weights, clearance = [], [], []
        if tf is not None:
            if clearances is not None:
                d, D_value = clearances
                D = ca.MX.sym("D", tf.pairs, n * T)
                symbols.append(D)
                values.append(D_value)
                linear.append(ca.vertcat(*[ca.mtimes(_block(D, k, n), X[:, k]) for k in range(T)]))
                clearance = [ca.vec(d)]
            if tf.stage_weight.size:
                Rx, Ru = (ca.MX.sym(name, tf.stage_weight.size, size * T) for name, size in (("Rx", n), ("Ru", m)))
                symbols += [Rx, Ru]
                values += tf.stage_residual.map(T)(starts, inputs, targets[:, :T])[1:]
                residuals += [
                    ca.mtimes(_block(Rx, k, n), starts[:, k]) + ca.mtimes(_block(Ru, k, m), inputs[:, k])
                    for k in range(T)
                ]
                weights += [tf.stage_weight] * T
            if tf.terminal_weight.size:
                RT = ca.MX.sym("RT", tf.terminal_weight.size, n)
                symbols.append(RT)
                values.append(tf.terminal_residual(X[:, T - 1], targets[:, T])[1])
                residuals.append(ca.mtimes(RT, X[:, T - 1]))
                weights.append(tf.terminal_weight)
        rows = ca.vertcat(*linear)
        outputs = [rows, ca.jacobian(rows, w)]
        if residuals:
            E = ca.jacobian(ca.vertcat(*residuals), w)
            outputs.append(2 * ca.mtimes(E.T, ca.mtimes(ca.diag(ca.DM(np.concatenate(weights))), E)))
        model = ca.Function("gauss_newton_model", [w, p] + symbols, outputs)
        rows, jac, *task = model(w, p, *values)
        g = ca.vertcat(rows[: n * T] + ca.vec(stages[2]), *clearance)
        # The quadratic cost's Hessian (Q, R through φ) does not depend on w or the parameters: a number.
        hess = ca.Function("cost_hessian", [w, p], [ca.hessian(quadratic, w)[0]])(0, 0)
        if task:
            hess = hess + task[0]
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", nlp["g"].numel())
        if self.method == "ipopt":
            return {
                "jac_g": ca.Function("nlp_jac_g", [w, p], [g, jac]),
                "hess_lag": ca.Function("nlp_hess_l", [w, p, lam_f, lam_g], [lam_f * ca.triu(hess)]),
            }
        return {
            "jac_fg": ca.Function("nlp_jac_fg", [w, p], [nlp["f"], ca.gradient(nlp["f"], w), g, jac]),
            "hess_lag": ca.Function("nlp_hess_l", [w, p, lam_f, lam_g], [lam_f * hess]),
        }

    def _build_fatrop(self, ocp: OCP) -> None:
        """The same NLP in fatrop's stage order, with ``_order`` mapping it to [x_1 … x_T, U].

        Traditional MPC (p = T): stage 0 holds u_0, stage k the pair (x_k, u_k), stage T x_T. With knots the
        stage-0 controls are the knots U and stages 1 … T−1 hold (x_k, C_k) with C_k = U carried by gap rows
        C_{k+1} = C_k, so each stage's input u_k = φ_k C_k is a function of that stage's variables only."""
        n, m, T, p = ocp.nx, ocp.nu, ocp.horizon, ocp.knots
        x0, goals = ca.MX.sym("x0", n), ca.MX.sym("goals", ocp.ng, T + 1)
        targets = goals[n:, :]
        phi = ocp.parameterization.basis
        traditional = ocp.parameterization.kind == "identity"
        c = m if traditional else p * m  # the controls of stage 0 / the carried block of stages 1 … T−1
        blocks, order_x, pos, self._copies = [], np.zeros((T, n), dtype=np.int64), 0, []
        u0 = ca.MX.sym("u0", c)
        blocks.append(u0)
        order_u0 = np.arange(c)
        pos += c
        carried, states = [u0], []
        for k in range(1, T + 1):
            xk = ca.MX.sym(f"x{k}", n)
            blocks.append(xk)
            order_x[k - 1] = pos + np.arange(n)
            pos += n
            states.append(xk)
            if k < T:
                ck = ca.MX.sym(f"c{k}", c)
                blocks.append(ck)
                carried.append(ck)
                if not traditional:
                    self._copies.append(pos)
                pos += c
        inputs = [
            carried[k] if traditional else ca.mtimes(ca.kron(ca.DM(phi[k : k + 1]), ca.DM.eye(m)), carried[k])
            for k in range(T)
        ]
        X, controls = ca.horzcat(*states), ca.horzcat(*inputs)
        starts = ca.horzcat(x0, X[:, :-1])
        J, quadratic = _objective(ocp, starts, controls, X[:, -1], goals)
        if self.hessian == "exact":
            predicted = ocp.discrete().map(T)(starts, controls)
        else:
            predicted, task = self._frozen_first_order(ocp, starts, controls, X[:, -1], targets)
            J = quadratic + task
        gaps = []
        for k in range(T):
            gap = states[k] - predicted[:, k]  # fatrop's sign: +I on the next stage's variables
            if not traditional and k + 1 < T:
                gap = ca.vertcat(gap, carried[k + 1] - carried[k])
            gaps.append(gap)
        # Knots from stage 0 (traditional: u_k is the control of stage k, columns of the knots (T, m)).
        if traditional:
            order_u = np.vstack([order_u0] + [order_x[k - 1, -1] + 1 + np.arange(m) for k in range(1, T)])
        else:
            order_u = order_u0.reshape(p, m)
        self._order = np.r_[order_x.ravel(), order_u.ravel()]
        nw = pos
        lo, hi = np.full(nw, -np.inf), np.full(nw, np.inf)
        lo[self._order] = np.r_[np.tile(ocp.x_min, T), np.tile(ocp.u_min, p)]
        hi[self._order] = np.r_[np.tile(ocp.x_max, T), np.tile(ocp.u_max, p)]
        self._lbx, self._ubx = lo, hi
        nlp = {"x": ca.vertcat(*blocks), "p": ca.vertcat(x0, ca.vec(goals)), "f": J, "g": ca.vertcat(*gaps)}
        self._lbg = self._ubg = 0.0
        nx = [0] + [n if traditional else n + c] * (T - 1) + [n]
        nu = [c] + [m if traditional else 0] * (T - 1) + [0]
        # Not expanded to SX: the expanded exact Hessian of the Puma 560's 50 inlined RK4 steps is one SX graph of
        # 30 M instructions (25 s to build; the Panda's 40 s); over MX its derivatives are generated per Function.
        opts = {
            "structure_detection": "manual",
            "N": T,
            "nx": nx,
            "nu": nu,
            "ng": [0] * (T + 1),
            "expand": False,
            "fatrop": {"print_level": 0, "tol": 1e-8},
            "print_time": False,
            "error_on_fail": False,
        }
        self._nlp = ("fatrop", nlp, opts)
        self._apply_limits()

    def _frozen_first_order(self, ocp: OCP, starts, inputs, last, targets):
        """The predicted states x_1 … x_T (columns) and the task's cost with the dynamics and the task's residuals
        replaced by their first-order models about the current point, the point and the Jacobians frozen
        (``ca.stop_diff``): the same values and first derivatives, and as exact Hessian of the Lagrangian the
        Gauss–Newton one — what the IPOPT path passes as its derivative functions (:meth:`_gauss_newton`), for a
        solver that takes none (fatrop). ``targets``: the goal window's targets, column k for stage k, T for x_T."""
        T, tf = ocp.horizon, ocp.task_functions
        A, B, w = (ca.stop_diff(v, 1) for v in self._stage(ocp, differentiable=True).map(T)(starts, inputs))
        predicted = ca.horzcat(
            *[
                ca.mtimes(_block(A, k, ocp.nx), starts[:, k]) + ca.mtimes(_block(B, k, ocp.nu), inputs[:, k]) + w[:, k]
                for k in range(T)
            ]
        )
        cost = 0
        if tf is not None and tf.stage_weight.size:
            r, Rx, Ru = (ca.stop_diff(v, 1) for v in tf.stage_residual.map(T)(starts, inputs, targets[:, :T]))
            dx, du = starts - ca.stop_diff(starts, 1), inputs - ca.stop_diff(inputs, 1)  # zero, with derivative I
            W = ca.DM(tf.stage_weight)
            for k in range(T):
                e = r[:, k] + ca.mtimes(_block(Rx, k, ocp.nx), dx[:, k]) + ca.mtimes(_block(Ru, k, ocp.nu), du[:, k])
                cost += ca.dot(e, W * e)
        if tf is not None and tf.terminal_weight.size:
            r, Rx = (ca.stop_diff(v, 1) for v in tf.terminal_residual(last, targets[:, T]))
            e = r + ca.mtimes(Rx, last - ca.stop_diff(last, 1))
            cost += ca.dot(e, ca.DM(tf.terminal_weight) * e)
        return predicted, cost

    def _stage(self, ocp: OCP, differentiable: bool = False) -> ca.Function:
        """The affine model (x̄, ū) -> (A_d, B_d, w_d) the Gauss–Newton derivatives evaluate, under the OCP's
        ``compiled`` policy; remembered so that a background compile that finishes later is taken up
        (:meth:`_solve` rebuilds the solver).

        ``differentiable``: CasADi builds the derivatives of a call even where ``stop_diff`` makes them zero, and
        compiled C has none; the same library is loaded once more with finite differences declared, which are
        never evaluated (their seeds are structurally zero)."""
        self._stage_model = fn = ocp.affine()
        if differentiable and fn.class_name() == "External":
            # The library OCP.affine compiled (the same Function, default flags), found in the cache by its hash.
            source = ocp.model.affine(ocp.dt, ocp.substeps, ocp.integrator)
            fn = ca.external(fn.name(), str(prebuild(source)), {"enable_fd": True})
        return fn

    def _solver_options(self, ocp: OCP) -> dict:
        if self.method == "ipopt":
            ipopt = {
                "print_level": 0,
                "sb": "yes",
                # Start from the supplied primal and dual point (the shifted previous solution).
                "warm_start_init_point": "yes",
                "mu_strategy": "adaptive",
            }
            return {"ipopt": ipopt, "print_time": False, "error_on_fail": False}
        qpsol = self.options.get("qpsol", "qrqp")
        quiet = {
            "qrqp": {"print_iter": False, "print_header": False, "print_info": False},
            "osqp": {"osqp": {"verbose": False}},
        }.get(qpsol, {})
        opts = {
            "qpsol": qpsol,
            "qpsol_options": {**quiet, "error_on_fail": False},
            "print_header": False,
            "print_iteration": False,
            "print_status": False,
            "print_time": False,
            "error_on_fail": False,
        }
        if self.hessian == "exact":
            # Exact Hessians of a nonlinear OCP can be indefinite; qrqp needs a convex QP. The Gauss–Newton one is
            # positive semidefinite: regularizing it (a Gershgorin bound, far above its smallest eigenvalue) cut
            # every step of an nlink:3 reach to 1e-2 and ran into the 100-iteration limit; unregularized, 5 to 14.
            opts["convexify_strategy"] = "regularize"
            if ocp.task_functions is not None:
                # A task's forward kinematics: the regularized exact Hessian ran into the 200-iteration limit on
                # every step of an nlink:3 reach (with or without an obstacle); BFGS converged in 12 iterations.
                opts["hessian_approximation"] = "limited-memory"
        return opts


def _objective(ocp: OCP, starts, inputs, last, goals):
    """(the OCP's cost, its built-in quadratic terms alone) of the stages (``starts``, ``inputs``: columns x_k, u_k,
    k = 0 … T−1) and the last state x_T: :class:`ocpkit.model.cost.Cost` summed over the horizon, stage k's terms
    towards column k of the goal window ``goals`` (ng, T+1), the terminal terms towards column T."""
    cost, T = ocp.cost, ocp.horizon
    return tuple(
        ca.sum2(stage.map(T)(starts, inputs, goals[:, :T])) + terminal(last, goals[:, T])
        for stage, terminal in ((cost.stage, cost.terminal), (cost.quadratic_stage, cost.quadratic_terminal))
    )


def _block(M, k: int, size: int):
    """Stage k's block of ``size`` columns of a mapped Function's horizontally stacked output."""
    return M[:, k * size : (k + 1) * size]
