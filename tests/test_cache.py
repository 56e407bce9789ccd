"""The cache of generated code: damaged entries rebuilt, unsafe folders refused, nothing left by failed builds."""

import os

import casadi as ca
import numpy as np
import pytest

from ocpkit.codegen.cache import UnsafeCacheError, cache_dir, entry_ok, write_entry
from ocpkit.codegen.compiled import CompileError, compile_function


@pytest.fixture
def cache(tmp_path, monkeypatch):
    root = tmp_path / "cache"
    monkeypatch.setenv("OCPKIT_CACHE_DIR", str(root))
    return root


def square_fn():
    x = ca.SX.sym("x", 2)
    return ca.Function("sq_test", [x], [x * x + 1])


def test_a_damaged_library_is_rebuilt_with_a_warning(cache):
    f = compile_function(square_fn())
    np.testing.assert_allclose(np.asarray(f([1.0, 2.0])).ravel(), [2.0, 5.0])
    (library,) = (cache / "compiled").glob("*/sq_test.so")
    assert entry_ok(library)
    for damage in (b"", library.read_bytes()[:1000]):  # an empty library, a truncated one
        # A new file under the name (as a crashed earlier run would leave): never rewrite a loaded library in place.
        (library.parent / "damaged").write_bytes(damage)
        os.replace(library.parent / "damaged", library)
        with pytest.warns(RuntimeWarning, match="damaged cache entry"):
            f = compile_function(square_fn())
        np.testing.assert_allclose(np.asarray(f([3.0, 0.0])).ravel(), [10.0, 1.0])
        assert entry_ok(library)


def test_no_compiler_is_one_line_and_leaves_nothing(cache, monkeypatch):
    monkeypatch.setenv("CC", "no-such-cc")
    with pytest.raises(CompileError, match="needs a C compiler, and `no-such-cc` was not found"):
        compile_function(square_fn())
    leftovers = [p.name for p in (cache / "compiled").rglob("*") if p.is_file()]
    assert not [n for n in leftovers if n.endswith(".so") or n.startswith("tmp")], leftovers


def test_a_cache_writable_by_others_is_refused(cache):
    cache.mkdir(mode=0o700)
    assert oct(cache_dir("x").stat().st_mode & 0o777) == "0o700"
    os.chmod(cache, 0o777)
    with pytest.raises(UnsafeCacheError, match="writable by other users.*chmod go-w"):
        cache_dir("x")


def test_entries_are_checked_against_their_hash(tmp_path):
    path = write_entry(tmp_path / "k.py", b"x = 1\n")
    assert entry_ok(path)
    path.write_bytes(b"import os; os.system('planted')\n")
    assert not entry_ok(path)
    assert not entry_ok(tmp_path / "missing.py")


def test_an_entry_lock_waits_for_its_holder_and_not_for_a_dead_one(tmp_path):
    """One build per entry machine-wide: a second builder waits for the holder (a TimeoutError naming its pid
    after its timeout), and a holder killed with SIGKILL leaves no lock behind (the kernel releases a flock)."""
    import signal
    import subprocess
    import sys
    import time

    from ocpkit.codegen.cache import entry_lock

    entry = tmp_path / "native" / "0123abcd"
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from pathlib import Path; "
            "from ocpkit.codegen.cache import entry_lock\n"
            "with entry_lock(Path(sys.argv[1])):\n print('locked', flush=True); time.sleep(300)",
            str(entry),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(TimeoutError, match=f"pid {holder.pid}.*building cache entry"):
            with entry_lock(entry, timeout=0.3):
                pass
        holder.send_signal(signal.SIGKILL)
        holder.wait(10)
        start = time.monotonic()
        with entry_lock(entry, timeout=5) as waited:
            assert not waited and time.monotonic() - start < 1
    finally:
        holder.kill()
        holder.wait()


def test_a_compiled_library_that_does_not_load_is_evicted_and_rebuilt_once(cache):
    from ocpkit.codegen import compiled

    fn = square_fn()
    library = compiled._library(fn, "-O1")  # compiled, not loaded by this process
    write_entry(library, b"\x7fELF\x01\x01\x01" + bytes(9) + b"\x03\x00\x03\x00" + bytes(200))  # a 32-bit ELF
    with pytest.warns(RuntimeWarning, match="does not load.*wrong ELF class.*building it again"):
        f = compile_function(fn)
    np.testing.assert_allclose(np.asarray(f([1.0, 2.0])).ravel(), [2.0, 5.0])
    assert entry_ok(library) and library.read_bytes()[4] == 2  # ELFCLASS64


def test_a_killed_compiler_is_named(cache, tmp_path, monkeypatch):
    killed = tmp_path / "killed-cc"
    killed.write_text("#!/bin/sh\nkill -KILL $$\n")
    killed.chmod(0o755)
    monkeypatch.setenv("CC", str(killed))
    with pytest.raises(CompileError, match="the compiler was killed by SIGKILL"):
        compile_function(square_fn())
