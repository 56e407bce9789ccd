"""The shipped cart-pole: its CasADi dynamics against pinocchio's ABA (an independent path), its registry entry and its
draws."""

import numpy as np
import pytest

from ocpkit import problems
from ocpkit.problems.cartpole import CartPole, pinocchio_model

pin = pytest.importorskip("pinocchio")


@pytest.mark.parametrize("params", [{}, {"M": 2.0, "m": 0.1, "l": 0.8}])
def test_dynamics_equal_pinocchio_aba(params):
    """ẋ from the CasADi model = pinocchio's forward dynamics of a prismatic (PX) and a revolute (RZ) joint, the force
    on the prismatic one, at random states and forces."""
    pb = CartPole(**params)
    model = pinocchio_model(pb.M, pb.m, pb.l, pb.g)
    data = model.createData()
    f = pb.plant().f
    rng = np.random.default_rng(5)
    for _ in range(20):
        q, qd, u = rng.uniform([-1, -np.pi], [1, np.pi]), rng.normal(size=2) * 3, rng.normal() * 10
        xdot = np.array(f(np.r_[q, qd], [u])).ravel()
        np.testing.assert_array_equal(xdot[:2], qd)
        np.testing.assert_allclose(xdot[2:], pin.aba(model, data, q, qd, np.array([u, 0.0])), rtol=1e-10, atol=1e-10)


def test_hangs_at_zero_and_the_error_multiplier_scales_the_masses():
    pb = problems.make("cartpole")
    assert isinstance(pb, CartPole) and pb.name == "cartpole" and "cartpole" in problems.names()
    f = pb.plant().f
    assert np.allclose(np.array(f([0.3, 0.0, 0.0, 0.0], [0.0])).ravel(), 0)  # hanging at rest: an equilibrium
    assert np.array(f([0.0, 0.1, 0.0, 0.0], [0.0])).ravel()[3] < 0  # pulled back towards θ = 0
    assert np.allclose(np.array(f([0.0, np.pi, 0.0, 0.0], [0.0])).ravel(), 0, atol=1e-12)  # upright: one too
    # a push on the hanging cart accelerates cart and pole together, the pole swinging back
    push = np.array(f([0.0, 0.0, 0.0, 0.0], [1.3])).ravel()
    assert push[2] == pytest.approx(1.3 / pb.M) and push[3] == pytest.approx(-1.3 / (pb.M * pb.l))
    heavy = np.array(pb.model(error=2.0).f([0.0, 0.0, 0.0, 0.0], [1.3])).ravel()
    assert heavy[2] == pytest.approx(1.3 / (2 * pb.M))
    with pytest.raises(ValueError, match="argument"):
        problems.make("cartpole:7")
    with pytest.raises(ValueError, match="m"):
        CartPole(m=-1.0)


def test_sample_moves_the_cart_with_the_pole_hanging():
    pb = CartPole()
    x0, goal = pb.sample(3)
    assert np.array_equal(x0, pb.sample(3)[0]) and not np.array_equal(x0, pb.sample(4)[0])
    assert np.array_equal(x0[1:], np.zeros(3)) and np.array_equal(goal[1:], np.zeros(3))
    assert abs(x0[0]) <= 0.5 and abs(goal[0]) <= 0.5
    ocp = pb.ocp(knots=3)
    assert ocp.nx == 4 and np.array_equal(ocp.u_max, [20.0]) and np.array_equal(ocp.u_min, [-20.0])


def test_the_benchmarks_tell_the_tutorials_cart_pole_by_its_spec_not_its_name():
    # the tutorial's cart-pole (θ = 0 upright) is flipped to start hanging; the shipped one (θ = 0 hanging) must not be
    from ocpkit.benchmarks.nlp import example_cartpole, is_example_cartpole

    assert not is_example_cartpole("cartpole")
    example = example_cartpole()  # None from an installed package: no examples/ beside it
    assert example is None or is_example_cartpole(example)
