"""Why an exported C step is not a success (issue 45, items 3 and 5): the reason codes the C step sets
(``mpc_last_reason``, named by ``mpc_reason_string``) reach ``Solution.reason`` through ExportedMPC, equal to the
Python step's reason for the same step; a step LinearMPC's C step hands to Python says so in its ``path``."""

from __future__ import annotations

import ctypes
import shutil
from dataclasses import replace

import numpy as np
import pytest

from ocpkit.export import ExportedMPC, build, export
from ocpkit.problems import make
from ocpkit.solvers.qp import LinearMPC
from ocpkit.status import SUCCESS, Reason

pytestmark = pytest.mark.skipif(shutil.which("cc") is None or shutil.which("make") is None, reason="needs cc and make")


@pytest.fixture(scope="module")
def bounded_pendulum(tmp_path_factory):
    """Pendulum with |q̇| ≤ 6, linearized about the plan, solved by DAQP (as tests/test_export.py's)."""
    problem = make("pendulum")
    ocp = problem.ocp(knots=5, horizon=50, x_min=[-np.inf, -6.0], x_max=[np.inf, 6.0])
    out = export(ocp, tmp_path_factory.mktemp("pend_daqp"), qp="daqp", linearization="plan")
    build(out.out_dir)
    with ExportedMPC(ocp, out.out_dir) as c:
        yield problem, ocp, c


def _last_reason(c: ExportedMPC) -> str:
    """The library's own words for its last reason (``mpc_reason_string(mpc_last_reason(mem))``)."""
    words = c._lib.mpc_reason_string
    words.restype = ctypes.c_char_p
    return words(c._lib.mpc_last_reason(c._mem)).decode()


@pytest.mark.parametrize("qp", ["daqp", "qrqp"])
def test_a_c_step_at_its_iteration_limit_says_why_as_the_python_step_does(bounded_pendulum, qp, tmp_path):
    """An iteration limit of 1: the C step's reason (mpc_last_reason, its code mapped by ExportedMPC) is the iteration
    limit, as LinearMPC's Python step says for the same step (DAQP at max_iter 1; qrqp has no Python twin)."""
    problem, ocp, _ = bounded_pendulum
    out = export(ocp, tmp_path, qp=qp, linearization="plan", max_iter=1)
    build(out.out_dir)
    x, goal = problem.sample(0)
    with ExportedMPC(ocp, out.out_dir) as c:
        sol = c.solve(x, goal)
        assert (sol.status, sol.reason, _last_reason(c)) == ("limited", Reason.ITERATION_LIMIT, "iteration limit")
    ref = LinearMPC(ocp, max_iter=1, linearization="plan", state_bounds="hard", native=False).solve(x, goal)
    assert (ref.status, ref.reason) == (sol.status, sol.reason), ref.raw_status


def test_an_infeasible_c_step_says_why_as_the_python_step_does(bounded_pendulum):
    """From q̇ = 9, past the bound 6: the C step's hard QP is infeasible, and it says so (QP infeasible) as the Python
    step with hard state bounds does; a success after it says no reason."""
    problem, ocp, c = bounded_pendulum
    ref = LinearMPC(ocp, linearization="plan", state_bounds="hard", native=False)
    goal = np.array([1.0, 0.0])
    for ctrl in (c, ref):
        ctrl.reset()
        assert ctrl.solve([0.0, 0.0], goal).reason is None
    a, b = c.solve([0.0, 9.0], goal), ref.solve([0.0, 9.0], goal)
    assert (a.status, a.reason, _last_reason(c)) == ("infeasible", Reason.QP_INFEASIBLE, "QP infeasible")
    assert (b.status, b.reason) == (a.status, a.reason), b.raw_status
    assert c.solve([0.0, 0.0], goal).ok and _last_reason(c) == "none"


def _crossed(qp):
    """The first knot's box bounds crossed: 1 <= z_0 <= -1."""
    lo, hi = qp.l.copy(), qp.u.copy()
    lo[0], hi[0] = 1.0, -1.0
    return replace(qp, l=lo, u=hi)


# A QP the C step and the Python step refuse before a solve, by the reason each should give.
REFUSED = {
    Reason.BOUNDS_CROSSED: _crossed,
    Reason.QP_DATA: lambda qp: replace(qp, q=np.r_[np.nan, qp.q[1:]]),
    Reason.ILL_CONDITIONED: lambda qp: replace(qp, P=qp.P * 1e20),
}  # its curvature unchanged


@pytest.mark.parametrize("reason", REFUSED, ids=str)
def test_a_refused_c_qp_says_why_as_the_python_step_does(bounded_pendulum, reason):
    """The C step's QP checks (mpc_solve_qp) refuse crossed bounds, non-finite data and an ill-conditioned Hessian
    for the reason the Python step refuses the same QP for."""
    _, ocp, c = bounded_pendulum
    py = LinearMPC(ocp, linearization="plan", state_bounds="hard", native=False)
    x, goal = np.array([0.0, 0.5]), np.array([1.0, 0.0])
    bad = REFUSED[reason](py.transcription.build(*py.affine_model(x, goal, "plan"), x, goal))
    status, _ = c.solve_qp(bad)
    assert status != SUCCESS and _last_reason(c) == reason, (status, _last_reason(c))
    py.transcription.build = lambda *args, **kwargs: bad
    sol = py.solve(x, goal)
    assert sol.status == status and sol.reason is reason, (sol.status, sol.reason, sol.raw_status)
    c.reset()


def test_a_c_step_answered_in_python_says_so_in_its_path(bounded_pendulum):
    """LinearMPC's C step hands a step its hard QP cannot answer (q̇ = 9, past the bound 6) to the soft QP in Python:
    that step's path says so (SOFTENED_AFTER_C), the C step's own answers say "C step"."""
    from ocpkit.solvers.qp import SOFTENED_AFTER_C

    _, ocp, _ = bounded_pendulum
    ctrl = LinearMPC(ocp, linearization="plan", native=True)
    goal = np.array([1.0, 0.0])
    assert ctrl.solve([0.0, 0.0], goal).path == "C step"
    sol = ctrl.solve([0.0, 9.0], goal)
    assert sol.applied and sol.path == SOFTENED_AFTER_C, (sol.status, sol.path, sol.raw_status)
