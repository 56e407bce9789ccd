"""A read-only cache (a shared install, a container image, a read-only root) is used as it is: a sound entry is
loaded, a missing one means the Python step (or CasADi's VM) with one warning, never an exception; `ocpkit build`
fills a cache ahead of deployment.

How the cache is made read-only: the subprocess tests run their command with the cache folder read-only through
:mod:`ocpkit.benchmarks.readonly` — as root (which ignores permission bits) a read-only bind mount of the folder
onto itself in a private mount namespace (``unshare -m``: writes fail with EROFS, as on a read-only file system),
for other users the folder's write permissions removed (EACCES); they are skipped where neither is possible. The
in-process tests simulate the read-only file system instead (``os.mkdir`` and ``os.open`` for writing raise EROFS
below the cache folder), so they run everywhere.
"""

import errno
import json
import os
import subprocess
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from ocpkit import problems
from ocpkit.codegen import cache
from ocpkit.export import native
from ocpkit.benchmarks import readonly
from ocpkit.codegen.cache import CacheReadOnlyError
from ocpkit.export import check_tools

try:
    check_tools()
except Exception as exc:  # noqa: BLE001
    pytest.skip(f"no C toolchain: {exc}", allow_module_level=True)

SPEC, KNOTS, HORIZON = "nlink:5", 3, 20  # the smallest robot whose default LinearMPC builds the C step
OCPKIT = [sys.executable, "-m", "ocpkit.cli"]
# One LinearMPC as a script writes it (the default policy), its warnings and whether it ran in C, as JSON.
SCRIPT = f"""
import json, warnings
from ocpkit import problems
from ocpkit.solvers.qp import LinearMPC
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    p = problems.make({SPEC!r})
    c = LinearMPC(p.ocp(knots={KNOTS}, horizon={HORIZON}))
    at_once = c.native
    x, goal = p.sample(0)
    first = c.solve(x, goal).status
    compiled = c.wait_compiled(120)
    second = c.solve(x, goal).status
print(json.dumps({{"native": at_once, "statuses": [first, second], "compiled": compiled,
                  "warnings": [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]}}))
"""

needs_read_only = pytest.mark.skipif(
    readonly.method() is None, reason="cannot make a folder read-only here (root without mount namespaces)"
)


def _env(root: Path) -> dict:
    return {**os.environ, "OCPKIT_CACHE_DIR": str(root)}


def _listing(root: Path) -> list:
    return sorted((str(p.relative_to(root)), p.stat().st_size) for p in root.rglob("*"))


def _run_read_only(folder: Path, root: Path, command: list[str], timeout: float = 300) -> subprocess.CompletedProcess:
    return readonly.run(
        folder, command, env=_env(root), cwd=folder.parent, capture_output=True, text=True, timeout=timeout
    )


@needs_read_only
def test_a_read_only_cache_with_a_sound_entry_is_used_as_it_is(tmp_path):
    root = tmp_path / "cache"
    filled = subprocess.run(
        [sys.executable, "-c", SCRIPT], env=_env(root), capture_output=True, text=True, timeout=600, cwd=tmp_path
    )  # not the checkout: it would shadow the installed ocpkit
    # the C step built in the background by a first run, as it is today
    assert filled.returncode == 0 and json.loads(filled.stdout.splitlines()[-1])["compiled"], filled.stderr
    before = _listing(root)

    run = _run_read_only(root, root, [sys.executable, "-c", SCRIPT])
    assert run.returncode == 0, run.stderr
    result = json.loads(run.stdout.splitlines()[-1])
    assert result == {"native": True, "statuses": ["success", "success"], "compiled": True, "warnings": []}
    cli = _run_read_only(
        root, root, [*OCPKIT, "solve", SPEC, "--knots", str(KNOTS), "--horizon", str(HORIZON), "--json"]
    )
    assert cli.returncode == 0, cli.stderr
    assert "C step" in json.loads(cli.stdout)["controller"] and "Warning" not in cli.stderr
    assert _listing(root) == before  # nothing written


@needs_read_only
def test_ocpkit_build_fills_a_cache_for_a_read_only_deployment(tmp_path):
    """`ocpkit build` puts the default C step and the compiled model in the cache and says where; read-only, the
    C step is loaded at once and so is the compiled model (the Python step's, here with native=False)."""
    root = tmp_path / "cache"
    args = [SPEC, "--knots", str(KNOTS), "--horizon", str(HORIZON)]
    built = subprocess.run(
        [*OCPKIT, "build", *args], env=_env(root), capture_output=True, text=True, timeout=600, cwd=tmp_path
    )
    assert built.returncode == 0, built.stderr
    lines = built.stdout.splitlines()
    (step,) = [line for line in lines if line.startswith("C step")]
    (model,) = [line for line in lines if line.startswith("compiled affine model")]
    assert step.endswith("libmpc.so (built now)") and model.endswith(".so (built now)"), built.stdout
    for line in (step, model):
        assert cache.entry_ok(Path(line.rsplit(": ", 1)[1].rsplit(" (", 1)[0]))
    before = _listing(root)

    run = _run_read_only(root, root, [sys.executable, "-c", SCRIPT])
    assert json.loads(run.stdout.splitlines()[-1])["native"] is True, run.stderr
    python_step = SCRIPT.replace("LinearMPC(p.ocp(", "LinearMPC(native=False, ocp=p.ocp(")
    run = _run_read_only(root, root, [sys.executable, "-c", python_step])
    result = json.loads(run.stdout.splitlines()[-1])
    assert result == {"native": False, "statuses": ["success", "success"], "compiled": True, "warnings": []}
    again = _run_read_only(root, root, [*OCPKIT, "build", *args])
    assert again.returncode == 0 and again.stdout.count("(already in the cache)") == 2, again.stdout + again.stderr
    assert _listing(root) == before  # nothing written


@needs_read_only
@pytest.mark.parametrize("state", ["empty", "absent"])
def test_a_read_only_cache_without_the_entry_runs_the_python_step_with_one_warning(tmp_path, state):
    folder = tmp_path / "ro"
    folder.mkdir(mode=0o700)
    root = folder if state == "empty" else folder / "absent"  # a cache folder that cannot even be created

    run = _run_read_only(folder, root, [sys.executable, "-c", SCRIPT])
    assert run.returncode == 0, run.stderr
    result = json.loads(run.stdout.splitlines()[-1])
    assert result["native"] is False and result["compiled"] is False and result["statuses"] == ["success"] * 2
    (warning,) = result["warnings"]  # the C step and the compiled model both missing: said once
    assert "read-only" in warning and "ocpkit build" in warning and "Python step" in warning

    cli = _run_read_only(folder, root, [*OCPKIT, "solve", SPEC, "--knots", str(KNOTS), "--horizon", str(HORIZON)])
    assert cli.returncode == 0 and "status = success" in cli.stdout, cli.stderr
    assert cli.stderr.count("RuntimeWarning") == 1 and "read-only" in cli.stderr and "Traceback" not in cli.stderr
    prebuild = _run_read_only(folder, root, [*OCPKIT, "build", SPEC, "--knots", str(KNOTS)])
    assert prebuild.returncode == 2 and "Traceback" not in prebuild.stderr
    assert prebuild.stderr.strip().splitlines()[-1].startswith("ocpkit: error: ") and "read-only" in prebuild.stderr
    assert not any(folder.rglob("*"))


# --- In process, the read-only file system simulated (EROFS below the cache folder): runs as any user.


@pytest.fixture
def read_only(tmp_path, monkeypatch):
    """A cache folder, and a function that makes it read-only from then on (as far as this process can tell)."""
    root = tmp_path / "cache"
    monkeypatch.setenv("OCPKIT_CACHE_DIR", str(root))
    monkeypatch.setattr(native, "_builds", {})
    monkeypatch.setattr(cache, "_warned_read_only", False, raising=False)

    def below(path) -> bool:
        return isinstance(path, (str, os.PathLike)) and Path(os.path.abspath(path)).is_relative_to(root)

    def freeze():
        real_mkdir, real_open = os.mkdir, os.open

        def mkdir(path, mode=0o777, *, dir_fd=None):
            if below(path):
                if os.path.exists(path):
                    raise FileExistsError(errno.EEXIST, "File exists", str(path))
                raise OSError(errno.EROFS, "Read-only file system", str(path))
            return real_mkdir(path, mode, dir_fd=dir_fd)

        def open_(path, flags, mode=0o777, *, dir_fd=None):
            if below(path) and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
                raise OSError(errno.EROFS, "Read-only file system", str(path))
            return real_open(path, flags, mode, dir_fd=dir_fd)

        monkeypatch.setattr(os, "mkdir", mkdir)
        monkeypatch.setattr(os, "open", open_)

    return root, freeze


def test_native_on_a_simulated_read_only_cache(read_only, recwarn):
    root, freeze = read_only
    problem = problems.make(SPEC)
    folder = native.start(problem.ocp(knots=KNOTS, horizon=HORIZON), eps=1e-9, max_iter=1000, wait=True).result()
    freeze()
    native._builds.clear()
    found = native.start(problem.ocp(knots=KNOTS, horizon=HORIZON), eps=1e-9, max_iter=1000)
    assert found is not None and found.done() and found.result() == folder  # used at once, nothing built

    missing = problem.ocp(knots=KNOTS, horizon=HORIZON + 1)
    recwarn.clear()
    assert native.start(missing, eps=1e-9, max_iter=1000) is None
    assert native.start(missing, eps=1e-9, max_iter=1000) is None
    messages = [str(w.message) for w in recwarn if issubclass(w.category, RuntimeWarning)]
    assert len(messages) == 1 and "is not in the cache" in messages[0] and "ocpkit build" in messages[0]
    with pytest.raises(CacheReadOnlyError, match="read-only.*ocpkit build"):
        native.start(problem.ocp(knots=KNOTS, horizon=HORIZON + 2), eps=1e-9, max_iter=1000, wait=True)
    assert not list(root.rglob(".build-*"))


def test_compiled_model_on_a_simulated_read_only_cache(read_only):
    from ocpkit.codegen.compiled import compile_function

    root, freeze = read_only
    x = ca.SX.sym("x", 2)
    sound, missing = (ca.Function(name, [x], [x * x + k]) for k, name in ((1, "ro_sound"), (2, "ro_missing")))
    compile_function(sound)
    freeze()
    np.testing.assert_allclose(np.asarray(compile_function(sound)([1.0, 2.0])).ravel(), [2.0, 5.0])
    with pytest.raises(CacheReadOnlyError, match="ro_missing.*is not in the cache.*read-only.*ocpkit build"):
        compile_function(missing)


def test_taichi_kernels_on_a_simulated_read_only_cache(read_only, taichi_arch):
    """The generated kernel module a read-only cache lacks goes to a folder of the process's own (it is generated
    every run anyway), instead of an OSError."""
    from ocpkit.codegen.kernels import translate as tr

    root, freeze = read_only
    freeze()
    x = ca.SX.sym("x", 2)
    kernel = tr.translate(ca.Function("ro_kernel", [x], [ca.sin(x[0]) * x[1] + 1.5]))
    assert kernel.path.exists() and not kernel.path.is_relative_to(root)
    (out,) = kernel(np.array([[0.5, 2.0]]))
    np.testing.assert_allclose(out.ravel(), [np.sin(0.5) * 2.0 + 1.5])


@pytest.mark.slow
def test_every_cache_row_of_bench_faults_acceptable():
    from ocpkit.benchmarks.faults_cache import cache_rows

    rows = cache_rows(out=lambda line: None)
    # read-only (sound entry, no entry), concurrent builds, planted entry, full disk (mount namespaces only)
    assert len(rows) == {None: 2, readonly.BIND_MOUNT: 5}.get(readonly.method(), 4)
    bad = [(r.case, r.solver, r.detail) for r in rows if not r.acceptable]
    assert not bad, bad
