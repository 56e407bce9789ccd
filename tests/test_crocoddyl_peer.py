"""The Crocoddyl peer: the same OCP as ocpkit's (dynamics, RK4 step, cost), FDDP at IPOPT's optimum, bench nlp."""

import sys

import numpy as np
import pytest

from ocpkit.benchmarks import crocoddyl_peer as peer
from ocpkit.benchmarks.nlp import bench_nlp
from ocpkit.solvers.nlp import NonlinearMPC

try:
    peer.require()
    MISSING = None
except ImportError as exc:  # not installed (CI installs ".[test]" only), or built for another pinocchio
    MISSING = str(exc)
needs_crocoddyl = pytest.mark.skipif(MISSING is not None, reason=f"Crocoddyl peer unavailable: {MISSING}")


def setup(spec="nlink:3", seed=0, horizon=20, integrator="rk4"):
    prob = peer.undamped(spec)
    ocp = prob.ocp(knots=None, horizon=horizon, integrator=integrator)
    x0, goal = prob.sample(seed)
    return prob, ocp, x0, goal


def test_asking_for_crocoddyl_without_it_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "crocoddyl", None)  # import crocoddyl now raises ImportError
    with pytest.raises(ImportError, match=r'pip install "ocpkit\[peers\]"'):
        bench_nlp(["nlink:2"], samples=1, steps=2, controllers=("ipopt", "crocoddyl"), echo=False)


def test_undamped_drops_damping_only():
    damped, plain = peer.registry.make("nlink:3"), peer.undamped("nlink:3")
    x, u = np.r_[0.1, -0.2, 0.3, 1.0, -2.0, 0.5], np.r_[0.5, -0.5, 0.2]
    gap = np.asarray(plain.model().f(x, u) - damped.model().f(x, u), dtype=float).ravel()
    np.testing.assert_allclose(gap[:3], 0.0, atol=1e-15)
    assert np.abs(gap[3:]).max() > 1e-3  # b q̇ with b = 0.01 through M⁻¹ of ~0.01 kg m²


@needs_crocoddyl
@pytest.mark.parametrize("spec", ["nlink:3", "panda"])
def test_same_dynamics_and_step(spec):
    """Crocoddyl's RK4 and Euler nodes step as ocpkit's "rk4" and "euler" (semi-implicit) discrete models."""
    import crocoddyl

    prob, ocp, _, _ = setup(spec)
    shooting = peer.ShootingOCP(prob, ocp)  # its construction checks ẋ against ocp.model.f
    nodes = {
        "rk4": crocoddyl.IntegratedActionModelRK(shooting.differential(), crocoddyl.RKType.four, ocp.dt),
        "euler": crocoddyl.IntegratedActionModelEuler(shooting.differential(), ocp.dt),
    }
    rng = np.random.default_rng(1)
    for _ in range(3):
        x, u = rng.uniform(-1, 1, ocp.nx), rng.uniform(-1, 1, ocp.nu)
        steps = {}
        for integrator, model in nodes.items():
            data = model.createData()
            model.calc(data, x, u)
            steps[integrator] = np.array(data.xnext)
            ours = np.asarray(prob.ocp(knots=None, integrator=integrator).discrete()(x, u), dtype=float).ravel()
            np.testing.assert_allclose(steps[integrator], ours, rtol=1e-12, atol=1e-12, err_msg=integrator)
        assert np.abs(steps["rk4"] - steps["euler"]).max() > 1e-6


@needs_crocoddyl
@pytest.mark.parametrize("integrator", ["rk4", "euler"])
@pytest.mark.parametrize("spec", ["nlink:3", "panda"])
def test_cost_is_the_objective_ipopt_minimizes(spec, integrator):
    """Crocoddyl's total cost at any trajectory (not a feasible one) equals the f of IPOPT's NLP, which ocpkit
    builds from the OCP on its own path (the Panda's input goal holds gravity compensation)."""
    prob, ocp, x0, goal = setup(spec, integrator=integrator)
    shooting = peer.ShootingOCP(prob, ocp)
    shooting.set(x0, goal)
    rng = np.random.default_rng(2)
    X = np.vstack([x0, goal + 0.3 * rng.normal(size=(ocp.horizon, ocp.nx))])
    U = ocp.input_goal(goal) + rng.normal(size=(ocp.horizon, ocp.nu))
    ipopt = NonlinearMPC(ocp)
    f = ipopt._solver.get_function("nlp_f")  # w = [x_1 … x_T, knots row by row], p = [x0, goal window (ng, T+1)]
    e0 = x0 - goal[: ocp.nx]  # the NLP's f has x_0's state term, a constant the peer's cost leaves out
    reference = float(f(np.r_[X[1:].ravel(), U.ravel()], np.r_[x0, np.tile(goal, ocp.horizon + 1)])) - e0 @ ocp.Q @ e0
    assert shooting.cost(X, U) == pytest.approx(reference, rel=1e-12)
    assert peer.objective(ocp, goal, X, U) == pytest.approx(reference, rel=1e-12)


@needs_crocoddyl
@pytest.mark.parametrize("integrator", ["rk4", "euler"])
def test_fddp_reaches_ipopts_optimum(integrator):
    """Same OCP, same integrator: FDDP's converged plan is IPOPT's p = T optimum (3e-14 relative cost measured, both
    integrators; bounds active, so BoxFDDP), cold and after a warm-started second step."""
    prob, ocp, x0, goal = setup(horizon=50, integrator=integrator)
    fddp, ipopt = peer.CrocoddylMPC(prob, ocp), NonlinearMPC(ocp)
    F = ocp.discrete()
    x = x0
    for _ in range(2):
        ours, theirs = ipopt.solve(x, goal), fddp.solve(x, goal)
        assert ours.ok and theirs.ok, (ours.raw_status, theirs.raw_status)
        costs = [peer.objective(ocp, goal, peer.rollout(ocp, x, s.knots), s.knots) for s in (ours, theirs)]
        assert costs[1] == pytest.approx(costs[0], rel=1e-8)
        assert np.isclose(np.abs(theirs.knots), ocp.u_max).any()
        np.testing.assert_allclose(theirs.knots, ours.knots, atol=1e-4 * ocp.u_max[0])
        x = np.asarray(F(x, ours.u), dtype=float).ravel()


@needs_crocoddyl
def test_what_crocoddyl_cannot_hold_is_refused():
    prob, ocp, _, _ = setup()
    with pytest.raises(ValueError, match="knots"):
        peer.ShootingOCP(prob, prob.ocp(knots=5, horizon=20))
    damped = peer.registry.make("nlink:3")
    with pytest.raises(ValueError, match="damping"):
        peer.ShootingOCP(damped, damped.ocp(knots=None))
    pendulum = peer.registry.make("pendulum")
    with pytest.raises(ValueError, match="pin_model"):
        peer.ShootingOCP(pendulum, pendulum.ocp(knots=None))
    with pytest.raises(ValueError, match="substeps"):
        peer.ShootingOCP(prob, prob.ocp(knots=None, horizon=20, substeps=2))


@needs_crocoddyl
def test_bench_nlp_column_and_per_solve_table(capsys):
    rows = bench_nlp(["nlink:2", "pendulum"], samples=1, steps=3, controllers=("ipopt", "crocoddyl"))
    out = capsys.readouterr().out
    croc = [r for r in rows if r["controller"] == "crocoddyl"]
    assert [r["problem"] for r in croc] == ["nlink:2"] and croc[0]["knots"] == "T" and croc[0]["fallbacks"] == 0
    assert "pendulum: no crocoddyl row" in out and "pin_model" in out
    assert "fddp rk4" in out and "FDDP / IPOPT at p = T" in out
