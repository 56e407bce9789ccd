"""MuJoCo as the plant: the same closed loops as ocpkit's own plant, MuJoCo's extra effects, clear errors."""

import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mujoco")

from ocpkit.cli import main  # noqa: E402
from ocpkit.sim.mujoco_plant import MuJoCoPlant, _mujoco  # noqa: E402
from ocpkit.problems import make  # noqa: E402
from ocpkit.problems.nlink import NLink  # noqa: E402
from ocpkit.sim.simulate import simulate  # noqa: E402
from ocpkit.solvers.qp import LinearMPC  # noqa: E402

# The paper's 2-link robot written by hand from its description (1 kg, 0.25 m uniform rods, b = 0.01 N·m·s, joints
# about z), not from ocpkit's Chain: its own joint names and a position servo that MuJoCoPlant replaces by torques.
# A thin rod has no moment about its own axis, which MuJoCo refuses; 1e-12 there is never excited (every joint
# turns about z).
ROD = 'mass="1" pos="0.125 0 0" diaginertia="1e-12 0.00520833333333333333 0.00520833333333333333"'
NLINK2 = f"""<mujoco model="two links">
  <worldbody>
    <body name="upper">
      <joint name="shoulder" type="hinge" axis="0 0 1" damping="0.01"/>
      <inertial {ROD}/>
      <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.02"/>
      <body name="fore" pos="0.25 0 0">
        <joint name="elbow" type="hinge" axis="0 0 1" damping="0.01"/>
        <inertial {ROD}/>
        <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.02"/>
      </body>
    </body>
  </worldbody>
  <actuator><position joint="shoulder" kp="50"/><position joint="elbow" kp="50"/></actuator>
</mujoco>
"""


def closed_loops(problem, plant, seed=0, duration=1.0):
    """ocpkit's plant and ``plant`` under the same LinearMPC from the same seeded start and goal."""
    x0, goal = problem.sample(seed)
    ctrl = LinearMPC(problem.ocp())
    return simulate(problem.plant(), ctrl, x0, goal, duration), simulate(plant, ctrl, x0, goal, duration)


@pytest.mark.parametrize("spec", ["nlink:3", "puma560", "panda"])
def test_closed_loop_matches_ocpkit_plant(spec):
    """1 s of LinearMPC: MuJoCo's RK4 at ocpkit's sub-step tracks ocpkit's plant to 1e-8 (no friction, no contacts):
    an MJCF generated from the Chain (nlink:3, the Puma 560) and MuJoCo's own import of the Panda's URDF.

    The closed loop feeds each plant's round-off back through the controller: the Panda's ill-conditioned QP turns
    a 1e-14 state difference into 4e-8 N·m at the first step (3.7e-6 from seed 4, whose closed loops then differ by
    5e-7). Replaying one run's inputs into MuJoCo open loop separates the plants from the controller."""
    problem = make(spec)
    mujoco_plant = MuJoCoPlant(problem)
    ours, theirs = closed_loops(problem, mujoco_plant)
    assert np.abs(ours.x - theirs.x).max() < 1e-8
    assert np.abs(ours.u - theirs.u).max() < 1e-6  # the inputs the controller chose from those states
    assert np.abs(ours.x[-1] - ours.goal).max() < np.abs(ours.x[0] - ours.goal).max()  # it moved towards the goal
    step, x = mujoco_plant.stepper(problem.dt, 10), ours.x[0]
    replayed = [x := step(x, u) for u in ours.u]
    assert np.abs(np.array(replayed) - ours.x[1:]).max() < 1e-9


@pytest.mark.parametrize("spec", ["nlink:3", "puma560", "panda", "nlink:13"])
def test_one_step_matches_ocpkit_plant(spec):
    """One control period from seeded states and inputs: RK4 agrees to round-off; MuJoCo's implicit integrator
    (first order) to within its O(h) error."""
    problem = make(spec)
    plant, dt, n = problem.plant(), problem.dt, problem.plant().nu
    rk4 = MuJoCoPlant(problem).stepper(dt, 10)
    implicit = MuJoCoPlant(problem, integrator="implicitfast").stepper(dt, 10)
    rng = np.random.default_rng(0)
    for seed in range(3):
        x = problem.sample(seed)[0] + np.r_[np.zeros(n), rng.uniform(-1, 1, n)]
        u = rng.uniform(-1, 1, n)
        exact = np.asarray(plant.rk4(dt, 10)(x, u)).ravel()
        scale = np.abs(exact - x).max()
        assert np.abs(rk4(x, u) - exact).max() < 1e-11 * max(1.0, scale)
        assert np.abs(implicit(x, u) - exact).max() < 0.05 * scale


def test_users_mjcf_with_joint_map(tmp_path):
    """A hand-written MJCF of the 2-link robot, its joints mapped by name: the same closed loop as ocpkit's plant."""
    path = tmp_path / "two_links.xml"
    path.write_text(NLINK2)
    problem = make("nlink:2")
    plant = MuJoCoPlant(problem, mjcf=path, joint_map={"joint1": "shoulder", "joint2": "elbow"})
    assert plant.model.nu == 2 and plant.source == f"mjcf:{path}"  # the file's servos replaced by two motors
    ours, theirs = closed_loops(problem, plant)
    assert np.abs(ours.x - theirs.x).max() < 1e-8
    in_order = MuJoCoPlant(problem, mjcf=path, joint_map=["shoulder", "elbow"])
    x, u = np.array([0.3, -0.2, 0.1, 0.5]), np.array([0.4, -0.1])
    np.testing.assert_array_equal(in_order.stepper(0.01, 10)(x, u), plant.stepper(0.01, 10)(x, u))


def test_pendulum_with_an_mjcf(tmp_path):
    """The pendulum is an ODE, not a Chain: with an MJCF of it (a point mass 0.5 m below a hinge about y, so that
    gravity pulls it towards q = 0, as m g l sin q does) MuJoCo follows its plant under a varying input."""
    path = tmp_path / "pendulum.xml"
    path.write_text(
        '<mujoco><worldbody><body><joint name="swing" type="hinge" axis="0 1 0" damping="0.1"/>'
        '<inertial pos="0 0 -0.5" mass="1" diaginertia="1e-12 1e-12 1e-12"/></body></worldbody></mujoco>'
    )
    problem = make("pendulum")
    ours, theirs = problem.plant().rk4(0.01, 10), MuJoCoPlant(problem, mjcf=path, joint_map=["swing"]).stepper(0.01, 10)
    x = y = np.array([1.0, 0.0])
    for k in range(100):
        u = np.array([np.sin(k / 10)])
        x, y = np.asarray(ours(x, u)).ravel(), theirs(y, u)
    assert np.abs(x - y).max() < 1e-9 and np.abs(x).max() > 0.5


def test_effects_ocpkit_leaves_out():
    """Friction and armature slow the arm, ctrlrange clamps the torque, a floor stops a falling arm."""
    problem = make("puma560")
    dt, x0 = problem.dt, np.zeros(12)
    u = np.array([0.0, 40.0, 20.0, 0.0, 0.0, 0.0])

    def after(plant, steps=20, torque=u):
        step, x = plant.stepper(dt, 10), x0
        for _ in range(steps):
            x = step(x, torque)
        return x

    free = after(MuJoCoPlant(problem))
    for option in ({"frictionloss": 5.0}, {"armature": 2.0}):
        slowed = after(MuJoCoPlant(problem, **option))
        assert np.abs(slowed[7:9]).max() < 0.9 * np.abs(free[7:9]).max(), option
    clamped = MuJoCoPlant(problem, ctrlrange=(-10.0, 10.0))
    np.testing.assert_allclose(after(clamped), after(MuJoCoPlant(problem), torque=np.clip(u, -10, 10)), atol=1e-12)
    # No torque: the arm falls under gravity; a floor 0.3 m below the shoulder holds its links above it.
    lowest = {}
    for floor in (None, -0.3):
        plant = MuJoCoPlant(problem, floor=floor)
        x = after(plant, steps=100, torque=np.zeros(6))
        import mujoco

        data = mujoco.MjData(plant.model)
        data.qpos[:] = x[:6]
        mujoco.mj_kinematics(plant.model, data)
        capsules = plant.model.geom_type == mujoco.mjtGeom.mjGEOM_CAPSULE
        lowest[floor] = float((data.geom_xpos[capsules, 2] - plant.model.geom_size[capsules, 1]).min())
    assert lowest[None] < -0.5 and lowest[-0.3] > -0.3 - 2 * problem.link_radius


def test_generated_robot_must_match_the_problems_dynamics():
    class Heavier(NLink):  # its dynamics are not its Chain's: the MJCF written from the Chain would be wrong
        def dynamics(self, error):
            return super().dynamics(1.5 * error)

    with pytest.raises(ValueError, match="gives q̈ up to .* away from the problem's dynamics"):
        MuJoCoPlant(Heavier(2))


@pytest.mark.parametrize(
    "kwargs,error,message",
    [
        ({"integrator": "verlet"}, ValueError, "integrator must be one of"),
        ({"frictionloss": -1.0}, ValueError, "frictionloss must be a finite scalar or 2 values >= 0"),
        ({"armature": [1.0, 2.0, 3.0]}, ValueError, "armature must be a finite scalar or 2 values >= 0"),
        ({"ctrlrange": (1.0, -1.0)}, ValueError, "ctrlrange must have low < high"),
        ({"ctrlrange": 2.0}, ValueError, "ctrlrange must be \\(low, high\\)"),
        ({"floor": "low"}, TypeError, "floor must be a height in m"),
        ({"limits": "yes"}, TypeError, "limits must be True, False or None"),
        ({"joint_map": ["a", "b"]}, ValueError, "joint_map names the joints of an MJCF file: give mjcf= too"),
        ({"mjcf": "no_such.xml"}, ValueError, "mjcf: no such file 'no_such.xml'"),
    ],
)
def test_bad_options(kwargs, error, message):
    with pytest.raises(error, match=message):
        MuJoCoPlant("nlink:2", **kwargs)


def test_bad_joint_maps(tmp_path):
    path = tmp_path / "two_links.xml"
    path.write_text(NLINK2)
    for joint_map, message in (
        (None, "the MJCF has no joint 'joint1'; its joints: shoulder, elbow"),
        (["shoulder"], "joint_map must be 2 MJCF joint names"),
        ({"joint1": "shoulder", "wrist": "elbow"}, "joint_map names 'wrist'"),
        ({"joint1": "shoulder"}, "no MJCF joint for the problem's joint 'joint2'"),
        (["shoulder", "shoulder"], "names an MJCF joint twice"),
    ):
        with pytest.raises(ValueError, match=message):
            MuJoCoPlant("nlink:2", mjcf=path, joint_map=joint_map)
    path.write_text("<mujoco><worldbody><body></mujoco>")
    with pytest.raises(ValueError, match="is not an MJCF MuJoCo can read"):
        MuJoCoPlant("nlink:2", mjcf=path)


def test_unsupported_problems_and_plants():
    with pytest.raises(ValueError, match="'pendulum' has no rigid-body description .*mjcf="):
        MuJoCoPlant("pendulum")
    with pytest.raises(ValueError, match="'baxter' has a plant of its own"):
        MuJoCoPlant("baxter")
    problem = make("nlink:2")
    with pytest.raises(TypeError, match="plant must be an ocpkit Model or a plant with stepper"):
        simulate(object(), LinearMPC(problem.ocp()), *problem.sample(0), 0.1)


def test_missing_mujoco_is_one_clear_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "mujoco", None)
    with pytest.raises(ImportError, match=r'^MuJoCoPlant needs MuJoCo: pip install "ocpkit\[mujoco\]"$'):
        _mujoco()


def test_cli_simulate_on_mujoco(tmp_path, capsys):
    args = ["simulate", "nlink:2", "--duration", "0.2", "--out", str(tmp_path / "f.png"), "--json"]
    assert main(args) == 0
    ours = json.loads(capsys.readouterr().out)
    assert main(args + ["--plant", "mujoco"]) == 0
    theirs = json.loads(capsys.readouterr().out)
    assert ours["plant"] == "ocpkit" and theirs["plant"].startswith("MuJoCoPlant('nlink:2', source='chain'")
    assert abs(ours["actual_cost"] - theirs["actual_cost"]) < 1e-8 * ours["actual_cost"]
    path = tmp_path / "two_links.xml"
    path.write_text(NLINK2)
    assert main(args + ["--plant", "mujoco", "--mjcf", str(path), "--joint-map", "joint1=shoulder,joint2=elbow"]) == 0
    mapped = json.loads(capsys.readouterr().out)
    assert abs(mapped["actual_cost"] - ours["actual_cost"]) < 1e-8 * ours["actual_cost"]


@pytest.mark.parametrize(
    "extra,message",
    [
        (["--mjcf", "x.xml"], "--mjcf applies to --plant mujoco only"),
        (["--frictionloss", "0.5"], "--frictionloss applies to --plant mujoco only"),
        (["--mujoco-integrator", "implicit"], "--mujoco-integrator applies to --plant mujoco only"),
        (["--plant", "mujoco", "--armature", "-1"], "armature must be a finite scalar"),
        (["--plant", "mujoco", "--joint-map", "a,b"], "--joint-map names the joints of an MJCF file: give --mjcf too"),
        (["--plant", "mujoco", "--mjcf", "x.xml", "--joint-map", "joint1=a,b"], "--joint-map must be MJCF joint names"),
        (["--plant", "mujoco"], "'pendulum' has no rigid-body description"),
    ],
)
def test_cli_plant_errors_are_one_line(extra, message, tmp_path, capsys):
    problem = "pendulum" if extra == ["--plant", "mujoco"] else "nlink:2"
    assert main(["simulate", problem, "--duration", "0.1", "--out", str(tmp_path / "f.png"), *extra]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def test_cli_mujoco_options_reach_the_plant(tmp_path, capsys):
    """simulate's MuJoCo options are MuJoCoPlant's, with its defaults: the same run as the Python API gives."""
    from ocpkit import cli
    from ocpkit.sim.mujoco_plant import INTEGRATORS, MuJoCoPlant
    from ocpkit.problems import make
    from ocpkit.sim.simulate import simulate
    from ocpkit.solvers.qp import LinearMPC
    from ocpkit.sim.metrics import actual_cost

    assert cli.MUJOCO_INTEGRATORS == INTEGRATORS
    options = {"frictionloss": 0.5, "armature": 0.01, "floor": -1.0, "integrator": "implicit"}
    assert (
        main(
            [
                "simulate",
                "nlink:2",
                "--duration",
                "0.2",
                "--out",
                str(tmp_path / "f.png"),
                "--json",
                "--plant",
                "mujoco",
                "--frictionloss",
                "0.5",
                "--armature",
                "0.01",
                "--floor",
                "-1",
                "--mujoco-integrator",
                "implicit",
            ]
        )
        == 0
    )
    run = json.loads(capsys.readouterr().out)
    problem = make("nlink:2")
    plant = MuJoCoPlant(problem, **options)
    assert run["plant"] == repr(plant)
    ctrl = LinearMPC(problem.ocp(knots=5))
    x0, goal = problem.sample(0)
    traj = simulate(plant, ctrl, x0, goal, 0.2)
    assert abs(run["actual_cost"] / actual_cost(traj, ctrl.ocp) - 1) < 1e-8


# --- the robustness study's MuJoCo variant (studies/robustness.py) and its place in reproduce ---------------------


def test_mujoco_trial_records_its_plant():
    from ocpkit.studies.robustness import mujoco_trial

    common = {"problem": "nlink:2", "controller": "LinearMPC", "duration": 0.5, "arch": "cpu", "seed": 0}
    base = mujoco_trial(plant="ocpkit", mismatch="none", level=0.0, **common)
    same = mujoco_trial(plant="mujoco", mismatch="none", level=0.0, **common)
    rubbing = mujoco_trial(plant="mujoco", mismatch="friction", level=0.2, **common)
    assert base["plant_model"].startswith("Model('nlink:2'")
    assert same["plant_model"] == "MuJoCoPlant('nlink:2', source='chain', integrator='rk4')"
    assert rubbing["plant_model"].endswith(", frictionloss)")
    assert abs(same["actual_cost"] / base["actual_cost"] - 1) < 1e-8  # MuJoCo's copy of ocpkit's plant
    assert abs(rubbing["actual_cost"] / base["actual_cost"] - 1) > 1e-3  # friction the model does not know
    with pytest.raises(ValueError, match="mismatch 'friction' needs plant 'mujoco'"):
        mujoco_trial(plant="ocpkit", mismatch="friction", level=0.2, **common)
    with pytest.raises(ValueError, match="mismatch must be one of"):
        mujoco_trial(plant="mujoco", mismatch="backlash", level=0.2, **common)


def test_mujoco_study_grid_and_a_problem_it_cannot_simulate():
    from ocpkit.studies import robustness

    study = robustness.study("quick", plant="mujoco")
    assert study.name == "robustness_mujoco"
    conditions = {(t["plant"], t["mismatch"]) for t in study.trials}
    assert conditions == {("ocpkit", "none"), ("mujoco", "none"), ("mujoco", "friction"), ("mujoco", "armature")}
    assert {t["controller"] for t in study.trials} == {"LinearMPC", "RTI", "EMPC"}
    with pytest.raises(ValueError, match="'pendulum' has no rigid-body description"):
        robustness.study("quick", problems=["pendulum"], plant="mujoco")
    with pytest.raises(ValueError, match="plant must be one of"):
        robustness.study("quick", plant="gazebo")


def _mujoco_table(costs):
    """A robustness_mujoco table: ``costs[controller][condition]`` per-seed actual costs, the baseline 10 + seed."""
    import pandas as pd

    rows = []
    for controller, by_condition in costs.items():
        for (plant, mismatch, level), values in by_condition.items():
            rows += [
                {
                    "status": "ok",
                    "problem": "nlink:2",
                    "controller": controller,
                    "plant": plant,
                    "mismatch": mismatch,
                    "level": level,
                    "seed": s,
                    "actual_cost": v,
                    "final_error": 0.1,
                    "fallbacks": 0,
                    "fallback_causes": "",
                    "child_win_rate": float("nan"),
                    "load": 1.0,
                }
                for s, v in enumerate(values)
            ]
    return pd.DataFrame(rows)


def test_mujoco_report_names_the_controller_that_degrades_least(tmp_path):
    from ocpkit.studies.robustness import mujoco_report

    base = [10.0, 11.0, 12.0]
    costs = {
        c: {
            ("ocpkit", "none", 0.0): base,
            ("mujoco", "none", 0.0): base,
            ("mujoco", "friction", 0.1): [b * f for b in base],
        }
        for c, f in (("LinearMPC", 1.5), ("RTI", 1.2), ("EMPC", 1.5))
    }
    costs["EMPC"][("mujoco", "armature", 0.5)] = [b * 1.3 for b in base]
    costs["LinearMPC"][("mujoco", "armature", 0.5)] = [b * 1.3 * (1 + 1e-12) for b in base]  # a tie: round-off
    costs["RTI"][("mujoco", "armature", 0.5)] = [b * 1.4 for b in base]
    for c in costs:  # all three tied: none degrades least
        costs[c][("mujoco", "friction", 0.05)] = [b * 1.02 for b in base]
    text = mujoco_report(_mujoco_table(costs), tmp_path)
    rows = {
        row.split(" | ")[0].lstrip("| "): row.rsplit("|", 2)[-2].strip()
        for row in text.split("Claim checks:")[1].splitlines()
        if row.startswith("| nlink")
    }
    assert rows == {
        "nlink:2: MuJoCo without mismatch reproduces ocpkit's plant (issue 34)": "held",
        "nlink:2, MuJoCo, friction 0.1: RTI degrades least of LinearMPC, RTI, EMPC (issue 34)": "held",
        "nlink:2, MuJoCo, armature 0.5: LinearMPC and EMPC degrade least of LinearMPC, RTI, EMPC (issue 34)": "held",
        "nlink:2, MuJoCo, friction 0.05: one of LinearMPC, RTI, EMPC degrades least (issue 34)": "not held",
    }
    assert "LinearMPC / RTI: 1 [1, 1] (75 %, n = 3) (tied)" in text
    assert (tmp_path / "robustness_mujoco_nlink_2.png").stat().st_size > 5000


def test_reproduce_adds_the_mujoco_section_after_robustness(monkeypatch):
    import importlib.util

    from ocpkit.studies import reproduce

    assert reproduce._parts(("knots", "robustness")) == [
        ("knots", "knots", {}),
        ("robustness", "robustness", {}),
        ("robustness_mujoco", "robustness", {"plant": "mujoco"}),
    ]
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "mujoco" else real(name, *a))
    assert reproduce._parts(("robustness",))[-1] == ("robustness_mujoco", None, {"plant": "mujoco"})
    with pytest.raises(ValueError, match="plant 'mujoco' applies to the robustness study only, not 'knots'"):
        reproduce.run_study("knots", "quick", "unused", plant="mujoco")


def test_cli_study_plant_applies_to_robustness_only(tmp_path, capsys):
    assert main(["study", "knots", "--plant", "mujoco", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "--plant applies to the robustness study only, not 'knots'" in err and len(err.strip().splitlines()) == 1


def test_bench_model_prints_mujoco_beside_ocpkits_plant():
    from ocpkit.benchmarks.model import bench_model

    lines = []
    rows = bench_model(links=(2,), states=1, repeats=1, out=lines.append)
    assert [r["robot"] for r in rows] == ["nlink:2", "puma560", "baxter"]
    assert all(r["plant_s"] > 0 for r in rows) and rows[0]["mujoco_s"] > 0 and rows[1]["mujoco_s"] > 0
    assert np.isnan(rows[2]["mujoco_s"])  # the Baxter arm's plant is a sampled servo: no MuJoCo column
    assert "MuJoCo: 1 s simulated [ms]" in lines[-4] and lines[-1].split()[-2:] == ["–", "–"]


def test_joint_limits_and_divergence(tmp_path, monkeypatch):
    """limits=True holds a joint driven into its range's end (ranges in rad, as the Chain's); a diverging step
    raises instead of continuing from the state MuJoCo resets to."""
    monkeypatch.chdir(tmp_path)  # MuJoCo logs its warnings to MUJOCO_LOG.TXT in the working directory
    problem = make("puma560")
    high = problem.pin_model.upperPositionLimit[3]
    u = np.array([0.0, 0.0, 0.0, 20.0, 0.0, 0.0])
    for limits in (True, False):
        plant = MuJoCoPlant(problem, limits=limits)
        np.testing.assert_allclose(plant.model.jnt_range[3], [problem.pin_model.lowerPositionLimit[3], high])
        step, x = plant.stepper(problem.dt, 10), np.zeros(12)
        for _ in range(100):
            x = step(x, u)
        assert (x[3] < high + 0.05) if limits else (x[3] > high + 1.0)
    with pytest.raises(FloatingPointError, match=r"MuJoCo found a NaN, inf or huge value in u stepping from x = "):
        MuJoCoPlant("nlink:3").stepper(0.01, 10)(np.zeros(6), np.full(3, 1e20))


# --- continuous joints, meshes, a user's MJCF checked against the problem's dynamics (issue 44) -----------------

WHEEL_ARM = Path(__file__).parent / "data" / "wheel_arm.urdf"  # continuous "shoulder" (z) and "spin" (tilted)


@pytest.mark.parametrize("generated", [False, True])
def test_continuous_joints_are_hinges_without_range(generated):
    """MuJoCo's import of a URDF with continuous joints, and the MJCF written from its Chain: hinges without a range
    (limits=True bounds only the revolute and prismatic joints), one step equal to ocpkit's plant beyond ±π."""
    from ocpkit import Problem

    problem = Problem.from_urdf(WHEEL_ARM)
    if generated:
        problem.urdf = None  # the robot written from the Chain, not MuJoCo's URDF import
    plant = MuJoCoPlant(problem, limits=True)
    assert plant.source == ("chain" if generated else f"urdf:{WHEEL_ARM}")
    model = plant.model
    hinge, slide = (int(getattr(_mujoco().mjtJoint, k)) for k in ("mjJNT_HINGE", "mjJNT_SLIDE"))
    assert [int(t) for t in model.jnt_type] == [hinge, hinge, slide, hinge]
    assert model.jnt_limited.tolist() == [0, 1, 1, 0]
    np.testing.assert_allclose(model.jnt_range[1:3], [[-2, 2], [0, 0.1]])
    x, u = np.r_[3.5, 0.4, 0.05, -5.0, 1.0, -1.0, 0.2, 3.0], np.array([1.0, -2.0, 3.0, 0.5])
    exact = np.asarray(problem.plant().rk4(0.01, 10)(x, u)).ravel()
    assert np.abs(plant.stepper(0.01, 10)(x, u) - exact).max() < 1e-11


def _urdf_with_meshes(tmp_path, mesh_file="package://nowhere/upper.stl"):
    """The wheel arm with the meshes of a real robot's URDF that are not shipped: a visual mesh on the base, a visual
    and a collision mesh on the upper arm (beside a collision cylinder)."""
    text = WHEEL_ARM.read_text().replace(
        '<link name="base"/>',
        '<link name="base"><visual><geometry><mesh filename="package://nowhere/base.stl"/></geometry></visual></link>',
    )
    text = text.replace(
        '<link name="upper">',
        f'''<link name="upper">
    <visual><geometry><mesh filename="package://nowhere/upper.dae"/></geometry></visual>
    <collision><geometry><mesh filename="{mesh_file}" scale="0.001 0.001 0.001"/></geometry></collision>
    <collision><origin xyz="0 0 0.2"/><geometry><cylinder radius="0.04" length="0.3"/></geometry></collision>''',
    )
    path = tmp_path / "meshes.urdf"
    path.write_text(text)
    return path


def test_urdf_meshes_are_left_out_of_the_dynamics_plant(tmp_path):
    """A URDF naming meshes it does not ship (package://…, as most robot files do): the plant builds without them
    and steps as ocpkit's plant; meshes=True keeps them and refuses an unresolvable one in one line naming it."""
    from ocpkit import Problem

    problem = Problem.from_urdf(_urdf_with_meshes(tmp_path))
    plant = MuJoCoPlant(problem)
    assert plant.model.nmesh == 0 and mujoco_geom_types(plant.model).count("mjGEOM_CYLINDER") == 1
    x, u = np.r_[0.5, 0.4, 0.05, -1.0, 1.0, -1.0, 0.2, 3.0], np.array([1.0, -2.0, 3.0, 0.5])
    exact = np.asarray(problem.plant().rk4(0.01, 10)(x, u)).ravel()
    assert np.abs(plant.stepper(0.01, 10)(x, u) - exact).max() < 1e-11
    with pytest.raises(ValueError) as err:
        MuJoCoPlant(problem, meshes=True)
    assert "'package://nowhere/upper.stl'" in str(err.value) and "meshes=True" in str(err.value)
    assert len(str(err.value).splitlines()) == 1
    with pytest.raises(ValueError, match="meshes=True applies to a URDF robot"):
        MuJoCoPlant("nlink:2", meshes=True)


def test_urdf_meshes_kept_when_they_resolve(tmp_path):
    """meshes=True with a mesh file beside the URDF: MuJoCo loads it as a collision geometry."""
    from ocpkit import Problem

    (tmp_path / "upper.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    problem = Problem.from_urdf(_urdf_with_meshes(tmp_path, "upper.obj"))
    assert MuJoCoPlant(problem).model.nmesh == 0
    plant = MuJoCoPlant(problem, meshes=True)
    assert plant.model.nmesh == 1 and "mjGEOM_MESH" in mujoco_geom_types(plant.model)


def mujoco_geom_types(model):
    return [_mujoco().mjtGeom(int(t)).name for t in model.geom_type]


def _last(text, old, new):
    head, tail = text.rsplit(old, 1)
    return head + new + tail


@pytest.mark.parametrize(
    "edit,names",
    [
        (lambda t: _last(t, 'mass="1"', 'mass="10"'), "'elbow', body 'fore'"),  # 10× the forearm's mass
        (lambda t: t.replace('mass="1"', 'mass="10"', 1), "'shoulder', body 'upper'"),  # 10× the upper arm's
        (
            lambda t: t.replace('name="elbow" type="hinge" axis="0 0 1"', 'name="elbow" type="hinge" axis="0 0.4 1"'),
            "'elbow', body 'fore'",
        ),  # a tilted axis
        (
            lambda t: t.replace('name="elbow" type="hinge"', 'name="elbow" type="slide"'),
            "'elbow', body 'fore'",
        ),  # slide
    ],
)
def test_users_mjcf_must_match_the_problems_dynamics(tmp_path, edit, names):
    """An MJCF that is not the problem's robot is refused in one line saying by how much q̈ differs and naming the
    deepest joint (and its body) whose torque differs; a looser check_tolerance accepts it, None skips the check."""
    path = tmp_path / "edited.xml"
    path.write_text(edit(NLINK2))
    joint_map = {"joint1": "shoulder", "joint2": "elbow"}
    with pytest.raises(ValueError) as err:
        MuJoCoPlant("nlink:2", mjcf=path, joint_map=joint_map)
    message = str(err.value)
    assert len(message.splitlines()) == 1 and names in message and "check_tolerance=None" in message
    size = float(re.search(r"q̈ up to ([0-9.e+-]+) away", message).group(1))
    assert size > 0.1
    MuJoCoPlant("nlink:2", mjcf=path, joint_map=joint_map, check_tolerance=None)
    MuJoCoPlant("nlink:2", mjcf=path, joint_map=joint_map, check_tolerance=1e3)


def test_users_mjcf_check_ignores_its_constraints(tmp_path):
    """The unedited MJCF is accepted with its own joint ranges, dry friction and a floor its links touch: the check
    compares the smooth dynamics (masses, axes, joint types, damping, gravity), not MuJoCo's constraints."""
    path = tmp_path / "two_links.xml"
    text = NLINK2.replace('damping="0.01"/>', 'damping="0.01" range="-0.1 0.1" limited="true" frictionloss="5"/>')
    path.write_text(text.replace("<worldbody>", '<worldbody><geom type="plane" size="1 1 1" pos="0 0 0.01"/>'))
    plant = MuJoCoPlant("nlink:2", mjcf=path, joint_map=["shoulder", "elbow"])
    assert plant.model.jnt_limited.tolist() == [1, 1]
    with pytest.raises(ValueError, match="check_tolerance must be finite and > 0"):
        MuJoCoPlant("nlink:2", mjcf=path, joint_map=["shoulder", "elbow"], check_tolerance=0.0)
