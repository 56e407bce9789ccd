"""Preconditioned CEM near the input bounds (issue 46): a draw that leaves them is shortened along its ray, not clipped,
so the elite mean keeps a bound the plan holds; MPPI's draws are still clipped. On the arch of `pytest --arch`."""

import numpy as np
import pytest

from ocpkit import problems
from ocpkit.solvers.cem import CrossEntropyMPC
from ocpkit.solvers.mppi import MPPI

pytestmark = pytest.mark.usefixtures("taichi_arch")

N3 = problems.make("nlink:3")


def _drawn(cls):
    """(mean, draws G ε, candidates) of one population drawn around a plan holding joint 1's torque at its lower
    bound (where the tracking reference's plan sits), after a step that set the preconditioner."""
    ocp = N3.ocp(knots=3, horizon=20)
    ctrl = cls(ocp, population=64, seed=0)
    x0, goal = N3.sample(0)
    ctrl.solve(x0, goal)
    mean = ctrl.preconditioner.newton.copy()
    mean[:, 0] = ocp.u_min[0]
    ctrl.std = np.full(ocp.knots * ocp.nu, ctrl.sigma)
    ctrl._sample(mean)
    first = 1 + 2  # the mean, then the seeds
    draws = ctrl._eps.to_numpy()[first:] @ (ctrl.preconditioner.whiten * ctrl.std).T
    return ocp, mean.ravel(), draws, ctrl.engine.knots.to_numpy()[first:].reshape(len(draws), -1)


def test_a_cem_draw_leaving_the_bounds_is_shortened_along_its_ray():
    ocp, mean, draws, candidates = _drawn(CrossEntropyMPC)
    lo, hi = np.tile(ocp.u_min, ocp.knots), np.tile(ocp.u_max, ocp.knots)
    assert (candidates >= lo - 1e-12).all() and (candidates <= hi + 1e-12).all()
    share = np.einsum("ij,ij->i", candidates - mean, draws) / np.einsum("ij,ij->i", draws, draws)
    np.testing.assert_allclose(candidates, mean + share[:, None] * draws, rtol=0, atol=1e-9)
    assert (share >= 0).all() and (share <= 1 + 1e-12).all()
    outside = ((mean + draws < lo) | (mean + draws > hi)).any(axis=1)
    assert outside.sum() >= len(draws) // 4  # the bound is active: many draws leave it
    np.testing.assert_allclose(share[~outside], 1.0, rtol=0, atol=1e-12)
    assert (share[outside] < 1).all()


def test_mppi_draws_are_still_clipped():
    ocp, mean, draws, candidates = _drawn(MPPI)
    lo, hi = np.tile(ocp.u_min, ocp.knots), np.tile(ocp.u_max, ocp.knots)
    np.testing.assert_allclose(candidates, np.clip(mean + draws, lo, hi), rtol=0, atol=1e-12)
