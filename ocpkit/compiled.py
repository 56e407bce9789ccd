"""CasADi Functions code-generated to C, compiled with the system compiler and loaded back.

The SX virtual machine evaluates a 13-link robot's RK4 affine model (264k instructions) in about 0.6 ms; the
same Function compiled at -O1 takes about 0.3 ms, at the price of a one-off compile of tens of seconds,
cached on disk by the Function's hash so it is paid once per model. The library is checked against the content
hash recorded beside it before it is loaded; a damaged one (truncated, empty) is rebuilt with a warning.
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import subprocess
import tempfile
import warnings
from pathlib import Path

import casadi as ca

from ocpkit.cache import _atomic_write, cache_dir, digest, entry_ok


class CompileError(RuntimeError):
    """The C compiler is missing or failed; the message is one line saying which."""


def compile_function(fn: ca.Function, flags: str = "-O1") -> ca.Function:
    """``fn`` as compiled C (same inputs, outputs and results), built once and cached."""
    if not isinstance(fn, ca.Function):
        raise TypeError(f"fn must be a casadi.Function, got {type(fn).__name__}")
    key = hashlib.sha256((fn.serialize() + flags).encode()).hexdigest()[:20]
    folder = cache_dir("compiled") / key
    library = folder / f"{fn.name()}.so"
    if not entry_ok(library):
        recorded = library.with_name(library.name + ".sha256")
        if library.exists() and (recorded.exists() or library.stat().st_size == 0):  # not merely from before hashes
            warnings.warn(f"damaged compiled cache entry {library} (its content does not match the hash recorded "
                          f"beside it): rebuilding it", RuntimeWarning, stacklevel=2)
        _build(fn, flags, folder, library)
    return ca.external(fn.name(), str(library))


def _build(fn: ca.Function, flags: str, folder: Path, library: Path) -> None:
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    # Generate and build in a private scratch folder, then rename: a concurrent process never compiles a
    # half-written source nor loads a half-written library, and a failed build leaves nothing behind.
    scratch = Path(tempfile.mkdtemp(dir=folder, prefix=".build-"))
    try:
        source = f"{fn.name()}.c"
        generator = ca.CodeGenerator(source, {"with_header": False})
        generator.add(fn)
        generator.generate(str(scratch) + os.sep)
        partial = scratch / library.name
        compiler = os.environ.get("CC", "cc")
        try:
            subprocess.run([compiler, *flags.split(), "-fPIC", "-shared", str(scratch / source), "-o", str(partial),
                            "-lm"], check=True, capture_output=True, text=True)
        except FileNotFoundError:
            raise CompileError(f"compiling {fn.name()} needs a C compiler, and `{compiler}` was not found on PATH: "
                               f"install one (e.g. apt install gcc) or run without --compiled") from None
        except subprocess.CalledProcessError as exc:
            message = " ".join(exc.stderr.split())[:300]
            raise CompileError(f"compiling {fn.name()} with `{compiler}` failed: {message}") from None
        _atomic_write(library.with_name(library.name + ".sha256"), digest(partial.read_bytes()).encode())
        os.replace(partial, library)
        with contextlib.suppress(OSError):
            shutil.copy(scratch / source, folder / source)  # kept for the curious reader; never compiled from
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
