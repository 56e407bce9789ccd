"""A full cache (no space left on its file system, or the user's disk quota spent) is a cache that cannot be
written: used as a read-only one is (the Python step, CasADi's VM, kernels compiled in memory, one warning naming
the folder as full), refused only where compiled code was asked for (``native=True``, ``compiled=True``,
``ocpkit build``).

In process, the full file system is simulated: creating a file or folder below the cache raises ENOSPC (or EDQUOT),
as on a file system out of room or inodes. As root with mount namespaces, the subprocess tests run on a real full
tmpfs (:func:`ocpkit.benchmarks.readonly.run_full`), where the writes themselves fail.
"""

import errno
import json
import os
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from ocpkit import problems
from ocpkit.codegen import cache, compiled
from ocpkit.export import native
from ocpkit.benchmarks import readonly
from ocpkit.codegen.cache import CacheReadOnlyError
from ocpkit.export import check_tools

try:
    check_tools()
except Exception as exc:  # noqa: BLE001
    pytest.skip(f"no C toolchain: {exc}", allow_module_level=True)

SPEC, KNOTS, HORIZON = "nlink:5", 3, 20  # the smallest robot whose default LinearMPC builds the C step
ERRNOS = [errno.ENOSPC, errno.EDQUOT]


@pytest.fixture(params=ERRNOS, ids=["ENOSPC", "EDQUOT"])
def full(request, tmp_path, monkeypatch):
    """An empty cache folder on a file system without room: creating anything below it raises the errno."""
    root = tmp_path / "cache"
    root.mkdir(mode=0o700)
    monkeypatch.setenv("OCPKIT_CACHE_DIR", str(root))
    monkeypatch.setattr(native, "_builds", {})
    monkeypatch.setattr(cache, "_warned_read_only", False)
    code = request.param
    real_mkdir, real_open = os.mkdir, os.open

    def below(path) -> bool:
        return isinstance(path, (str, os.PathLike)) and Path(os.path.abspath(path)).is_relative_to(root)

    def mkdir(path, mode=0o777, *, dir_fd=None):
        if below(path) and not os.path.exists(path):
            raise OSError(code, os.strerror(code), str(path))
        return real_mkdir(path, mode, dir_fd=dir_fd)

    def open_(path, flags, mode=0o777, *, dir_fd=None):
        if below(path) and flags & os.O_CREAT and not os.path.exists(path):
            raise OSError(code, os.strerror(code), str(path))
        return real_open(path, flags, mode, dir_fd=dir_fd)

    monkeypatch.setattr(os, "mkdir", mkdir)
    monkeypatch.setattr(os, "open", open_)
    # The background compile in this process, where the simulation holds (its child process would see the disk).
    monkeypatch.setattr(compiled, "_compile_out_of_process", compiled.compile_function)
    return root, code


def _runtime_warnings(record) -> list[str]:
    return [str(w.message) for w in record if issubclass(w.category, RuntimeWarning)]


def test_linear_mpc_on_a_full_cache_runs_its_python_step_with_one_warning(full, recwarn):
    from ocpkit.solvers.qp import LinearMPC

    root, code = full
    problem = problems.make(SPEC)
    ctrl = LinearMPC(problem.ocp(knots=KNOTS, horizon=HORIZON))
    x, goal = problem.sample(0)
    assert ctrl.solve(x, goal).status == "success" and not ctrl.wait_compiled(60) and not ctrl.native
    (warning,) = _runtime_warnings(recwarn)
    assert f"cache folder {root / 'native'} is full ({os.strerror(code)})" in warning and "Python step" in warning
    assert not any(root.rglob("*"))


def test_compiled_code_asked_for_on_a_full_cache_is_refused_in_one_line(full):
    from ocpkit.solvers.qp import LinearMPC

    root, code = full
    ocp = problems.make(SPEC).ocp(knots=KNOTS, horizon=HORIZON)
    with pytest.raises(CacheReadOnlyError, match=f"is full \\({os.strerror(code)}\\): make room") as caught:
        LinearMPC(ocp, native=True)
    assert caught.value.errno == code and "\n" not in str(caught.value)
    x = ca.SX.sym("x", 2)
    with pytest.raises(CacheReadOnlyError, match="'full_fn'.*is not in the cache.*is full"):
        compiled.compile_function(ca.Function("full_fn", [x], [x * x]))


def test_taichi_kernels_on_a_full_cache_are_kept_in_memory_with_one_warning(full, recwarn, taichi_arch):
    from ocpkit.codegen.kernels import runtime
    from ocpkit.codegen.kernels import translate as tr

    root, code = full
    settings = runtime._offline_cache()
    assert not settings["offline_cache"] and not Path(settings["offline_cache_file_path"]).is_relative_to(root)
    (warning,) = _runtime_warnings(recwarn)
    assert f"cache folder {root / 'taichi-kernels'} is full" in warning
    x = ca.SX.sym("x", 2)
    # a Function of its own per errno: a module imported before would not be written again
    kernel = tr.translate(ca.Function("full_kernel", [x], [ca.cos(x[0]) * x[1] + code]))
    assert kernel.path.exists() and not kernel.path.is_relative_to(root)
    (out,) = kernel(np.array([[0.5, 2.0]]))
    np.testing.assert_allclose(out.ravel(), [np.cos(0.5) * 2.0 + code])
    assert len(_runtime_warnings(recwarn)) == 1


# --- A real full file system (root with mount namespaces): the writes themselves fail with ENOSPC.

needs_full = pytest.mark.skipif(
    readonly.method() != readonly.BIND_MOUNT, reason="a full file system needs root with mount namespaces"
)
# A default LinearMPC and EMPC as a script writes them: statuses, whether in C, the warnings, as JSON.
SCRIPT = f"""
import json, warnings
from ocpkit import problems, solvers
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    p = problems.make({SPEC!r})
    x, goal = p.sample(0)
    c, e = (solvers.make(name, p.ocp(knots={KNOTS}, horizon={HORIZON})) for name in ("qp", "empc"))
    statuses = [c.solve(x, goal).status, e.solve(x, goal).status]
    compiled = c.wait_compiled(60)
print(json.dumps({{"statuses": statuses, "native": c.native, "compiled": compiled,
                  "warnings": [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]}}))
"""


@needs_full
def test_a_real_full_file_system(tmp_path):
    """LinearMPC and EMPC on a full tmpfs: both succeed, one warning naming the folder as full; `ocpkit build`
    (compiled code asked for) exits 2 with one line."""
    root = tmp_path / "cache"
    root.mkdir(mode=0o700)
    env = {**os.environ, "OCPKIT_CACHE_DIR": str(root)}
    run = readonly.run_full(
        root, [sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=600, cwd=tmp_path
    )
    assert run.returncode == 0, run.stderr
    result = json.loads(run.stdout.splitlines()[-1])
    assert result["statuses"] == ["success", "success"] and not result["native"] and not result["compiled"]
    (warning,) = result["warnings"]
    assert f"{root}/native is full (No space left on device)" in warning and "Python step" in warning
    build = readonly.run_full(
        root,
        [sys.executable, "-m", "ocpkit.cli", "build", SPEC, "--knots", str(KNOTS)],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        cwd=tmp_path,
    )
    assert build.returncode == 2 and "Traceback" not in build.stderr, build.stderr
    assert build.stderr.strip().splitlines()[-1].startswith("ocpkit: error: ") and "is full" in build.stderr
