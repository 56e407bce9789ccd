"""The non-convex suite: its cases, its paired statistics against known values, IPOPT multi-start, and the study end
to end on a tiny grid."""

import math

import numpy as np
import pandas as pd
import pytest

from ocpkit import problems
from ocpkit.runs import study as runner
from ocpkit.studies import NAMES, get, nonconvex, nonconvex_report, nonconvex_trials
from ocpkit.studies.evidence import HELD, INCONCLUSIVE, NOT_HELD, median_interval
from ocpkit.studies.nonconvex_cases import (
    CASES,
    LIMIT_GAP,
    ROBOTS,
    SEED_OFFSET,
    START_ANGLE,
    START_SPEED,
    SWING_ROBOTS,
    SWINGUP,
    TORQUE_FRACTION,
    case,
    joint_limits,
    static_torque,
)
from ocpkit.studies.nonconvex_multistart import MultiStartNLP
from ocpkit.studies.nonconvex_stats import binomial_cdf_half, mcnemar_exact, paired_interval, paired_success
from ocpkit.studies.reach_trials import MARGIN, clearances


@pytest.mark.parametrize("robot", ROBOTS)
def test_cases_block_the_straight_path(robot):
    pb = problems.make(robot)
    n = pb.kinematics.n
    for kind in CASES:
        for seed in range(2):  # development draws: the study's are SEED_OFFSET + s
            s = case(robot, kind, seed)
            again = case(robot, kind, seed)
            assert np.array_equal(s["x0"], again["x0"]) and s["obstacles"] == again["obstacles"]  # deterministic
            q = np.vstack([s["x0"][:n], s["q_target"]])
            assert clearances(pb, s["obstacles"], q).min() >= MARGIN  # start and target clear of every sphere
            p0, pg = pb.kinematics.positions(pb.end_effector, q)
            assert np.allclose(pg, s["target"])
            t = np.linspace(0, 1, 201)[:, None]
            path = p0 + t * (pg - p0)
            # the end effector's sphere moving along the straight segment hits some sphere
            depth = min(np.linalg.norm(path - o.center, axis=1).min() - o.radius for o in s["obstacles"])
            assert depth < pb.link_radius, (kind, seed)
            assert len(s["obstacles"]) == {"sphere": 1, "spheres": 3, "passage": 2, "limits": 1}[kind]
            if kind == "limits":
                lo, hi = s["limits"]
                assert ((lo <= s["x0"][:n]) & (s["x0"][:n] <= hi)).all()
                assert np.isclose(np.minimum(s["q_target"] - lo, hi - s["q_target"]).min(), LIMIT_GAP)
            else:
                assert s["limits"] is None
    assert joint_limits(robot, pb)[0].shape == (n,)


@pytest.mark.parametrize("robot", SWING_ROBOTS)
def test_swingup_draws_from_its_seed_and_blocks_a_quasi_static_path(robot):
    pb = problems.make(robot)
    n = pb.model().nx // 2
    a, again, other = case(robot, SWINGUP, 0), case(robot, SWINGUP, 0), case(robot, SWINGUP, 1)
    assert np.array_equal(a["x0"], again["x0"]) and not np.array_equal(a["x0"], other["x0"])
    assert (np.abs(a["x0"][:n]) <= START_ANGLE).all() and (np.abs(a["x0"][n:]) <= START_SPEED).all()  # hanging
    assert np.array_equal(a["x_goal"], np.r_[np.pi, np.zeros(2 * n - 1)])  # upright, at rest
    horizontal = static_torque(pb, np.r_[np.pi / 2, np.zeros(n - 1)])
    assert abs(horizontal[0]) > a["tau_max"] == pytest.approx(TORQUE_FRACTION * abs(horizontal[0]))
    assert TORQUE_FRACTION < 2 / np.pi  # nor one push: τ·π < the 2 m g l a pendulum's top takes
    ocp = nonconvex_trials.task_ocp(robot, a, 300)
    assert np.array_equal(ocp.u_max, np.full(n, a["tau_max"])) and np.array_equal(ocp.u_min, -ocp.u_max)
    assert ocp.parameterization.knots == nonconvex_trials.SWING_KNOTS
    if robot == "pendulum":
        assert horizontal[0] == pytest.approx(pb.m * pb.g * pb.l)
    with pytest.raises(ValueError, match="robot"):
        case("nlink:3", SWINGUP, 0)


def test_swing_errors_wrap_angles():
    x_goal = np.array([np.pi, 0.0, 0.0, 0.0])
    x = np.array([[-np.pi, 2 * np.pi, 0.0, 0.0], [np.pi + 0.1, -0.2, 0.3, -0.4], [0.0, 0.0, 0.0, 0.0]])
    angle, speed = nonconvex_trials.swing_errors(x, x_goal)
    assert np.allclose(angle, [0.0, 0.2, np.pi]) and np.allclose(speed, [0.0, 0.4, 0.0])


def test_swingup_trial_runs_within_its_torque_limit():
    r = nonconvex_trials.trial("pendulum", SWINGUP, nonconvex_trials.RTI, 10, 0.05, 32, "cpu", 0.01, 0)
    assert r["case_seed"] == SEED_OFFSET and r["steps"] == 5 and not r["success"] and r["verdict"] == "not upright"
    assert r["torque_max"] <= r["tau_max"] and r["collision_steps"] == 0 and np.isfinite(r["actual_cost"])
    assert r["final_angle_error"] > 2.5  # still hanging after 0.05 s


def test_bspline_rows_run_the_same_controller_on_a_cubic_bspline_of_as_many_knots():
    drawn = case("nlink:3", "sphere", 0)
    for name, plain in ((nonconvex_trials.LTV_BSPLINE, nonconvex_trials.LTV), (nonconvex_trials.EMPC_BSPLINE, "EMPC")):
        assert nonconvex_trials.CONTROLLERS[name] == nonconvex_trials.CONTROLLERS[plain]
        spline = nonconvex_trials.task_ocp("nlink:3", drawn, 10, nonconvex_trials.basis(name)).parameterization
        linear = nonconvex_trials.task_ocp("nlink:3", drawn, 10, nonconvex_trials.basis(plain)).parameterization
        assert (spline.kind, linear.kind) == ("bspline", "linear") and spline.knots == linear.knots
    assert not set(nonconvex_trials.BSPLINE) & set(nonconvex.SIZES["quick"]["controllers"])  # full size only
    r = nonconvex_trials.trial("nlink:3", "sphere", nonconvex_trials.LTV_BSPLINE, 10, 0.05, 32, "cpu", 0.01, 0)
    assert r["steps"] == 5 and r["successes"] == 5


def test_mcnemar_exact_against_known_values():
    assert binomial_cdf_half(0, 5) == 1 / 32 and binomial_cdf_half(2, 10) == 56 / 1024
    assert mcnemar_exact(5, 0) == 2 / 32  # the smallest p with five discordant pairs
    assert mcnemar_exact(10, 2) == pytest.approx(2 * (1 + 12 + 66) / 4096)
    assert mcnemar_exact(1, 1) == 1.0 and mcnemar_exact(0, 0) == 1.0 and mcnemar_exact(3, 4) == 1.0
    scipy = pytest.importorskip("scipy.stats")
    for b, c in ((7, 1), (0, 6), (12, 5), (20, 20), (3, 9)):
        assert mcnemar_exact(b, c) == pytest.approx(scipy.binomtest(b, b + c, 0.5).pvalue, rel=1e-12)
    with pytest.raises(ValueError):
        mcnemar_exact(-1, 2)


def test_paired_success_and_its_verdict():
    keys = pd.Index(range(12), name="seed")
    a = pd.Series([True] * 10 + [False, True], index=keys)
    b = pd.Series([False] * 9 + [True, True, True], index=keys)
    s = paired_success(a, b.iloc[1:])  # only the keys both have: 11
    assert (s.n, s.both, s.a_only, s.b_only, s.neither) == (11, 2, 8, 1, 0)
    assert s.p == pytest.approx(2 * (1 + 9) / 512) and s.share == pytest.approx(8 / 9)
    assert s.low > 0.5 and s.verdict() == HELD  # 8 of 9 discordant: Clopper–Pearson low 0.518
    assert paired_success(a[:3], b[:3]).verdict() == INCONCLUSIVE  # 3 of 3: low 0.29
    assert paired_success(b, b).verdict() == INCONCLUSIVE  # no discordant seed: no evidence either way
    assert math.isnan(paired_success(b, b).share)
    never, always = pd.Series([False] * 6), pd.Series([True] * 6)
    assert paired_success(never, always).verdict() == NOT_HELD  # B only on 6 of 6 discordant: high 0.46 < ½
    assert paired_success(never[:5], always[:5]).verdict() == INCONCLUSIVE  # 5 of 5: high 0.52


def test_paired_interval_is_the_median_interval_of_the_ratios():
    keys = pd.Index(range(9))
    a = pd.Series(np.arange(1.0, 10.0), index=keys)
    b = pd.Series(np.full(9, 2.0), index=keys)
    got = paired_interval(a, b.iloc[:8])
    want = median_interval(np.arange(1.0, 9.0) / 2)
    assert (got.value, got.low, got.high, got.n) == (want.value, want.low, want.high, 8)
    assert paired_interval(a, b, "difference").value == 3.0


def test_multistart_keeps_the_least_objective_of_its_starts():
    pb = problems.make("nlink:2")
    ocp = pb.ocp(knots=3, horizon=10)
    x0, goal = pb.sample(3)
    one = MultiStartNLP(ocp, starts=1).solve(x0, goal)
    plain = nonconvex_trials.solvers.make("ipopt", ocp).solve(x0, goal)
    assert np.array_equal(one.u, plain.u)  # one start: NonlinearMPC's cold start
    many = MultiStartNLP(ocp, starts=4, seed=1)
    sol = many.solve(x0, goal)
    assert sol.ok and many.starts_run == 4 and "best of 4 starts" in sol.raw_status
    again = MultiStartNLP(ocp, starts=4, seed=1).solve(x0, goal)
    assert np.array_equal(sol.u, again.u)  # seeded guesses: repeatable
    assert sol.raw_status.endswith(f"objective {np.nanmin(many.objectives):.6g}")
    many.solve(x0, goal)  # warm: one start
    assert many.starts_run == 4 and many.steps_run == 1
    stuck = MultiStartNLP(ocp, starts=3, max_iter=1)  # one iteration: no start converges
    assert not stuck.solve(x0, goal).ok and stuck.starts_run == 3
    assert not stuck.solve(x0, goal).ok and stuck.starts_run == 3  # then one start a step until one converges
    stuck.max_iter = 200
    assert stuck.solve(x0, goal).ok and stuck.starts_run == 3
    assert stuck.solve(x0, goal).ok and stuck.starts_run == 3  # warm
    every = MultiStartNLP(ocp, starts=2, every_step=True)
    every.solve(x0, goal), every.solve(x0, goal)
    assert every.starts_run == 4


def test_multistart_picks_the_least_objective_beyond_rounding(monkeypatch):
    """Starts whose objectives are 5, 3, 4 and 3 (1e-9 less): the second start's answer is kept."""
    from ocpkit.studies import nonconvex_multistart

    fake = iter([5.0, 3.0, 4.0, 3.0 - 1e-9])

    class Faked(nonconvex_multistart._Recording):
        def __call__(self, **args):
            res = self.solver(**args)
            self.f = next(fake)
            return res

    monkeypatch.setattr(nonconvex_multistart, "_Recording", Faked)
    pb = problems.make("nlink:2")
    ctrl = MultiStartNLP(pb.ocp(knots=3, horizon=10), starts=4)
    sol = ctrl.solve(*pb.sample(3))
    assert ctrl.objectives == [5.0, 3.0, 4.0, 3.0 - 1e-9] and "start 1, objective 3" in sol.raw_status
    assert ctrl.random_win_rate == 1.0


TINY = {
    "seeds": {"nlink:3": 1},
    "duration": 0.05,
    "horizon": 10,
    "population": 32,
    "arch": "cpu",
    "budget": 0.01,
    "swingup": {"seeds": {}, "horizon": 10, "duration": 0.05},
}


def _tiny(monkeypatch, tmp_path, cases, controllers):
    assert "nonconvex" in NAMES and get("nonconvex") is nonconvex
    monkeypatch.setitem(nonconvex.SIZES, "quick", {**TINY, "controllers": list(controllers)})
    monkeypatch.setattr(nonconvex, "CASES", cases)
    df = runner.run(nonconvex.study("quick"), tmp_path, workers=1, progress=False)
    assert (df["status"] == "ok").all(), df["error"].dropna().tolist()
    seeds = sum(TINY["seeds"].values()) * len(cases) + sum(TINY["swingup"]["seeds"].values())
    assert len(df) == seeds * len(controllers)
    # 0.05 s is too short to get there: nobody succeeds, nobody collides, every metric is recorded
    assert not df["success"].any() and (df["collision_steps"] == 0).all() and (df["steps"] == 5).all()
    assert (df["step_max"] >= df["step_median"]).all() and (df["case_seed"] == SEED_OFFSET).all()
    text = nonconvex.report(df, tmp_path)
    for piece in ("Per controller over every robot", "EMPC against each controller", "not used in development"):
        assert piece in text, piece
    claims = text.split("Claim checks:")[1].strip().splitlines()[2:]
    verdicts = [row.rsplit("|", 2)[-2].strip() for row in claims]
    assert len(verdicts) == 2 and set(verdicts) <= {"held", "not held", "inconclusive", "not tested"}
    return df, verdicts


def test_nonconvex_tiny(monkeypatch, tmp_path):
    """The fast twin: the limits case, EMPC and RTI at the default and at the budget."""
    names = [nonconvex_trials.EMPC, nonconvex_trials.RTI]
    names += [name + nonconvex_trials.BUDGET for name in names]
    df, verdicts = _tiny(monkeypatch, tmp_path, ("limits",), names)
    # no seed where one succeeds and the other misses; on a busy machine a budgeted run may not fit a single search
    # (see below): then EMPC at the budget has no baseline left, or is left out itself
    blind = nonconvex_report.no_search(df).any()
    assert verdicts[0] == "inconclusive" and verdicts[1] == ("not tested" if blind else "inconclusive")
    assert df.loc[df["controller"] == nonconvex_trials.EMPC, "child_win_rate"].notna().all()
    # a budgeted controller whose every step was a fallback ran no search: listed apart, in no success table or test
    rti = nonconvex_trials.RTI + nonconvex_trials.BUDGET
    df = df.assign(fallbacks=0)  # a synthetic table: every run searched
    blind = df.copy()
    rows = blind["controller"] == rti
    blind.loc[rows, "fallbacks"] = blind.loc[rows, "steps"]
    blind.loc[rows, "first_fallback"] = "time budget: 9.8 ms left, an IPOPT iteration measured at 23 ms"
    assert nonconvex_report.no_search(blind).tolist() == rows.tolist()
    rti_default = blind["controller"] == nonconvex_trials.RTI
    blind.loc[rti_default, "fallbacks"] = blind.loc[rti_default, "steps"]  # a default controller: no rule
    assert nonconvex_report.no_search(blind).tolist() == rows.tolist()
    text = nonconvex.report(blind, tmp_path)
    cannot, rest = text.split("Cannot run at this budget")[1].split("Per controller over every robot")
    assert f"| {rti} |" in cannot and "measured at 23 ms" in cannot and "nlink:3 · limits" in cannot
    assert f"| {rti} |" not in rest and f"{nonconvex_trials.EMPC + nonconvex_trials.BUDGET} · {rti}" not in rest
    assert "Cannot run at this budget" not in nonconvex.report(df, tmp_path)


def test_nonconvex_tiny_swingup(monkeypatch, tmp_path):
    """The swing-up in the study's grid and report (its own horizon and duration)."""
    monkeypatch.setitem(TINY, "seeds", {})  # no reaches
    monkeypatch.setitem(TINY, "swingup", {"seeds": {"pendulum": 1}, "horizon": 12, "duration": 0.05})
    df, _ = _tiny(monkeypatch, tmp_path, CASES, [nonconvex_trials.RTI, nonconvex_trials.EMPC])
    assert set(df["robot"]) == {"pendulum"} and set(df["case"]) == {SWINGUP} and (df["horizon"] == 12).all()
    text = nonconvex.report(df, tmp_path)
    assert "pendulum · swingup · RTI" in text and "swing-up: horizon 12" in text


@pytest.mark.slow
def test_nonconvex_tiny_every_controller_and_case(monkeypatch, tmp_path):
    _tiny(monkeypatch, tmp_path, CASES, list(nonconvex_trials.CONTROLLERS))
