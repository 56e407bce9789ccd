"""NonlinearMPC's Gauss–Newton derivatives (the default) against CasADi's exact ones on the same NLP.

Independent paths compared: IPOPT with the exact Hessian and CasADi's AD of the whole NLP (the reference) against
IPOPT, SQP and fatrop with the Gauss–Newton Hessian and the constraint Jacobian assembled from the per-stage affine
model; the virtual machine's affine model against the compiled one, including the switch to it mid-loop.
"""

from __future__ import annotations

from concurrent.futures import Future

import numpy as np
import pytest

import ocpkit.problems as problems
from ocpkit.codegen.compiled import SwitchingFunction, compile_function
from ocpkit.sim.simulate import simulate
from ocpkit.solvers.nlp import NonlinearMPC
from ocpkit.model.task import Sphere, reach

# Every solver converged far below the 1e-6 the optima are compared at.
TIGHT = {
    "ipopt": {"tol": 1e-10},
    "sqp": {"tol_pr": 1e-9, "tol_du": 1e-9, "min_step_size": 1e-16},
    "fatrop": {"tol": 1e-10},
}


def _solve(ocp, x0, goal, method="ipopt", **kwargs):
    sol = NonlinearMPC(ocp, method=method, options=TIGHT[method], **kwargs).solve(x0, goal)
    assert sol.ok, sol.raw_status
    return sol


def _same_optimum(sol, ref, tol=1e-6):
    np.testing.assert_allclose(sol.knots, ref.knots, atol=tol * max(1.0, np.abs(ref.knots).max()))
    np.testing.assert_allclose(sol.x_pred, ref.x_pred, atol=tol * max(1.0, np.abs(ref.x_pred).max()))


@pytest.mark.parametrize(
    "name, horizon, methods",
    [
        ("nlink:3", 20, ("ipopt", "sqp", "fatrop")),
        pytest.param("puma560", 50, ("ipopt", "fatrop"), marks=pytest.mark.slow),  # 4.4 s: the rigid-body model
    ],
)
def test_gauss_newton_reaches_the_exact_hessians_optimum(name, horizon, methods):
    prob = problems.make(name)
    ocp = prob.ocp(knots=5, horizon=horizon)
    x0, goal = prob.sample(0)
    ref = _solve(ocp, x0, goal, hessian="exact")
    for method in methods:
        _same_optimum(_solve(ocp, x0, goal, method), ref)


def test_warm_started_closed_loop_follows_the_exact_path_in_fewer_iterations():
    """Each step starts from the previous primal and dual solution shifted by one step: the inputs are those of
    the exact-Hessian controller, and the warm steps take fewer iterations than the same steps started cold."""
    prob = problems.make("nlink:3")
    ocp = prob.ocp(knots=5, horizon=20)
    x0, goal = prob.sample(1)
    runs = {
        key: simulate(prob.plant(), NonlinearMPC(ocp, options=TIGHT["ipopt"], **kwargs), x0, goal, 8 * ocp.dt)
        for key, kwargs in (("exact", {"hessian": "exact"}), ("warm", {}), ("cold", {"warm_start": False}))
    }
    assert all(traj.fallbacks == 0 for traj in runs.values())
    np.testing.assert_allclose(runs["warm"].u, runs["exact"].u, atol=1e-6)
    iterations = {key: [sol.iterations for sol in traj.solutions[1:]] for key, traj in runs.items()}
    assert sum(iterations["warm"]) < sum(iterations["cold"]), iterations


@pytest.mark.parametrize("method", ["ipopt", "sqp"])
def test_a_task_with_an_active_obstacle_reaches_the_exact_optimum(method):
    """The task's residuals enter the Gauss–Newton Hessian and its clearances the constraint Jacobian: a reach of
    nlink:3's tip past a ball that the exact-Hessian plan touches (the clearance constraint active). IPOPT reaches
    the exact-Hessian optimum. The ball makes the NLP nonconvex, and SQP's Gauss–Newton path is sensitive to
    rounding: after other tests of the session (sampling planners' Taichi runtime, compiled models) it ended in
    another local minimum (a knot at its bound); of SQP the test asks a converged, feasible solve (sqpmethod's
    success)."""
    prob = problems.make("nlink:3")
    x0 = np.r_[0.3, 0.4, 0.3, 0.0, 0.0, 0.0]
    tip = prob.kinematics.function(prob.end_effector)
    target = np.asarray(tip([1.7, 0.3, 0.2])[0]).ravel()
    free = reach(prob, knots=5, horizon=20, compiled=False)
    goal = free.goal(x0, position=target)
    plan = _solve(free, x0, goal, hessian="exact")
    ball = Sphere(tuple(np.asarray(tip(plan.x_pred[12, :3])[0]).ravel()), 0.03)
    ocp = reach(prob, [ball], knots=5, horizon=20, compiled=False)
    ref = _solve(ocp, x0, goal, hessian="exact")
    assert np.abs(ref.knots - plan.knots).max() > 1e-2  # the ball moved the plan: the constraint is active
    if method == "ipopt":
        _same_optimum(_solve(ocp, x0, goal, method), ref)
        return
    _solve(ocp, x0, goal, method)  # converged and feasible (asserted in _solve)


@pytest.mark.parametrize("method, integrator", [("ipopt", "rk4"), ("fatrop", "rk4"), ("fatrop", "euler")])
def test_compiled_affine_model_gives_the_virtual_machines_optimum(method, integrator):
    """The derivatives from the compiled affine model (fatrop: the library loaded again with finite differences
    declared for CasADi's derivative generation under stop_diff, never evaluated) equal those from the virtual
    machine's, for each of the OCP's integrators."""
    prob = problems.make("nlink:3")
    x0, goal = prob.sample(0)
    vm, compiled = (
        _solve(prob.ocp(knots=5, horizon=20, integrator=integrator, compiled=policy), x0, goal, method)
        for policy in (False, True)
    )
    _same_optimum(compiled, vm, 1e-9)


@pytest.mark.parametrize("method", ["ipopt", "fatrop"])
def test_a_compile_finishing_mid_loop_is_taken_up(method, monkeypatch):
    """Under the default policy the affine model is the virtual machine's until its background compile finishes
    (a SwitchingFunction); the NLP is then rebuilt on the compiled one between two warm-started steps, and the
    closed loop is the one on the virtual machine throughout. The compile is handed over by hand after step 1."""
    prob = problems.make("nlink:3")
    x0, goal = prob.sample(0)
    ocp = prob.ocp(knots=5, horizon=20)
    vm = ocp.affine()
    assert not isinstance(vm, SwitchingFunction)  # nlink:3 is below the size the default policy compiles
    done = Future()
    switching = SwitchingFunction(vm, done)
    monkeypatch.setattr(ocp, "affine", lambda: switching.compiled() or switching)  # as OCP.affine
    ctrl = NonlinearMPC(ocp, method=method, options=TIGHT[method])
    reference = NonlinearMPC(prob.ocp(knots=5, horizon=20), method=method, options=TIGHT[method])

    def hand_over(k, x, sol):
        if k == 1:
            done.set_result(compile_function(vm))

    switched = simulate(prob.plant(), ctrl, x0, goal, 4 * ocp.dt, callback=hand_over)
    assert switched.fallbacks == 0 and ctrl._stage_model.class_name() == "External"
    np.testing.assert_allclose(switched.u, simulate(prob.plant(), reference, x0, goal, 4 * ocp.dt).u, atol=1e-8)


def test_a_task_without_targets_reaches_the_exact_optimum():
    """A task whose terms take no targets (the goal vector is x_goal alone): the reach study's keep-out hinge."""
    from ocpkit.studies.reach_trials import squared_hinge_term
    from ocpkit.model.task import Task

    prob = problems.make("nlink:3")
    x0, goal = prob.sample(0)
    ocp = prob.ocp(knots=5, horizon=20, compiled=False, task=Task([squared_hinge_term((x0[:3] + goal[:3]) / 2)]))
    assert ocp.ng == ocp.nx
    _same_optimum(_solve(ocp, x0, goal), _solve(ocp, x0, goal, hessian="exact"))
