"""LinearMPC's compiled C step (ocpkit.export.native): the same step as the Python one, its fallbacks, budget and
cache."""

import os
from pathlib import Path

import numpy as np
import pytest

from ocpkit import problems
from ocpkit.export import native
from ocpkit.status import LIMITED, SOFT, SUCCESS
from ocpkit.export import check_tools, export
from ocpkit.solvers.qp import LinearMPC

try:
    check_tools()
except Exception as exc:  # noqa: BLE001
    pytest.skip(f"no C toolchain: {exc}", allow_module_level=True)

PROBLEM = problems.make("nlink:2")


@pytest.fixture(scope="module")
def ocp():
    return PROBLEM.ocp(knots=4, horizon=40)


def _same_closed_loop(ocp, seed, steps, **options):
    """The C step and the Python step from the same states: the same status, u and knots every step."""
    c, py = LinearMPC(ocp, native=True, **options), LinearMPC(ocp, native=False, **options)
    assert c.native and not py.native
    x, goal = PROBLEM.sample(seed)
    F = ocp.discrete()
    for _ in range(steps):
        a, b = c.solve(x, goal), py.solve(x, goal)
        assert a.status == b.status == (SUCCESS if abs(x[2]) <= 2.0 else SOFT)  # past a bound: "soft"
        assert (a.path, b.path) == ("C step", "Python step")
        np.testing.assert_allclose(a.u, b.u, atol=1e-8)
        np.testing.assert_allclose(a.knots, b.knots, atol=1e-8)
        assert set(a.times) == {"model", "build", "solve", "total"} and a.times["total"] >= a.times["solve"] > 0
        x = np.asarray(F(x, a.u)).ravel()
    return goal


def test_c_step_equals_python_step_along_a_closed_loop(ocp):
    _same_closed_loop(ocp, seed=3, steps=60)


def test_c_step_linearized_about_the_plan_equals_python_step(ocp):
    _same_closed_loop(ocp, seed=4, steps=30, linearization="plan")


def test_controllers_of_one_ocp_share_one_build(ocp):
    a, b = LinearMPC(ocp, native=True), LinearMPC(ocp, native=True)
    assert a.native and b.native
    assert a._native is not b._native and a._native.out_dir == b._native.out_dir  # own memory, one library


def test_an_equal_ocp_finds_the_build_without_exporting_again(ocp, monkeypatch):
    """Every trial of a study builds its own OCP: an equal one (same digest) gets the C step of the first in this
    process without generating its code again; a different one (other weights) is exported."""
    LinearMPC(ocp, native=True)  # built (or found) and its key known
    exported = []
    monkeypatch.setattr(native, "export", lambda *a, **k: exported.append(1) or export(*a, **k))
    again = PROBLEM.ocp(knots=4, horizon=40)
    assert again is not ocp
    assert LinearMPC(again, native=True).native and exported == []
    other = PROBLEM.ocp(knots=4, horizon=40, R=2 * ocp.R)
    LinearMPC(other, native=True)
    assert exported == [1]


def test_configurations_without_a_c_step_say_why(ocp):
    for kwargs, why in (({"form": "sparse"}, "form 'sparse'"), ({"qp": "proxqp"}, "qp 'proxqp'")):
        with pytest.raises(ValueError, match=f"native=True.*{why}"):
            LinearMPC(ocp, native=True, **kwargs)
    with pytest.raises(TypeError, match="native"):
        LinearMPC(ocp, native="yes")


def test_soft_state_bounds_c_step_then_the_soft_qp_in_python():
    """Soft bounds (the default): the C step solves the hard QP; where that fails (a start past a bound) the soft
    QP is solved in Python — the Python step's answers throughout."""
    bounded = PROBLEM.ocp(knots=4, horizon=40, x_min=[-np.inf, -np.inf, -2.0, -2.0], x_max=[np.inf, np.inf, 2.0, 2.0])
    c, py = LinearMPC(bounded, native=True), LinearMPC(bounded, native=False)
    assert c.native
    goal = PROBLEM.sample(0)[1]
    for x in ([0.3, -0.2, 0.5, 0.0], [0.0, 0.0, 2.9, -2.5]):  # inside the bounds; past them (within 1.5x)
        a, b = c.solve(x, goal), py.solve(x, goal)
        assert a.status == b.status == (SUCCESS if abs(x[2]) <= 2.0 else SOFT)  # past a bound: "soft"
        np.testing.assert_allclose(a.u, b.u, atol=1e-8)
    assert b.x_pred is not None and np.abs(b.x_pred[1, 2:]).max() > 2.0  # the second start: the soft QP


def test_budget_too_small_for_the_c_step_gives_the_fallback(ocp):
    c = LinearMPC(ocp, native=True)
    x, goal = PROBLEM.sample(1)
    first = c.warm_up(x, goal)
    c.time_limit = 1e-9
    sol = c.solve(x, goal)
    assert sol.status == LIMITED and sol.fallback and "C step" in sol.raw_status and sol.path.startswith("fallback")
    np.testing.assert_allclose(sol.knots, np.clip(ocp.parameterization.shift(first.knots), ocp.u_min, ocp.u_max))


def test_changing_max_iter_returns_to_the_python_step(ocp):
    c = LinearMPC(ocp, native=True)
    c.max_iter = 50
    assert not c.native
    x, goal = PROBLEM.sample(2)
    assert c.solve(x, goal).status == SUCCESS


def test_damaged_cache_entry_is_rebuilt(ocp, tmp_path, monkeypatch):
    monkeypatch.setenv("OCPKIT_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(native, "_builds", {})
    fresh = PROBLEM.ocp(knots=4, horizon=40)
    folder = native.start(fresh, eps=1e-9, max_iter=1000, wait=True).result()
    library = folder / f"lib{native.NAME}.so"
    (folder / "damaged").write_bytes(b"not a library")  # a new file under the name: the loaded one stays mapped
    os.replace(folder / "damaged", library)
    monkeypatch.setattr(native, "_builds", {})
    with pytest.warns(RuntimeWarning, match="damaged cache entry"):
        again = native.start(PROBLEM.ocp(knots=4, horizon=40), eps=1e-9, max_iter=1000, wait=True).result()
    assert again == folder and library.read_bytes()[:4] == b"\x7fELF"


def test_without_a_compiler_the_python_step_runs_and_one_line_says_so(monkeypatch, tmp_path):
    import warnings

    monkeypatch.setenv("OCPKIT_CACHE_DIR", str(tmp_path))  # an empty cache (a cached C step needs no compiler)
    monkeypatch.setenv("CC", "no-such-cc")
    problem = problems.make("nlink:5")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ctrl = LinearMPC(problem.ocp(knots=3, horizon=20))
        x, goal = problem.sample(0)
        assert ctrl.solve(x, goal).status == SUCCESS and not ctrl.native
    messages = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert len(messages) == 1 and "no C compiler (`no-such-cc`)" in messages[0]


def test_two_threads_on_one_c_step_give_the_sequential_answers(ocp):
    import threading

    ctrl, ref = LinearMPC(ocp, native=True), LinearMPC(ocp, native=True)
    rng = np.random.default_rng(0)
    goal = PROBLEM.sample(0)[1]
    states = [rng.uniform(-1, 1, ocp.nx) for _ in range(80)]
    answers = {}

    def run(part):
        for i in part:
            answers[i] = ctrl.solve(states[i], goal)

    threads = [threading.Thread(target=run, args=(range(k, 80, 2),)) for k in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for i, x in enumerate(states):  # the goal-linearized C step does not depend on the previous step's plan
        expected = ref.solve(x, goal)
        assert answers[i].status == expected.status == SUCCESS
        np.testing.assert_allclose(answers[i].u, expected.u, atol=1e-10)


def test_goal_input_is_generated_into_the_c_step(ocp):
    """An input goal nonlinear in the goal (gravity compensation's kind): the same step in C as in Python."""
    import casadi as ca

    from ocpkit.model.problem import GoalInputOCP

    xg = ca.SX.sym("x_goal", ocp.nx)
    h = ca.Function("h", [xg], [ca.vertcat(3 * ca.sin(xg[0]), ca.cos(xg[1]) * xg[0])])
    gocp = GoalInputOCP(
        ocp.model,
        ocp.dt,
        ocp.horizon,
        ocp.Q,
        ocp.R,
        u_min=ocp.u_min,
        u_max=ocp.u_max,
        parameterization=ocp.parameterization,
        goal_input=h,
    )
    goal = _same_closed_loop(gocp, seed=4, steps=30)
    assert np.abs(gocp.input_goal(goal) - ocp.input_goal(goal)).max() > 0.1  # h changed the problem


def test_background_build_fills_the_cache_even_after_the_process_exits(tmp_path):
    """A script shorter than the build: its child process finishes the build, and the next run finds it."""
    import os
    import subprocess
    import sys
    import time

    env = {**os.environ, "OCPKIT_CACHE_DIR": str(tmp_path)}
    script = (
        "from ocpkit import problems; from ocpkit.solvers.qp import LinearMPC; "
        "p = problems.make('nlink:2'); c = LinearMPC(p.ocp(knots=3, horizon=20, compiled=True)); "
        "print(c.native, c.path)"
    )
    out = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True, cwd=tmp_path
    )
    assert out.stdout.strip() == "False Python step, C step building"  # it exited before the build finished
    deadline = time.monotonic() + 120
    while not list(tmp_path.glob(f"native/*/lib{native.NAME}.so.sha256")) and time.monotonic() < deadline:
        time.sleep(0.2)
    script = script.replace("print(c.native, c.path)", "print(c.wait_compiled(60))")
    out = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True, cwd=tmp_path
    )
    assert out.stdout.strip() == "True"
    # The first run's build child (niced) removes its scratch folder just after it installs the library: on a busy
    # machine that can come after the second run (a fresh-clone CI run saw it), so the check waits for it.
    deadline = time.monotonic() + 60
    while list(tmp_path.glob("native/.build-*")) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not list(tmp_path.glob("native/.build-*"))


# --- Cache entries: one that does not load is evicted and rebuilt once; one build per entry machine-wide; a killed
# build says so. `make` is replaced on PATH by a script that logs each build (and can be killed) before the real one.


def _make_wrapper(folder, monkeypatch, body: str) -> Path:
    """A `make` first on PATH that runs ``body`` (sh; $LOG is a file in ``folder``) and then the real make."""
    import shutil

    real = shutil.which("make")
    bin_dir = folder / "bin"
    bin_dir.mkdir(parents=True)
    wrapper = bin_dir / "make"
    log = folder / "make.log"
    wrapper.write_text(f'#!/bin/sh\nLOG={log}\n{body}\nexec {real} "$@"\n')
    wrapper.chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    return log


ELF32 = b"\x7fELF\x01\x01\x01" + bytes(9) + b"\x03\x00\x03\x00" + bytes(200)  # a 32-bit x86 ELF header


def test_a_cached_library_that_does_not_load_is_evicted_and_rebuilt_once(tmp_path, monkeypatch):
    """A library whose hash matches but which the loader refuses ("wrong ELF class": another machine's) was
    warned about on every run and never rebuilt; now it is removed and built again, once."""
    import subprocess
    import sys
    import warnings

    from ocpkit.codegen.cache import write_entry

    monkeypatch.setenv("OCPKIT_CACHE_DIR", str(tmp_path / "cache"))
    # LinearMPC's entry (its eps and max_iter), built by another process: this one must not have loaded the
    # library path before (dlopen keeps a library by its name).
    script = (
        "from ocpkit import problems; from ocpkit.export import native; p = problems.make('nlink:2'); "
        "print(native.start(p.ocp(knots=4, horizon=30), eps=1e-9, max_iter=10_000, wait=True).result())"
    )
    folder = Path(
        subprocess.run(
            [sys.executable, "-c", script], capture_output=True, text=True, check=True, env=os.environ, cwd=tmp_path
        ).stdout.split()[-1]
    )
    library = folder / f"lib{native.NAME}.so"
    write_entry(library, ELF32)  # garbage with a matching hash
    log = _make_wrapper(tmp_path, monkeypatch, 'echo build >> "$LOG"')
    monkeypatch.setattr(native, "_builds", {})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ctrl = LinearMPC(PROBLEM.ocp(knots=4, horizon=30, compiled=True))
        assert ctrl.wait_compiled(120) and ctrl.native
    messages = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert len(messages) == 1 and "wrong ELF class" in messages[0] and "building it again" in messages[0], messages
    assert log.read_text().count("build") == 1 and library.read_bytes()[4] == 2  # ELFCLASS64
    x, goal = PROBLEM.sample(0)
    assert ctrl.solve(x, goal).status == SUCCESS


def test_concurrent_scripts_build_one_entry_once(tmp_path, monkeypatch):
    """Four short scripts started together: one build (the entry's lock), and all four then run the C step."""
    import subprocess
    import sys

    monkeypatch.setenv("OCPKIT_CACHE_DIR", str(tmp_path / "cache"))
    log = _make_wrapper(tmp_path, monkeypatch, 'echo build >> "$LOG"; sleep 1')  # widen the window
    script = (
        "from ocpkit import problems; from ocpkit.solvers.qp import LinearMPC; "
        "p = problems.make('nlink:2'); c = LinearMPC(p.ocp(knots=3, horizon=25, compiled=True)); "
        "print(c.wait_compiled(180))"
    )
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", script],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=os.environ,
            cwd=tmp_path,
        )
        for _ in range(4)
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    assert [out.strip() for out, _ in outs] == ["True"] * 4, [err[-500:] for _, err in outs]
    assert log.read_text().count("build") == 1
    assert not list((tmp_path / "cache").glob("native/.build-*"))


def test_a_killed_build_says_it_was_killed(tmp_path, monkeypatch):
    """make killed (here and now), and the background build's own process killed: each named with its signal,
    not the last line make printed ("CC mpc.c")."""
    from ocpkit.export import BuildError

    monkeypatch.setenv("OCPKIT_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(native, "_builds", {})
    _make_wrapper(tmp_path / "a", monkeypatch, 'echo "CC mpc.c"; kill -KILL $$')
    with pytest.raises(BuildError, match="make was killed by SIGKILL"):
        native.start(PROBLEM.ocp(knots=3, horizon=31), eps=1e-9, max_iter=1000, wait=True)
    # The background build's own process (make's parent, the child that runs it) killed.
    _make_wrapper(
        tmp_path / "b",
        monkeypatch,
        'if grep -q "ocpkit.export.native import _child" /proc/$PPID/cmdline; then kill -KILL $PPID; exit 1; fi',
    )
    future = native.start(PROBLEM.ocp(knots=3, horizon=32), eps=1e-9, max_iter=1000)
    with pytest.raises(BuildError, match=r"its build process \(pid \d+\) was killed by SIGKILL"):
        future.result(120)


# --- Obstacles (issue 43): the C step appends the linearized clearance rows as the Python step does.


def _same_steps_with_obstacles(problem, ocp, x, goal, steps, tol, **options):
    """LinearMPC's C step and its Python step from the same states: the same statuses, knots to ``tol``; the
    closed loop's clearances (true, no margin)."""
    from ocpkit.model.task import clearances

    c, py = LinearMPC(ocp, native=True, **options), LinearMPC(ocp, native=False, **options)
    assert c.native and c.path == "C step"
    F, xs = ocp.discrete(), []
    for _ in range(steps):
        a, b = c.solve(x, goal), py.solve(x, goal)
        assert a.status == b.status, (a.raw_status, b.raw_status)
        np.testing.assert_allclose(a.knots, b.knots, atol=tol, rtol=0)
        x = np.asarray(F(x, a.u)).ravel()
        xs.append(x[: problem.kinematics.n])
    return clearances(problem.kinematics, ocp.task.robot, ocp.task.obstacles, np.array(xs))


def _ee_target(problem, seed):
    fk = problem.kinematics.function(problem.end_effector)
    return np.asarray(fk(problem.sample(seed)[1][: problem.kinematics.n])[0]).ravel()


def test_c_step_with_obstacles_equals_python_step_past_a_ball():
    """nlink:3 reaching past a ball it starts 1.2 cm from (margin 1 cm): 150 steps, the obstacle rows in the QP
    while the arm passes the ball; every step answered by the C step's hard QP."""
    from ocpkit.model.task import ACTIVATION, reach

    problem = problems.make("nlink:3")
    ocp = reach(problem, ["0.58,-0.02,0,0.06"], knots=5, compiled=False)
    x, _ = problem.sample(0)
    gaps = _same_steps_with_obstacles(problem, ocp, x, ocp.goal(x, position=_ee_target(problem, 1)), 150, 1e-8)
    assert gaps.min() > 0 and (gaps < ACTIVATION).sum() >= 20 and gaps[-1] > ACTIVATION, gaps


def test_c_step_with_obstacles_inside_the_margin_goes_on_to_the_softened_qp():
    """A start under 5 mm from the ball: the C step's hard QP is infeasible, and the QP with the obstacle rows
    softened answers in Python — the Python step's answer."""
    from ocpkit.model.task import clearances, reach

    problem = problems.make("nlink:3")
    ocp = reach(problem, ["0.58,-0.02,0,0.06"], knots=5, compiled=False)
    x, _ = problem.sample(0)
    x[0] -= 0.1
    assert clearances(problem.kinematics, ocp.task.robot, ocp.task.obstacles, x[None, :3])[0] < 0.005
    goal = ocp.goal(x, position=_ee_target(problem, 1))
    c, py = LinearMPC(ocp, native=True), LinearMPC(ocp, native=False)
    a, b = c.solve(x, goal), py.solve(x, goal)
    assert a.status == b.status == SOFT and not a.fallback and "DAQP optimal" in a.raw_status, a.raw_status
    np.testing.assert_allclose(a.knots, b.knots, atol=1e-8, rtol=0)


@pytest.mark.slow  # 30-60 s: the Panda's C step builds
def test_c_step_with_obstacles_equals_python_step_on_the_readme_panda_case():
    """The README's Panda reach past a sphere: 10 steps of the C step equal the Python step's. The arm's reach QP is
    ill-conditioned (tests/test_export_task.py): knots to 5e-8."""
    from ocpkit.model.task import Sphere, reach

    problem = problems.make("panda")
    ocp = reach(problem, [Sphere((0.4, -0.25, 0.35), 0.08)], knots=5, compiled=False)
    x, _ = problem.sample(seed=0)
    gaps = _same_steps_with_obstacles(problem, ocp, x, ocp.goal(x, position=(0.4, 0.0, 0.3)), 10, 5e-8)
    assert gaps.min() < 0.1  # the obstacle rows are in the QPs
