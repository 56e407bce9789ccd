"""The default affine model: CasADi's VM until a background compile finishes, then the compiled C
(ocpkit.codegen.compiled)."""

import threading
import warnings
import weakref

import numpy as np
import pytest

import ocpkit.codegen.compiled as compiled
import ocpkit.model.ocp as ocp_module
from ocpkit.codegen.compiled import SwitchingFunction
from ocpkit.numeric import BufferedFunction
from ocpkit.problems import make
from ocpkit.solvers.qp import LinearMPC


@pytest.fixture
def background(tmp_path, monkeypatch):
    """A private cache and every model large enough for the background compile."""
    monkeypatch.setenv("OCPKIT_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(ocp_module, "BACKGROUND_MIN_INSTRUCTIONS", 0)
    return tmp_path


def _close(a, b):
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    np.testing.assert_allclose(a, b, atol=1e-12 * max(1.0, np.abs(b).max()), rtol=0)


def test_switched_model_equals_the_vm(background):
    problem = make("nlink:2")
    ocp = problem.ocp(horizon=20, knots=3)
    fn = ocp.affine()
    assert isinstance(fn, SwitchingFunction)
    vm = problem.ocp(horizon=20, knots=3, compiled=False).affine()
    assert not isinstance(vm, SwitchingFunction)
    buffered = BufferedFunction(fn)
    rng = np.random.default_rng(0)
    points = [(rng.normal(size=ocp.nx), rng.normal(size=ocp.nu)) for _ in range(3)]
    before = [[np.array(v) for v in buffered(x, u)] for x, u in points]  # copies: a vector output is the buffer
    assert fn.wait(300) is not None
    after = [[np.array(v) for v in buffered(x, u)] for x, u in points]
    assert buffered._buffer.switched
    for (x, u), b, a in zip(points, before, after):
        for vb, va, ref in zip(b, a, vm(x, u)):
            _close(vb, ref)
            _close(va, ref)
    # Once compiled, the OCP hands out the compiled Function itself; calls and maps switch too.
    assert not isinstance(ocp.affine(), SwitchingFunction)
    x, u = points[0]
    for va, ref in zip(fn(x, u), vm(x, u)):
        _close(va, ref)
    xs, us = rng.normal(size=(ocp.nx, 4)), rng.normal(size=(ocp.nu, 4))
    for va, ref in zip(fn.map(4)(xs, us), vm.map(4)(xs, us)):
        _close(va, ref)
    assert len(list((background / "compiled").glob("*/*.so"))) == 1


def test_controller_keeps_solving_while_the_compile_runs(background, monkeypatch):
    gate, started = threading.Event(), threading.Event()
    real = compiled._compile_out_of_process

    def held(fn, flags="-O1"):
        started.set()
        assert gate.wait(300)
        return real(fn, flags)

    monkeypatch.setattr(compiled, "_compile_out_of_process", held)
    problem = make("nlink:2")
    ocp = problem.ocp(horizon=30, knots=4)
    ctrl, ref = LinearMPC(ocp), LinearMPC(problem.ocp(horizon=30, knots=4, compiled=False))
    x, goal = problem.sample(1)
    plant = problem.ocp(horizon=30, knots=4, compiled=False).discrete()

    def step(x):
        sol, expected = ctrl.solve(x, goal), ref.solve(x, goal)
        assert sol.ok and expected.ok
        np.testing.assert_allclose(sol.u, expected.u, atol=1e-7)
        return np.asarray(plant(x, sol.u)).ravel()

    for _ in range(5):  # the compile is held: every step on the VM, none waits for it
        x = step(x)
    assert started.is_set() and not ctrl._affine_model._buffer.switched
    gate.set()
    assert ocp.affine().wait(300) if isinstance(ocp.affine(), SwitchingFunction) else True
    for _ in range(5):
        x = step(x)
    assert ctrl._affine_model._buffer.switched


def test_compiled_false_and_small_models_stay_on_the_vm(tmp_path, monkeypatch):
    monkeypatch.setenv("OCPKIT_CACHE_DIR", str(tmp_path))
    problem = make("nlink:2")
    assert not isinstance(problem.ocp(knots=3, compiled=False).affine(), SwitchingFunction)
    assert not isinstance(problem.ocp(knots=3).affine(), SwitchingFunction)  # 1.6k instructions: below the size
    assert not (tmp_path / "compiled").exists() or not any((tmp_path / "compiled").iterdir())


def test_no_compiler_one_warning_and_the_vm(background, monkeypatch):
    monkeypatch.setenv("CC", "no-such-compiler-ocpkit")
    problem = make("nlink:2")
    ocp = problem.ocp(horizon=20, knots=3)
    with pytest.warns(RuntimeWarning, match="no C compiler") as record:
        fn = ocp.affine()
    assert len(record) == 1 and not isinstance(fn, SwitchingFunction)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert ocp.affine() is fn
        x, goal = problem.sample(0)
        assert LinearMPC(ocp).solve(x, goal).ok


def test_exit_during_a_background_compile_leaves_no_compiler_nor_scratch(tmp_path):
    import os
    import subprocess
    import sys

    script = (
        "import time, ocpkit.model.ocp as o\nfrom ocpkit.problems import make\n"
        "o.BACKGROUND_MIN_INSTRUCTIONS = 0\n"
        "fn = make('nlink:3').ocp(knots=3).affine()\nimport ocpkit.codegen.compiled as c\n"
        "for _ in range(600):\n    time.sleep(0.05)\n    if c._compiling: break\n"
        "print(len(c._compiling))\n"
    )
    env = {**os.environ, "OCPKIT_CACHE_DIR": str(tmp_path)}
    # cwd away from the checkout: `python -c` puts the cwd first on sys.path, and the checkout's ocpkit/ has no
    # problems/ (that only exists as ocpkit.problems once installed).
    out = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300, cwd=tmp_path
    )
    assert out.returncode == 0, out.stderr
    if out.stdout.strip() == "1":  # it exited while the compiler ran
        assert not list((tmp_path / "compiled").glob("*/.build-*"))


def test_background_compile_hashes_and_generates_out_of_process(background, monkeypatch):
    # The 13-link model's serialization is 23 MB: as a Python string, copied and encoded for the hash, it held the
    # GIL for tens of ms and paused a running control loop. The parent process must not serialize at all.
    import casadi as ca

    def refuse(self, *args):
        raise AssertionError("serialize() called in the control loop's process during a background compile")

    problem = make("nlink:2")
    ocp = problem.ocp(horizon=20, knots=3)
    fn = ocp.affine()
    assert isinstance(fn, SwitchingFunction)
    monkeypatch.setattr(ca.Function, "serialize", refuse)
    assert fn.wait(300) is not None, fn._future.exception()
    monkeypatch.undo()
    vm = problem.ocp(horizon=20, knots=3, compiled=False).affine()
    x, u = problem.sample(0)[0], np.zeros(ocp.nu)
    for va, ref in zip(fn(x, u), vm(x, u)):
        _close(va, ref)
    # The same cache entry as a foreground compile: compiled=True finds it and builds nothing.
    before = sorted(p.stat().st_mtime_ns for p in (background / "compiled").glob("*/*.so"))
    problem.ocp(horizon=20, knots=3, compiled=True).affine()
    assert sorted(p.stat().st_mtime_ns for p in (background / "compiled").glob("*/*.so")) == before


def test_background_compile_error_is_one_line(background, monkeypatch):
    monkeypatch.setenv("CC", "false")  # a "compiler" that is on PATH and fails
    problem = make("nlink:2")
    fn = problem.ocp(horizon=20, knots=3).affine()
    assert isinstance(fn, SwitchingFunction)
    with pytest.warns(RuntimeWarning, match="compiling affine with `false` failed"):
        assert fn.wait(300) is None


def test_a_cached_library_is_taken_at_once(background, monkeypatch):
    """With the compiled model in the cache, a new OCP's affine model is that library from its first call: no
    background compile, no VM phase (a controller built on a warm cache does not rebuild itself later)."""
    problem = make("nlink:2")
    assert problem.ocp(horizon=20, knots=3).affine().wait(300) is not None  # fills the cache

    def refuse(*args):
        raise AssertionError("a background compile started for a cached library")

    monkeypatch.setattr(compiled, "_compile_out_of_process", refuse)
    monkeypatch.setattr(compiled, "_background", weakref.WeakKeyDictionary())  # as in a new process
    ocp = problem.ocp(horizon=20, knots=3)
    fn = ocp.affine()
    assert fn.class_name() == "External" and not isinstance(fn, SwitchingFunction)
    vm = problem.ocp(horizon=20, knots=3, compiled=False).affine()
    x, u = problem.sample(0)[0], np.zeros(ocp.nu)
    for va, ref in zip(fn(x, u), vm(x, u)):
        _close(va, ref)
