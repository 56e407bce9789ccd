"""Bad input is rejected at construction with an error naming the argument."""

import numpy as np
import pytest

from ocpkit.model.ocp import OCP
from ocpkit.model.parameterization import Parameterization
from ocpkit.problems import make

MODEL = make("pendulum").plant()
GOOD = dict(model=MODEL, dt=0.01, horizon=10, Q=np.eye(2), R=[[1.0]])


def build(**changes):
    kw = {**GOOD, **changes}
    return OCP(kw.pop("model"), kw.pop("dt"), kw.pop("horizon"), kw.pop("Q"), kw.pop("R"), **kw)


@pytest.mark.parametrize(
    "changes,match",
    [
        (dict(dt=0.0), "dt must be finite and > 0"),
        (dict(dt=-1), "dt must be finite and > 0"),
        (dict(dt=float("nan")), "dt must be finite and > 0"),
        (dict(horizon=0), "horizon must be >= 1"),
        (dict(Q=np.eye(3)), "Q must have shape"),
        (dict(Q=[[1, 1], [0, 1]]), "Q must be symmetric"),
        (dict(Q=np.diag([1, -1])), "Q must be positive semidefinite"),
        (dict(Q=[[np.nan, 0], [0, 1]]), "Q must be finite"),
        (dict(R=[[0.0]]), "R must be positive definite"),
        (dict(R=[[np.inf]]), "R must be finite"),
        (dict(u_min=[1.0], u_max=[-1.0]), r"u_min\[0\] = 1.0 is above u_max\[0\] = -1.0"),
        (dict(x_min=[0, 0], x_max=[1, -1]), r"x_min\[1\]"),
        (dict(u_min=[np.nan]), "u_min must be free of NaN"),
        (dict(u_max=[1.0, 2.0]), "u_max must have shape"),
        (dict(u_goal=[np.inf]), "u_goal must be finite"),
        (dict(Q_terminal=-np.eye(2)), "Q_terminal must be positive semidefinite"),
        (dict(parameterization=Parameterization.linear_interp(5, 3)), "parameterization has horizon 5"),
        (dict(parameterization="linear"), "parameterization must be a Parameterization"),
        (dict(model="pendulum"), "model must be an ocpkit Model"),
    ],
)
def test_bad_ocp(changes, match):
    with pytest.raises((ValueError, TypeError), match=match):
        build(**changes)


def test_weights_accept_scalars_and_diagonals():
    ocp = build(Q=[10.0, 0.1], R=0.5)
    np.testing.assert_array_equal(ocp.Q, np.diag([10.0, 0.1]))
    np.testing.assert_array_equal(ocp.R, [[0.5]])


def test_solve_rejects_bad_state():
    from ocpkit.solvers.qp import LinearMPC

    c = LinearMPC(build())
    with pytest.raises(ValueError, match="x must be finite"):
        c.solve([np.nan, 0.0], [0.0, 0.0])
    with pytest.raises(ValueError, match="goal must have shape"):
        c.solve([0.0, 0.0], [0.0])


def test_unknown_names():
    with pytest.raises(ValueError, match="unknown problem 'pendulm'"):
        make("pendulm")
    from ocpkit.solvers import make as make_solver

    with pytest.raises(ValueError, match="unknown solver 'foo'"):
        make_solver("foo", build())
    from ocpkit.solvers.qp import LinearMPC

    with pytest.raises(ValueError, match="form must be one of"):
        LinearMPC(build(), form="dense")
    with pytest.raises(ValueError, match="qp must be one of"):
        LinearMPC(build(), qp="gurobi")
