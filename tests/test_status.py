"""Statuses and failure reasons (issue 45, item 3): an enum whose members are the old strings, and decisions that
read a step's ``reason``, never the words of its raw status."""

import json
import pickle

import numpy as np
import pytest

from ocpkit import problems
from ocpkit.export.library import c_reason
from ocpkit.qp.quadratic_program import QP
from ocpkit.solvers.qp import LinearMPC
from ocpkit.status import INFEASIBLE, NAN, REASONS, SOFT, STATUSES, SUCCESS, Reason, Refusal, Solution, Status

PENDULUM = problems.make("pendulum")
X0, GOAL = PENDULUM.sample(0)


def test_statuses_are_their_strings():
    assert STATUSES == ("success", "limited", "infeasible", "nan", "exception", "soft")  # C codes index this order
    assert SUCCESS == "success" and Status("soft") is SOFT and "nan" == NAN
    assert {"success": 1}[SUCCESS] == 1 and SOFT in {"soft"} and f"{INFEASIBLE} step" == "infeasible step"
    assert json.dumps({"status": NAN, "reason": Reason.TIME_BUDGET}) == '{"status": "nan", "reason": "time budget"}'
    sol = Solution(u=np.zeros(1), knots=np.zeros((1, 1)), status="success")  # a stored string still reads as a status
    assert sol.ok and sol.reason is None and json.loads(json.dumps(sol.to_dict()))["reason"] is None


def test_refusal_is_its_text_with_a_reason():
    why = Refusal("lower bound above upper bound in 1 constraint rows", Reason.BOUNDS_CROSSED)
    assert "above" in why and why.reason is Reason.BOUNDS_CROSSED
    again = pickle.loads(pickle.dumps(why))
    assert again == why and again.reason is Reason.BOUNDS_CROSSED


@pytest.mark.parametrize("reason, status", [(Reason.QP_DATA, NAN), (Reason.BOUNDS_CROSSED, INFEASIBLE)])
def test_a_refused_qp_is_classified_by_its_reason_not_its_words(monkeypatch, reason, status):
    # the words say "above" either way; only the reason says the bounds crossed
    monkeypatch.setattr(QP, "check", lambda self: Refusal("a row above its bound", reason))
    sol = LinearMPC(PENDULUM.ocp(knots=3), native=False).solve(X0, GOAL)
    assert (sol.status, sol.reason, sol.fallback, sol.raw_status) == (status, reason, True, "a row above its bound")


def test_only_an_ill_conditioned_reason_adds_the_diagnosis():
    ctrl = LinearMPC(PENDULUM.ocp(knots=3), native=False)
    ctrl.solve(X0, GOAL)
    words = ctrl._fail(NAN, "a QP called ill-conditioned", {}, reason=Reason.QP_DATA)
    assert words.raw_status == "a QP called ill-conditioned" and words.reason is Reason.QP_DATA
    said = ctrl._fail(NAN, "refused", {}, reason=Reason.ILL_CONDITIONED)
    assert said.raw_status.startswith("refused (|eig A_d| = ") and said.reason is Reason.ILL_CONDITIONED


def test_reasons_of_the_controller_and_the_c_step():
    ctrl = LinearMPC(PENDULUM.ocp(knots=3), native=False)
    assert ctrl.solve([1e20, 0.0], GOAL).reason is Reason.STATE_BEYOND_LIMIT
    ok = ctrl.solve(X0, GOAL)
    assert ok.ok and ok.reason is None
    assert c_reason(0) is None and [c_reason(1 + REASONS.index(r)) for r in Reason] == list(Reason)  # C's codes


def test_the_nonlinear_and_sampling_controllers_say_why():
    """NonlinearMPC stopped at its iteration limit says so in Solution.reason; a sampling planner whose budget
    cannot pay for a generation says time budget; an IPOPT return status maps to its reason."""
    from ocpkit import solvers
    from ocpkit.solvers.nlp import _FAILED, _REASON

    pendulum = problems.make("pendulum")
    ocp = pendulum.ocp(knots=3)
    x, goal = pendulum.sample(0)
    sol = solvers.make("ipopt", ocp, max_iter=1).solve(x, goal)
    assert sol.status == "limited" and sol.reason is Reason.ITERATION_LIMIT, (sol.status, sol.reason, sol.raw_status)
    assert _REASON["Maximum_WallTime_Exceeded"] is Reason.TIME_BUDGET and set(_FAILED) >= {"limited", "nan"}
    empc = solvers.make("empc", ocp, arch="cpu", population=64)
    empc.warm_up(x, goal)
    empc.time_limit = 1e-9
    sol = empc.solve(x, goal)
    assert sol.status == "limited" and sol.reason is Reason.TIME_BUDGET, (sol.status, sol.reason, sol.raw_status)
