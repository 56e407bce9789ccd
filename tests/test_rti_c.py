"""The real-time iteration as compiled C (ocpkit.export with linearization "trajectory", LinearMPC's C step)
against the Python RealTimeIteration: the same closed loops, predicted states and iterations, to rounding."""

import numpy as np
import pytest

from ocpkit import problems
from ocpkit.export import export
from ocpkit.sim.simulate import simulate
from ocpkit.solvers.rti import RealTimeIteration
from ocpkit.solvers.qp import LinearMPC
from ocpkit.model.task import FramePosition, Task


@pytest.mark.parametrize(
    "name, horizon, iterations, tol, integrator",
    [
        ("nlink:3", 40, 1, 0.0, "rk4"),
        ("puma560", 50, 1, 0.0, "rk4"),
        ("panda", 30, 1, 0.0, "rk4"),
        ("nlink:3", 40, 3, 1e-6, "rk4"),
        ("puma560", 50, 1, 0.0, "euler"),
        ("panda", 30, 2, 0.0, "euler"),
    ],
)
def test_c_step_equals_python_rti_in_closed_loop(name, horizon, iterations, tol, integrator):
    prob = problems.make(name)
    ocp = prob.ocp(knots=5, horizon=horizon, integrator=integrator)
    c = RealTimeIteration(ocp, iterations=iterations, tol=tol, native=True)
    py = RealTimeIteration(ocp, iterations=iterations, tol=tol, native=False)
    assert "C step" in repr(c) and "C step" not in repr(py)
    for seed in (0, 1):  # reset between runs: the C step's own plan and warm start are forgotten too
        x0, goal = prob.sample(seed)
        c.reset(), py.reset()
        tc, tp = (simulate(prob.plant(), ctrl, x0, goal, 0.3) for ctrl in (c, py))
        assert tc.fallbacks == tp.fallbacks == 0
        np.testing.assert_allclose(tc.x, tp.x, rtol=0, atol=1e-8)
        for sc, sp in zip(tc.solutions, tp.solutions):
            np.testing.assert_allclose(sc.knots, sp.knots, rtol=0, atol=1e-7)
            np.testing.assert_allclose(sc.x_pred, sp.x_pred, rtol=0, atol=1e-8)
            assert sc.certificate is not None and sc.certificate.failed() is None


def test_linear_mpc_trajectory_and_rti_take_the_c_step():
    prob = problems.make("nlink:3")
    ocp = prob.ocp(knots=4, horizon=30)
    ltv = LinearMPC(ocp, linearization="trajectory", native=True)
    rti = RealTimeIteration(ocp, native=True)
    x0, goal = prob.sample(2)
    a, b = ltv.solve(x0, goal), rti.solve(x0, goal)
    assert "C step" in repr(ltv) and "C step" in repr(rti)
    assert a.ok and b.ok and a.times["model"] > 0  # measured in C
    np.testing.assert_allclose(a.knots, b.knots, rtol=0, atol=1e-12)


def test_trajectory_export_refuses_what_it_cannot_do(tmp_path):
    prob = problems.make("nlink:3")
    ocp = prob.ocp(knots=3, horizon=20)
    with pytest.raises(ValueError, match="iterations and tol are options of linearization 'trajectory'"):
        export(ocp, tmp_path / "a", iterations=2)
    with pytest.raises(ValueError, match="iterations must be"):
        export(ocp, tmp_path / "b", linearization="trajectory", iterations=0)
    tasked = prob.ocp(knots=3, horizon=20, task=Task([FramePosition(prob.kinematics, "tip", 50.0)]))
    with pytest.raises(ValueError, match="linearization 'trajectory'"):
        export(tasked, tmp_path / "c", linearization="trajectory")
    why = RealTimeIteration(tasked)._no_native_step()
    assert why is not None and "task" in why


def test_cli_exports_the_real_time_iteration(tmp_path, capsys):
    from ocpkit.cli import main

    rc = main(
        [
            "export",
            "nlink:3",
            "--horizon",
            "30",
            "--linearization",
            "trajectory",
            "--iterations",
            "2",
            "--out",
            str(tmp_path / "rti"),
        ]
    )
    out = capsys.readouterr().out
    assert rc == 0 and "linearization trajectory" in out and "agree" in out
