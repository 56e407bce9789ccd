"""The reach study on a tiny grid (3-link arm and keep-out ball), its scenarios and its keep-out term."""

import numpy as np
import pytest

from ocpkit import problems
from ocpkit.runs import study as runner
from ocpkit.sim.simulate import MOVING, STALLED
from ocpkit.studies import NAMES, get, keepout, reach, reach_trials

TINY = {
    "seeds": {"nlink:3": 1, "baxter": 0, "panda": 0, reach.KEEPOUT: 1},
    "duration": {"nlink:3": 0.1, "baxter": 0.1, reach.KEEPOUT: 0.1},
    "horizon": {"nlink:3": 20, "baxter": 20, reach.KEEPOUT: 20},
    "population": 32,
    "arch": "cpu",
}


def test_reach_tiny(monkeypatch, tmp_path):
    assert "reach" in NAMES and get("reach") is reach
    monkeypatch.setitem(reach.SIZES, "quick", TINY)
    df = runner.run(reach.study("quick"), tmp_path, workers=1, progress=False)
    assert (df["status"] == "ok").all(), df["error"].dropna().tolist()
    assert len(df) == len(reach.CONTROLLERS) + len(reach.KEEPOUT_CONTROLLERS)
    arm = df[df["scenario"] == "nlink:3"]
    # 0.1 s is too short to get there: nobody succeeds, nobody collides, every metric is recorded.
    assert not arm["success"].any() and (arm["collision_steps"] == 0).all()
    assert (arm["final_distance"] > reach_trials.TOLERANCE).all() and (arm["min_clearance"] > 0).all()
    assert (arm["step_max"] >= arm["step_median"]).all() and (arm["actual_cost"] > 0).all()
    # steps by how they were answered, and the loop's verdict: 0.1 s is shorter than the 0.5 s window
    assert (arm["successes"] + arm["soft_steps"] + arm["fallbacks"] == arm["steps"]).all()
    assert (arm["steps"] == 10).all()
    assert (arm["verdict"] == MOVING).all() and (arm["success_while_colliding"] == 0).all()
    keep = df[df["scenario"] == reach.KEEPOUT]
    assert (keep["actual_cost"] >= keep["quadratic_cost"]).all()
    text = reach.report(df, tmp_path)
    for piece in (
        "Reach: per robot and controller",
        "EMPC vs the gradient methods",
        "Keep-out verdict, as measured",
        "IPOPT and RTI reach ≥ 90 %",
        "within 1.2× of IPOPT",
        "were not tuned on",
        "No controller reports success on a step whose actual next state collides",
    ):
        assert piece in text, piece
    claims = text.split("Claim checks:")[1].strip().splitlines()[2:]
    verdicts = [row.rsplit("|", 2)[-2].strip() for row in claims]
    assert len(verdicts) == 4 and set(verdicts) <= {"held", "not held", "inconclusive", "not tested"}
    assert "not tested" in verdicts  # IPOPT did not succeed: no cost ratio
    for stem in ("reach_success", "reach_step_time", "reach_paths_nlink3", "reach_keepout_cost"):
        assert (tmp_path / f"{stem}.png").stat().st_size > 5000
        assert (tmp_path / f"{stem}.pdf").exists()


@pytest.mark.parametrize("robot", reach.ROBOTS)
def test_scenarios_block_the_straight_path(robot):
    pb = problems.make(robot)
    n = pb.kinematics.n
    for seed in range(3):
        s = reach_trials.scenario(robot, seed)
        again = reach_trials.scenario(robot, seed)
        assert np.array_equal(s["x0"], again["x0"]) and s["obstacles"] == again["obstacles"]  # deterministic
        p0, pg = pb.kinematics.positions(pb.end_effector, np.vstack([s["x0"][:n], s["q_target"]]))
        assert np.allclose(pg, s["target"]) and np.linalg.norm(pg - p0) >= reach_trials.MIN_DISTANCE
        q_rows = np.vstack([s["x0"][:n], s["q_target"]])
        assert reach_trials.clearances(pb, s["obstacles"], q_rows).min() >= reach_trials.MARGIN
        (o,) = s["obstacles"]
        c = np.asarray(o.center)
        t = np.clip(np.dot(c - p0, pg - p0) / np.dot(pg - p0, pg - p0), 0, 1)
        # The end effector's sphere moving along the straight segment would hit the obstacle.
        assert np.linalg.norm(p0 + t * (pg - p0) - c) < o.radius + pb.link_radius
        if robot == "nlink:3":
            assert abs(c[2]) < 1e-12 and abs(s["target"][2]) < 1e-12


def test_squared_hinge_term_is_zero_outside_and_grows_inside():
    import casadi as ca

    term = reach_trials.squared_hinge_term([0.0, 0.0, 0.0])
    x, u = ca.SX.sym("x", 6), ca.SX.sym("u", 3)
    r, w, _ = term.expression(x, u, ca.SX(0, 1))
    f = ca.Function("r", [x], [r])
    assert float(f([1.0, 0, 0, 0, 0, 0])) == 0.0
    assert float(f([0.0] * 6)) == pytest.approx(keepout.RADIUS + 0.01, abs=1e-5)
    assert w[0] == reach_trials.HINGE_WEIGHT and term.terminal
    with pytest.raises(ValueError, match="controller must be one of"):
        reach.trial("keepout", "IPOPT", 20, 0.1, 32, "cpu", 0)


def test_report_counts_stalls_soft_steps_and_successes_while_colliding(tmp_path):
    """The reach table per controller from stored trials: a stalled run, a collision with successes while colliding,
    soft steps by cause; the claim that no success collides is not held."""
    import pandas as pd

    def row(controller, seed, **values):
        base = {
            "status": "ok",
            "scenario": "panda",
            "controller": controller,
            "seed": seed,
            "success": True,
            "verdict": "reached",
            "collision_steps": 0,
            "success_while_colliding": 0,
            "successes": 200,
            "soft_steps": 0,
            "soft_causes": "",
            "fallbacks": 0,
            "fallback_causes": "",
            "steps": 200,
            "min_clearance": 0.01,
            "final_distance": 0.001,
            "actual_cost": 100.0 + seed,
            "step_median": 0.01,
            "step_max": 0.02,
            "rejected": 0,
            "duration": 2.0,
            "horizon": 50,
            "population": 256,
            "device": "cpu",
            "child_win_rate": float("nan"),
            "load": 1.0,
        }
        return {**base, **values}

    rows = [row(reach_trials.IPOPT, s) for s in range(3)]
    rows += [
        row(reach_trials.RTI, 0),
        row(reach_trials.RTI, 1, success=False, verdict=STALLED, final_distance=0.05),
        row(
            reach_trials.RTI,
            2,
            success=False,
            verdict=MOVING,
            collision_steps=11,
            success_while_colliding=10,
            successes=187,
            soft_steps=3,
            soft_causes="clearance 2, state bound 1",
            fallbacks=10,
            fallback_causes="nan 10",
            min_clearance=-0.07,
            final_distance=0.18,
        ),
    ]
    text = reach.report(pd.DataFrame(rows), tmp_path)
    table = text.split("Reach: per robot and controller")[1]
    header = [c.strip() for c in table.splitlines()[2].strip("|").split("|")]
    lines = {
        cells[0]: dict(zip(header, cells))
        for cells in ([c.strip() for c in line.strip("|").split("|")] for line in table.splitlines()[4:6])
    }
    rti = lines[f"panda · {reach_trials.RTI}"]
    assert rti["success"] == "1/3" and rti["collided"] == "1" and rti["stalled (no collision)"] == "1"
    assert rti["colliding states"] == "11" and rti["success while colliding"] == "10" and rti["soft steps"] == "3"
    assert rti["soft causes"] == "clearance 2, state bound 1" and rti["fallbacks"] == "10"
    assert lines[f"panda · {reach_trials.IPOPT}"]["success while colliding"] == "0"
    claim = next(line for line in text.splitlines() if line.startswith("| No controller reports success"))
    assert f"{reach_trials.RTI} 10" in claim and claim.rstrip(" |").endswith("not held")
    assert "1 stalled short of the target without collision" in text
