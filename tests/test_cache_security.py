"""Code another user could have planted in the cache is never loaded: every folder from the cache root down to a
library (or kernel module), and the file itself, must be this user's or root's and writable by no one else, checked
before anything is loaded (a planted library's constructor runs at ``dlopen``, before any symbol is looked up)."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import casadi as ca
import pytest

from ocpkit import problems
from ocpkit.codegen import compiled
from ocpkit.export import native
from ocpkit.codegen.cache import UnsafeCacheError, check_trusted, write_entry

SPEC, KNOTS, HORIZON = "nlink:5", 3, 20  # as tests/test_cache_readonly.py: a default LinearMPC that wants its C step
OTHER_UID = 12345
UNSAFE = ["folder 777", "folder 770", "file 666"] + (["folder of another user"] if os.getuid() == 0 else [])

pytestmark = pytest.mark.skipif(shutil.which(os.environ.get("CC", "cc")) is None, reason="no C compiler")


@pytest.fixture
def cache(tmp_path, monkeypatch):
    root = tmp_path / "cache"
    monkeypatch.setenv("OCPKIT_CACHE_DIR", str(root))
    return root


def plant(library: Path, marker: Path) -> None:
    """A library whose constructor writes ``marker`` the moment it is loaded, as the cache entry ``library`` with a
    matching content hash (what another user who could write the entry's folder would leave)."""
    source = library.parent.parent / "planted.c"
    source.write_text(
        "#include <stdio.h>\n__attribute__((constructor)) static void planted(void) "
        f'{{ FILE *f = fopen("{marker}", "w"); if (f) fclose(f); }}\n'
    )
    built = library.parent.parent / "planted.so"
    subprocess.run([os.environ.get("CC", "cc"), "-shared", "-fPIC", str(source), "-o", str(built)], check=True)
    write_entry(library, built.read_bytes())


def make_unsafe(library: Path, how: str) -> Path:
    """Open the entry to other users as ``how`` says; the path now unsafe."""
    if how == "file 666":
        library.chmod(0o666)
        return library
    if how == "folder of another user":
        os.chown(library.parent, OTHER_UID, -1)
    else:
        library.parent.chmod(int(how.split()[1], 8))
    return library.parent


def expected(how: str, path: Path) -> str:
    what = "belongs to another user \\(uid 12345\\)" if "another" in how else "is writable by other users"
    return f"cache (folder|file) {path} {what}"


@pytest.mark.parametrize("how", UNSAFE)
def test_check_trusted_names_the_unsafe_part(cache, how):
    library = cache / "native" / "0123abcd" / "libmpc.so"
    library.parent.mkdir(mode=0o700, parents=True)
    write_entry(library, b"not loaded")
    cache.chmod(0o700)
    assert check_trusted(library) == library.resolve()
    unsafe = make_unsafe(library, how)
    with pytest.raises(UnsafeCacheError, match=expected(how, unsafe)) as caught:
        check_trusted(library)
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize("how", UNSAFE)
def test_a_planted_compiled_library_is_not_loaded(cache, tmp_path, how):
    x = ca.SX.sym("x", 2)
    fn = ca.Function(f"planted_{how.replace(' ', '_')}", [x], [x * x + 1])  # a path of its own: dlopen caches by path
    library = compiled._entry(fn, "-O1")
    library.parent.mkdir(mode=0o700, parents=True)
    marker = tmp_path / "constructor-ran"
    plant(library, marker)
    unsafe = make_unsafe(library, how)
    for load in (compiled.compile_function, compiled.compile_in_background):
        with pytest.raises(UnsafeCacheError, match=expected(how, unsafe)):
            load(fn)
    assert not marker.exists()


# A default LinearMPC in a fresh process (a library loaded before under the same path would not be loaded again).
SCRIPT = f"""
from ocpkit import problems
from ocpkit.solvers.qp import LinearMPC
p = problems.make({SPEC!r})
c = LinearMPC(p.ocp(knots={KNOTS}, horizon={HORIZON}))
print("constructed, native:", c.wait_compiled(60) and c.native)
"""


@pytest.mark.parametrize("how", UNSAFE)
def test_a_planted_c_step_is_not_loaded_by_a_default_linear_mpc(cache, tmp_path, how):
    """The issue's case: the C step's entry opened to others and its libmpc.so and hash replaced; LinearMPC refuses
    as for an unsafe cache root (UnsafeCacheError, one line), and the planted constructor never runs."""
    from ocpkit.solvers.qp import LinearMPC

    ocp = problems.make(SPEC).ocp(knots=KNOTS, horizon=HORIZON)
    probe = LinearMPC(ocp, native=False)  # the settings a default LinearMPC hands to native.start
    settings = (probe._backend.tolerance, probe.max_iter, probe.linearization, 1, 0.0)
    scratch, key, _ = native._generate(ocp, settings, native.cache_dir("native"))  # the entry's key, nothing built
    shutil.rmtree(scratch)
    library = cache / "native" / key / f"lib{native.NAME}.so"
    library.parent.mkdir(mode=0o700)
    marker = tmp_path / "constructor-ran"
    plant(library, marker)
    unsafe = make_unsafe(library, how)
    run = subprocess.run(
        [sys.executable, "-c", SCRIPT],
        env={**os.environ, "OCPKIT_CACHE_DIR": str(cache)},
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert run.returncode == 1 and not marker.exists(), run.stdout + run.stderr
    last = run.stderr.strip().splitlines()[-1]
    assert last.startswith("ocpkit.codegen.cache.UnsafeCacheError: ") and f"{unsafe} " in last, run.stderr


def test_taichi_kernel_cache_with_a_file_others_can_write_is_refused(cache):
    from ocpkit.codegen.kernels import runtime

    assert runtime._offline_cache()["offline_cache"]  # created private, so trusted
    planted = cache / "taichi-kernels" / "Tplanted.tic"
    planted.write_bytes(b"kernel")
    planted.chmod(0o666)
    with pytest.raises(UnsafeCacheError, match=f"cache file {planted} is writable by other users"):
        runtime._offline_cache()


def test_a_generated_kernel_module_others_can_write_is_not_imported(cache, taichi_arch):
    from ocpkit.codegen.kernels import translate as tr

    x = ca.SX.sym("x", 2)
    fn = ca.Function("trusted_kernel", [x], [x[0] * x[1] + 2.5])
    path = tr.translate(fn).path
    name = next(
        m
        for m in list(sys.modules)
        if m.startswith("ocpkit_kernel_") and sys.modules[m].__file__ == str(path.resolve())
    )
    del sys.modules[name]
    path.chmod(0o666)
    with pytest.raises(UnsafeCacheError, match=f"cache file {path} is writable by other users"):
        tr.translate(fn)
    assert name not in sys.modules
