"""RealTimeIteration: real-time iteration (Diehl et al.), Gauss–Newton SQP steps on the multiple-shooting NLP.

One step per control step by default (``iterations``). Each step is the QP of LinearMPC with the model linearized
stage by stage along the current iterate — the previous plan shifted by one step, then each new QP solution — so it
reuses the sparse and condensed knot QPs, their backends and LinearMPC's C step. The cost is quadratic, so the
Gauss–Newton Hessian is exact in the cost and a fixed point of the iteration is a KKT point of the NLP: iterated, it
reaches the optimum of NonlinearMPC (:mod:`ocpkit.solvers.nlp`).
"""

from __future__ import annotations

import numpy as np

from ocpkit._checks import integer
from ocpkit.status import Solution
from ocpkit.model.ocp import OCP
from ocpkit.solvers.methods import RTI
from ocpkit.solvers.qp import LinearMPC


class RealTimeIteration(LinearMPC):
    """Real-time iteration: ``iterations`` Gauss–Newton SQP steps per control step on the knot QP linearized
    along the iterate (LinearMPC's "trajectory" linearization), warm-started by shifting the previous plan.

    Iteration i + 1 linearizes at iteration i's QP solution (x̄_0 = x, x̄_k its predicted states, ū its inputs);
    ``tol`` > 0 stops early once the knots and predicted states move less than ``tol`` (max norm). When an
    iteration after the first fails (a time budget, a QP limit), the previous iteration's plan is returned:
    every iterate is a usable plan, the point of RTI.

    Where there are no predicted states to shift (a cold start, the step after a fallback) the first iteration
    linearizes at x held over the horizon, as NonlinearMPC and acados' SQP-RTI start cold, never along a rollout: the
    undamped Panda's input-goal rollout (|eig A_d| 1.11 a step at dt 0.01) ran 16-64 from x within T = 50 steps, and
    the closed loop cost 1.11 [1.61] times acados' with RK4 (median [worst], seeds 100-104 x 50 steps), 1.34 [3.30]
    and 29 fallbacks with Euler; held, the first plan equals acados' to 3e-7 and the closed-loop costs to 2e-5, no
    fallbacks (seeds 200-204 alike; the Puma 560 and nlink:13 within 2e-5 of before).

    Where LinearMPC builds its C step (:mod:`ocpkit.export.native`: DAQP, a robot-sized model, no task) the whole
    iteration runs as compiled C (:func:`ocpkit.export.export` with linearization "trajectory"), the same steps to
    rounding: until it is built, and after a failed step's soft-bound retry, in Python. A step's goal window, moved
    obstacles and initial guess (the first iterate) as LinearMPC takes them.

    For traditional MPC (p = T) ``form="sparse", qp="hpipm"`` (HPIPM's Riccati interior point through CasADi, on
    the stage-ordered sparse QP, warm-started) is the fastest path, every step certified. T = 50, RK4, 50 steps of
    seeds 0-2 and 3-5, median step in CPU time beside acados' SQP-RTI (partial-condensing HPIPM) run alike in the
    same minutes (load 2.8 on 2 CPUs): nlink:13 12.8 and 11.0 ms against acados' 10.2 and 10.3 (1.26x, 1.07x; the
    condensed C step about 51), Puma 560 3.0 and 2.3 against 2.9 and 2.7, Panda 3.1 and 3.2 against 4.8 and 4.6;
    90th percentile 14.1 and 12.3, 4.4 and 3.2, 4.3 and 4.8 ms (acados 11.0 and 11.5, 3.1 and 3.0, 5.4 and 5.2), the
    worst the first step (with the interface's build, 30 ms). An HPIPM iteration takes 0.85 ms (CPU) at nlink:13,
    acados' 0.28 (its own timer): CasADi's BLASFEO is the generic build (no AVX2 or FMA kernels), acados' the
    Haswell one. It is not the default: it takes hard state bounds only, no task terms, has no C step
    (:mod:`ocpkit.export`), and cannot run in a process that has loaded acados.

    ``form="sparse"`` alone (ProxQP's sparse backend) is faster than the condensed C step in the median, but its tail
    is heavy: at nlink:13 its cold first steps (27-44 iterations) and the steps after far warm starts cost 10-25 ms
    (CPU) an iteration, about 4 on the median warm step (4 iterations), and a warm start that stalls is solved
    again cold (587 iterations, 1.5 s); 90th percentile 7.0, 19.7 and 105 ms at load 0.6-0.9, worst 1.2 s on
    nlink:13.

    ``options`` are LinearMPC's but ``linearization`` (always along the iterate): ``form``, ``qp``, ``state_bounds``
    (soft by default), ``max_iter`` (each QP's iterations), ``time_limit`` (the whole step's budget, all iterations
    together), ``eps``, ``slack_weight``, ``native``, ``warm_start``, ``raise_on_fail``, ``threads``, ``gains`` (the
    last iteration's QP's feedback gain, each iteration computing its own)."""

    def __init__(
        self,
        ocp: OCP,
        *,
        iterations: int = RTI["iterations"].default,
        tol: float = RTI["tol"].default,
        state_bounds: str = RTI["state_bounds"].default,
        **options,
    ):
        if "linearization" in options:
            raise ValueError("RealTimeIteration takes no linearization: it always linearizes along its iterate")
        self.iterations = integer(iterations, "iterations", 1)
        if not (isinstance(tol, (int, float)) and np.isfinite(tol) and tol >= 0):
            raise ValueError(f"tol must be a finite number >= 0, got {tol!r}")
        self.tol = float(tol)
        super().__init__(ocp, linearization="trajectory", state_bounds=state_bounds, **options)

    def _native_options(self) -> dict:
        return {"iterations": self.iterations, "tol": self.tol}

    def __repr__(self):
        return f"RealTimeIteration({self.iterations}, {self.form}, {self.qp_name}, {self.path}, {self.ocp!r})"

    # C twin: step.in.c rti(), shifted_plan() and stage_models(); parity: tests/test_twins.py
    def _python_step(self, x: np.ndarray, goal: np.ndarray) -> Solution:
        """The iterations in Python (the C step, where loaded, runs the same ones: linearization "trajectory"), from
        the shifted plan or the step's initial guess."""
        deadline, par = self._deadline(), self.ocp.parameterization
        times = {"model": 0.0, "build": 0.0, "solve": 0.0}
        along, sol, qp_iterations, moved, done = self.shifted_plan(x, goal), None, 0, np.inf, 0
        for i in range(self.iterations):
            new = self._qp_step(x, goal, along, deadline, times, knots=None if sol is None else sol.knots)
            qp_iterations += new.iterations
            if not new.ok:
                if sol is None:
                    return new
                self._x_plan = sol.x_pred  # the last good iterate stays the plan
                sol.raw_status = f"{sol.raw_status}; iteration {i + 1} {new.status}: {new.raw_status}"
                break
            moved = (
                np.inf
                if sol is None
                else max(np.abs(new.knots - sol.knots).max(), np.abs(new.x_pred - sol.x_pred).max())
            )
            sol, done = new, i + 1
            if moved <= self.tol:
                break
            along = (np.vstack([x, sol.x_pred[1:-1]]), par.inputs(sol.knots))
        # Each iteration's QP is certified; the NLP's KKT point only where the iteration converged.
        converged = (
            f"converged (last iteration moved the plan {moved:.2g} <= tol {self.tol:g})"
            if moved <= self.tol
            else "not iterated to convergence"
            + (f" (last iteration moved the plan {moved:.2g})" if np.isfinite(moved) else "")
        )
        sol.raw_status = f"RTI {done} of {self.iterations} iterations, {converged}; QP: {sol.raw_status}"
        sol.iterations, sol.times = qp_iterations, times
        return sol


SOLVERS = {"rti": RealTimeIteration}
