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
    FORCE_FRACTION,
    LIMIT_GAP,
    ROBOTS,
    SEED_OFFSET,
    START_ANGLE,
    START_CART,
    START_SPEED,
    SWING_ROBOTS,
    SWINGUP,
    TORQUE_FRACTION,
    TRACK,
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


@pytest.mark.parametrize("robot", [r for r in SWING_ROBOTS if r != "cartpole"])
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
        rng = np.random.default_rng(0)  # the draw as it was before the cart-pole joined: the same stream
        assert np.array_equal(a["x0"], [rng.uniform(-START_ANGLE, START_ANGLE), rng.uniform(-START_SPEED, START_SPEED)])
    assert a["limits"] is None and a["angles"].all()
    with pytest.raises(ValueError, match="robot"):
        case("nlink:3", SWINGUP, 0)


def test_cartpole_swingup_starts_hanging_on_its_track_and_no_single_stroke_lifts_it():
    pb = problems.make("cartpole")
    a, again, other = case("cartpole", SWINGUP, 0), case("cartpole", SWINGUP, 1), case("cartpole", SWINGUP, 1)
    assert np.array_equal(again["x0"], other["x0"]) and not np.array_equal(a["x0"], other["x0"])
    for s in (case("cartpole", SWINGUP, seed) for seed in range(5)):
        assert abs(s["x0"][0]) <= START_CART and abs(s["x0"][1]) <= START_ANGLE  # cart near 0, pole hanging
        assert (np.abs(s["x0"][2:]) <= START_SPEED).all()
    assert np.array_equal(a["x_goal"], [0.0, np.pi, 0.0, 0.0]) and a["angles"].tolist() == [False, True]
    assert a["limits"][0].tolist() == [-TRACK, -np.inf] and a["limits"][1].tolist() == [TRACK, np.inf]
    lift = 2 * pb.m * pb.g * pb.l  # hanging at rest to upright at rest
    force = a["tau_max"]
    assert force == pytest.approx(FORCE_FRACTION * lift / (TRACK + START_CART))

    def energy(p_dot, theta, theta_dot):  # above hanging at rest
        kinetic = (pb.M + pb.m) * p_dot**2 / 2 + pb.m * pb.l * np.cos(theta) * p_dot * theta_dot
        return kinetic + pb.m * pb.l**2 * theta_dot**2 / 2 + pb.m * pb.g * pb.l * (1 - np.cos(theta))

    corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T * [
        START_SPEED,
        START_ANGLE,
        START_SPEED,
    ]
    most = max(energy(*c) for c in corners)
    # the force's work over the longest one-way stroke the track allows (from -START_CART to +TRACK) is less than
    # the lift less the most energy a start brings: no single stroke gets the pole up; the controller must pump
    assert force * (TRACK + START_CART) < lift - most
    ocp = nonconvex_trials.task_ocp("cartpole", a, 300)
    assert ocp.u_max.tolist() == [force] and ocp.u_min.tolist() == [-force]
    assert ocp.x_min.tolist() == [-TRACK, -np.inf, -np.inf, -np.inf] and ocp.x_max[0] == TRACK
    assert ocp.parameterization.knots == nonconvex_trials.SWING_KNOTS


def test_swing_errors_wrap_angles():
    x_goal = np.array([np.pi, 0.0, 0.0, 0.0])
    x = np.array([[-np.pi, 2 * np.pi, 0.0, 0.0], [np.pi + 0.1, -0.2, 0.3, -0.4], [0.0, 0.0, 0.0, 0.0]])
    angle, speed = nonconvex_trials.swing_errors(x, x_goal)
    assert np.allclose(angle, [0.0, 0.2, np.pi]) and np.allclose(speed, [0.0, 0.4, 0.0])
    # the cart-pole: the pole's angle wraps, the cart's position (metres) does not
    x_goal, angles = np.array([0.0, np.pi, 0.0, 0.0]), np.array([False, True])
    x = np.array([[2 * np.pi, -np.pi, 0.0, 0.0], [0.05, 3 * np.pi + 0.02, -0.3, 0.1]])
    angle, speed = nonconvex_trials.swing_errors(x, x_goal, angles)
    assert np.allclose(angle, [2 * np.pi, 0.05]) and np.allclose(speed, [0.0, 0.3])


def test_cartpole_swing_verdict_on_synthetic_trajectories():
    """Upright over the last 0.2 s with the cart within 0.1 m of the centre and on its track at every state."""
    from types import SimpleNamespace

    drawn = case("cartpole", SWINGUP, 0)
    t = np.arange(0, 1.0 + 1e-9, 0.01)

    def verdict(p, theta=np.pi, p_dot=0.0, u=1.0):
        x = np.column_stack([np.broadcast_to(p, t.shape), np.full(t.shape, theta), np.full(t.shape, p_dot), 0 * t])
        return nonconvex_trials._swung(SimpleNamespace(t=t, x=x, u=np.full((t.size - 1, 1), u)), None, drawn)

    assert verdict(0.05)["success"] and verdict(-0.09)["success"]
    assert not verdict(0.15)["reached"]  # upright, but the cart 0.15 m off the centre
    assert not verdict(2 * np.pi)["reached"]  # a cart 2π m away is not wrapped onto the centre
    assert verdict(0.0, theta=-np.pi)["success"]  # the pole's angle is
    assert not verdict(0.0, p_dot=0.6)["reached"]  # the cart at 0.6 m/s
    off = np.where(t < 0.5, TRACK + 0.05, 0.0)  # upright at the end, but off the track's end earlier
    r = verdict(off)
    assert r["reached"] and not r["success"] and r["beyond_limit"] == pytest.approx(0.05)
    assert not verdict(0.0, u=drawn["tau_max"] * 1.01)["success"]  # beyond the force limit


def test_swingup_trial_runs_within_its_torque_limit():
    r = nonconvex_trials.trial("pendulum", SWINGUP, nonconvex_trials.RTI, 10, 0.05, 32, "cpu", 0.01, 0)
    assert r["case_seed"] == SEED_OFFSET and r["steps"] == 5 and not r["success"] and r["verdict"] == "not upright"
    assert r["torque_max"] <= r["tau_max"] and r["collision_steps"] == 0 and np.isfinite(r["actual_cost"])
    assert r["final_angle_error"] > 2.5  # still hanging after 0.05 s


def test_cartpole_swingup_trial_runs_on_its_track():
    r = nonconvex_trials.trial("cartpole", SWINGUP, nonconvex_trials.RTI, 10, 0.05, 32, "cpu", 0.01, 0)
    assert r["steps"] == 5 and not r["success"] and r["verdict"] == "not upright" and np.isfinite(r["actual_cost"])
    assert r["torque_max"] <= r["tau_max"] and r["beyond_limit"] == 0.0 and r["final_angle_error"] > 2.5


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


def test_ablation_rows_change_one_choice_of_empc_each_and_get_their_own_table(monkeypatch, tmp_path):
    """Issue 49's ablation: each row is EMPC's default with one option changed, at the full size only; the report
    pairs EMPC against them in their own table, not among the baselines."""
    t = nonconvex_trials
    default = t.CONTROLLERS[t.EMPC][1]
    changed = {name: {k: v for k, v in opts.items() if default.get(k) != v} for name, (_, opts) in t.ABLATION.items()}
    assert changed == {
        t.EMPC_PAPER: {"variant": "paper"},
        t.EMPC_NONLINEAR: {"dynamics": "nonlinear"},
        t.EMPC_GENERATIONS: {"generations": 3},
    }
    assert all(solver == "empc" for solver, _ in t.ABLATION.values())
    assert not set(t.ABLATION) & set(nonconvex.SIZES["quick"]["controllers"])
    assert set(t.ABLATION) <= set(nonconvex.SIZES["full"]["controllers"])
    df, _ = _tiny(monkeypatch, tmp_path, ("sphere",), [t.EMPC, t.RTI, t.EMPC_PAPER, t.EMPC_GENERATIONS])
    text = nonconvex.report(df, tmp_path)
    baselines, ablation = text.split("EMPC against each controller")[1].split("What each of EMPC's choices")
    assert "EMPC · RTI" in baselines and f"EMPC · {t.EMPC_PAPER}" not in baselines
    assert f"EMPC · {t.EMPC_PAPER}" in ablation and f"EMPC · {t.EMPC_GENERATIONS}" in ablation
    assert "EMPC · RTI" not in ablation
    # EMPC and its ablation alone (no baseline): the report has the ablation table and no empty baseline table
    alone = nonconvex.report(df[df["controller"] != t.RTI], tmp_path)
    assert "What each of EMPC's choices" in alone and "EMPC against each controller" not in alone


@pytest.mark.slow
def test_nonconvex_tiny_every_controller_and_case(monkeypatch, tmp_path):
    _tiny(monkeypatch, tmp_path, CASES, list(nonconvex_trials.CONTROLLERS))
