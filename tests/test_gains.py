"""Issue 46, item 3: Solution.gains, the first input's feedback gain K = ∂u₀/∂x₀ of the solved QP, against central
finite differences of u₀ over x₀ (the same QP re-solved cold from x₀ ± h e_i, its affine model held fixed)."""

import numpy as np
import pytest

from ocpkit.problems import make
from ocpkit.qp.certificate import active
from ocpkit.solvers.qp import LinearMPC
from ocpkit.solvers.rti import RealTimeIteration

H = 1e-4  # the QP is piecewise affine in x₀: central differences are exact while the active set holds


def _spied(ctrl):
    """Record each QP build of ``ctrl`` (the transcription, its arguments, the QP) in ``ctrl.builds``."""
    ctrl.builds = []
    for tr in {id(t): t for t in (*ctrl._transcriptions, ctrl.transcription)}.values():

        def build(*args, _tr=tr, _build=tr.build, **kwargs):
            qp = _build(*args, **kwargs)
            ctrl.builds.append((_tr, _build, args, qp))
            return qp

        tr.build = build
    return ctrl


def _finite_differences(ctrl):
    """∂u₀/∂x₀ by central differences: the last solved QP rebuilt from x₀ ± h e_i with its model, solved cold."""
    tr, build, (Ad, Bd, wd, x0, goal), _ = ctrl.builds[-1]
    phi0 = ctrl.ocp.parameterization.basis[0]
    K = np.empty((ctrl.ocp.nu, x0.size))
    for i in range(x0.size):
        u = []
        for sign in (1.0, -1.0):
            res = ctrl._backend.solve(build(Ad, Bd, wd, x0 + sign * H * np.eye(x0.size)[i], goal), None, None)
            assert res.status == "success", res.raw_status
            u.append(phi0 @ tr.knots(res.z))
        K[:, i] = (u[0] - u[1]) / (2 * H)
    return K


def _check(ctrl, x, goal, steps=2):
    for _ in range(steps):  # the second step linearizes along a plan (trajectory, RTI)
        sol = ctrl.solve(x, goal)
        assert sol.applied, sol.raw_status  # a success, or "soft": the QP's answer, its plan checked on the model
    assert sol.gains.shape == (ctrl.ocp.nu, ctrl.ocp.nx)
    K = _finite_differences(ctrl)
    np.testing.assert_allclose(sol.gains, K, rtol=0, atol=1e-6 * np.abs(K).max())
    return sol


def _nlink(**overrides):
    return make("nlink:2").ocp(horizon=20, knots=5, **overrides)


X, GOAL = np.array([0.1, -0.2, 0.3, 0.0]), np.array([1.0, 1.0, 0.0, 0.0])


@pytest.mark.parametrize("form", ["condensed", "sparse"])
@pytest.mark.parametrize("linearization", ["goal", "trajectory"])
def test_gains_are_the_finite_differences_and_zero_at_an_active_input_bound(form, linearization):
    """p = 5 < T = 20 knots; the goal far enough that u₀'s first component is at its bound: its row of K is 0."""
    ctrl = _spied(LinearMPC(_nlink(), form=form, linearization=linearization, gains=True, native=False))
    sol = _check(ctrl, X, GOAL)
    at_bound = np.isclose(np.abs(sol.u), ctrl.ocp.u_max)
    assert at_bound.any() and not at_bound.all(), sol.u
    assert np.all(sol.gains[at_bound] == 0.0)
    assert np.abs(sol.gains[~at_bound]).max() > 1e-3


@pytest.mark.parametrize("form", ["condensed", "sparse"])
def test_gains_with_an_active_state_bound(form):
    """A joint rate bound the plan runs along: state-bound rows in the active set, K still the differences."""
    ocp = _nlink(x_min=np.array([-np.inf, -np.inf, -0.4, -0.4]), x_max=np.array([np.inf, np.inf, 0.4, 0.4]))
    ctrl = _spied(LinearMPC(ocp, form=form, gains=True, native=False))
    _check(ctrl, X, GOAL)
    tr, _, (*_, x0, _), qp = ctrl.builds[-1]
    res = ctrl._backend.solve(qp, None, None)
    upper, lower = active(qp, res.z, res.w)
    boxes = 0 if qp.box is None else len(qp.box)
    state_rows = (upper | lower)[boxes:] if form == "condensed" else (upper | lower)[tr.u_rows.size :][: tr.x_rows.size]
    assert state_rows.any()


@pytest.mark.parametrize("form", ["condensed", "sparse"])
def test_rti_gains_are_the_finite_differences(form):
    ctrl = _spied(RealTimeIteration(_nlink(), form=form, gains=True, native=False))
    _check(ctrl, X, GOAL, steps=3)


def test_gains_only_on_request_and_not_on_a_fallback():
    ocp = _nlink()
    assert LinearMPC(ocp, native=False).solve(X, GOAL).gains is None
    ctrl = LinearMPC(ocp, gains=True, native=False)
    assert ctrl.gains and "gains" in ctrl._no_native_step()
    assert ctrl.solve(np.full(4, 1e9), GOAL).gains is None  # beyond the state limit: the fallback
    with pytest.raises(TypeError, match="gains"):
        LinearMPC(ocp, gains=1)
