"""References over the horizon (ocpkit.model.reference) and how a step takes them: goal windows, moving obstacles and
a user's plan, checked and refused by name."""

import numpy as np
import pytest

from ocpkit import problems
from ocpkit.model.reference import ObstaclePath, Reference
from ocpkit.model.task import reach
from ocpkit.sim.metrics import cost_by_term
from ocpkit.sim.simulate import Trajectory

N3 = problems.make("nlink:3")


def test_a_reference_from_samples_is_linear_between_them_and_held_beyond():
    ref = Reference([0.0, 1.0, 3.0], [[0.0, 10.0], [1.0, 10.0], [1.0, 30.0]])
    np.testing.assert_allclose(ref.at(0.5), [0.5, 10.0])
    np.testing.assert_allclose(ref.at(2.0), [1.0, 20.0])
    np.testing.assert_allclose(ref.at(-1.0), [0.0, 10.0])
    np.testing.assert_allclose(ref.at(9.0), [1.0, 30.0])
    window = ref.window(0.5, 0.25, 4)  # t = 0.5, 0.75, 1.0, 1.25, 1.5
    np.testing.assert_allclose(window[:, 0], [0.5, 0.75, 1.0, 1.0, 1.0])
    np.testing.assert_allclose(window[:, 1], [10.0, 10.0, 10.0, 12.5, 15.0])
    fn = Reference.from_function(lambda t: [np.sin(t), t], 2)
    np.testing.assert_allclose(fn.window(0.0, 0.1, 2), [[0, 0], [np.sin(0.1), 0.1], [np.sin(0.2), 0.2]])
    with pytest.raises(ValueError, match="times must increase"):
        Reference([0.0, 0.0], np.zeros((2, 2)))


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
def test_a_reference_file_names_its_columns_as_the_goal(tmp_path, suffix):
    ocp = reach(N3, [], knots=5, horizon=10)
    names = ocp.goal_names()
    assert names[:6] == ocp.model.state_names and names[6:] == ["position[0]", "position[1]", "position[2]"]
    t = np.array([0.0, 1.0])
    columns = {"t": t, names[0]: np.array([0.0, 1.0]), "position[1]": np.array([0.2, 0.4])}
    path = tmp_path / f"ref{suffix}"
    if suffix == ".csv":
        np.savetxt(path, np.column_stack(list(columns.values())), delimiter=",", header=",".join(columns), comments="")
    else:
        np.savez(path, **columns)
    ref = Reference.load(path, ocp)
    expected = np.zeros(ocp.ng)
    expected[0], expected[7] = 0.5, 0.3
    np.testing.assert_allclose(ref.at(0.5), expected)
    bad = tmp_path / "bad.csv"
    bad.write_text("t,elbow_typo\n0,1\n")
    with pytest.raises(ValueError, match="unknown column.*elbow_typo"):
        Reference.load(bad, ocp)


def test_an_obstacle_path_predicts_at_constant_velocity():
    path = ObstaclePath(lambda t: [[0.1 * t, 0.0, 0.5, 0.05]])
    window = path.window(1.0, 0.5, 3)
    np.testing.assert_allclose(window[:, 0, 0], [0.1, 0.15, 0.2, 0.25])
    np.testing.assert_allclose(window[:, 0, 3], 0.05)
    held = ObstaclePath(lambda t: [[0.1 * t, 0.0, 0.5, 0.05]], predict=False).window(1.0, 0.5, 3)
    np.testing.assert_allclose(held[:, 0, 0], 0.1)
    given = ObstaclePath(lambda t: [[0.0, 0.0, 0.5, 0.05]], lambda t: [[0.0, 2.0, 0.0]]).window(0.0, 0.5, 1)
    np.testing.assert_allclose(given[1, 0, :3], [0.0, 1.0, 0.5])


def test_windows_obstacles_and_guesses_are_checked_naming_the_argument():
    ocp = reach(N3, ["0.3,0.3,0,0.05"], knots=4, horizon=8)
    T, ng = ocp.horizon, ocp.ng
    assert ocp.goal_window(np.zeros(ng)).shape == (T + 1, ng)
    with pytest.raises(ValueError, match=r"goal must have shape \(9, 9\)"):
        ocp.goal_window(np.zeros((T, ng)))
    declared = ocp.obstacle_window()
    np.testing.assert_allclose(declared[3, 0], [0.3, 0.3, 0.0, 0.05])
    assert ocp.obstacle_window([[0.1, 0.2, 0.0, 0.1]]).shape == (T + 1, 1, 4)
    with pytest.raises(ValueError, match="obstacles: radii must be > 0"):
        ocp.obstacle_window([[0.1, 0.2, 0.0, -0.1]])
    with pytest.raises(ValueError, match="declares no obstacles"):
        reach(N3, [], knots=4, horizon=8).obstacle_window([[0.1, 0.2, 0.0, 0.1]])
    U = np.arange(12.0).reshape(4, 3)
    np.testing.assert_allclose(ocp.guess_knots(U), U)
    np.testing.assert_allclose(ocp.guess_knots(ocp.parameterization.inputs(U)), U, atol=1e-12)
    with pytest.raises(ValueError, match=r"initial_guess must be knots \(4, 3\) or inputs over the horizon \(8, 3\)"):
        ocp.guess_knots(np.zeros((5, 3)))


def test_a_controller_refuses_what_it_does_not_take_naming_it():
    from ocpkit.controller import Controller

    class Held(Controller):
        def _solve(self, x, goal):  # pragma: no cover - never reached
            raise AssertionError

    ocp = reach(N3, ["0.3,0.3,0,0.05"], knots=4, horizon=8)
    ctrl = Held(ocp)
    window = np.tile(ocp.goal(position=[0.2, 0.3, 0.0]), (ocp.horizon + 1, 1))
    window[-1, -3] = 0.25
    with pytest.raises(ValueError, match="Held does not take a moving goal window"):
        ctrl.solve(np.zeros(ocp.nx), window)
    with pytest.raises(ValueError, match="Held does not take a moving obstacles"):
        ctrl.solve(np.zeros(ocp.nx), window[0], obstacles=[[0.1, 0.2, 0.0, 0.1]])
    with pytest.raises(ValueError, match="Held does not take a moving initial guess"):
        ctrl.solve(np.zeros(ocp.nx), window[0], initial_guess=np.zeros((4, 3)))


def test_the_actual_cost_follows_the_reference_at_each_time():
    ocp = N3.ocp(knots=5)
    rng = np.random.default_rng(4)
    H = 5
    x, u = rng.normal(size=(H + 1, ocp.nx)), rng.normal(size=(H, ocp.nu))
    reference = rng.normal(size=(H + 1, ocp.nx))
    moving = Trajectory(t=np.arange(H + 1) * ocp.dt, x=x, u=u, goal=reference[-1], reference=reference)
    expected = sum((x[i] - reference[i]) @ ocp.Q @ (x[i] - reference[i]) for i in range(H + 1))
    assert cost_by_term(moving, ocp)["state"] == pytest.approx(expected, rel=1e-13)


def test_a_reference_without_preview_holds_its_present_value():
    ref = Reference([0.0, 1.0], [[0.0], [1.0]])
    held = ref.without_preview()
    np.testing.assert_allclose(held.window(0.5, 0.25, 3), 0.5)
    np.testing.assert_allclose(ref.window(0.5, 0.25, 2).ravel(), [0.5, 0.75, 1.0])


def test_tracking_tutorial_runs_as_written(capsys):
    """The tutorial "Track a moving reference" (examples/tracking.py): its printed claims hold (preview beats the held
    goal; the gain's feedback at 1 kHz beats holding u₀ under the disturbance)."""
    import re

    from conftest import run_example

    run_example("tracking.py")
    errors = [float(v) for v in re.findall(r"RMS error ([0-9.]+) rad", capsys.readouterr().out)]
    preview, held, hold_u0, feedback = errors
    assert preview < 0.2 * held and feedback < hold_u0, errors
