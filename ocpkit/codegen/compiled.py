"""CasADi Functions code-generated to C, compiled with the system compiler and loaded back.

Compiled at -O1, a Function evaluates faster than on CasADi's SX virtual machine (docs, Benchmarks), at the price
of a one-off compile, cached on disk by the Function's hash so it is paid once per model. The library is checked against
the content hash recorded beside it before it is loaded; a damaged one (truncated, empty) is rebuilt with a warning, and
one that does not load (another machine's) is removed and compiled once more. One compile per entry machine-wide: the
compiler runs under the entry's lock (:func:`ocpkit.codegen.cache.entry_lock`). A read-only cache is used as it is; a
Function it lacks raises :class:`ocpkit.codegen.cache.CacheReadOnlyError` (in the background: the VM, one warning).

:func:`compile_in_background` runs that compile in a child process at lower priority (``nice`` +10), and
:class:`SwitchingFunction` evaluates the Function on the virtual machine until the compiled twin is ready, then on the
twin: the default path of ``OCP.affine``. The child does the hashing and the code generation as well as the compiler: in
the parent a large model's serialization became a Python string that was copied and encoded with the GIL held, pausing a
running control loop; the parent now only writes the Function to a file with ``Function.save`` (C++, GIL released) and
loads the finished library.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import shutil
import signal
import subprocess
import tempfile
import threading
import warnings
import weakref
from concurrent.futures import Future
from pathlib import Path

import casadi as ca

from ocpkit.codegen.builder import build_entry, child_failure, entry_key, loadable, signal_name, spawn
from ocpkit.codegen.cache import (
    CacheReadOnlyError,
    cache_dir,
    check_trusted,
    entry_problem,
    install,
    read_only,
    read_only_entry,
    warn_read_only,
)


class CompileError(RuntimeError):
    """The C compiler is missing or failed; the message is one line saying which."""


def compile_function(fn: ca.Function, flags: str = "-O1") -> ca.Function:
    """``fn`` as compiled C (same inputs, outputs and results), built once and cached."""
    if not isinstance(fn, ca.Function):
        raise TypeError(f"fn must be a casadi.Function, got {type(fn).__name__}")
    return _load(fn.name(), _library(fn, flags), lambda: _library(fn, flags))


def prebuild(fn: ca.Function, flags: str = "-O1") -> Path:
    """The cached library of ``fn`` compiled with ``flags`` (what the default background compile of an OCP's
    affine model loads), compiled first unless a sound one that loads is there; ``ocpkit build`` fills a cache
    with it ahead of deployment."""
    if not isinstance(fn, ca.Function):
        raise TypeError(f"fn must be a casadi.Function, got {type(fn).__name__}")
    library = _library(fn, flags)
    _load(fn.name(), library, lambda: _library(fn, flags))
    return library


def _load(name: str, library: Path, rebuild) -> ca.Function:
    """``ca.external`` of the cached ``library`` once it proves loadable (:func:`ocpkit.codegen.builder.loadable`: one
    that does not load is removed and ``rebuild()`` compiles it once more)."""
    return ca.external(name, str(loadable(library, name, rebuild, f"the compiled function {name!r}", CompileError)))


def _entry(fn: ca.Function, flags: str) -> Path:
    """Where the library of ``fn`` compiled with ``flags`` is cached (keyed by the serialized Function), once the
    folders down to it and the library are proved safe to load from (:func:`ocpkit.codegen.cache.check_trusted`)."""
    library = cache_dir("compiled") / entry_key(fn.serialize().encode(), flags.encode()) / f"{fn.name()}.so"
    check_trusted(library)
    return library


def _cached(fn: ca.Function, flags: str) -> ca.Function | None:
    """The compiled twin of ``fn`` from a sound cache entry that loads, or None (absent, damaged, not loading: the
    background compile sees to it)."""
    library = _entry(fn, flags)
    if entry_problem(library, fn.name()) is not None:
        return None
    return ca.external(fn.name(), str(library))


def _library(fn: ca.Function, flags: str) -> Path:
    """The cached library of ``fn`` compiled with ``flags``, built first (:func:`ocpkit.codegen.builder.build_entry`)
    unless a sound one is there; :class:`CacheReadOnlyError` where it is not and the cache is read-only or full."""
    library = _entry(fn, flags)
    try:
        build_entry(library, lambda: _build(fn, flags, library.parent, library), "a compiled function")
    except OSError as exc:  # CacheReadOnlyError, or a write on a full file system
        if not read_only(exc):
            raise
        return read_only_entry(library, fn.name(), f"the compiled function {fn.name()!r}", exc)
    return library


def _build(fn: ca.Function, flags: str, folder: Path, library: Path) -> None:
    # Generate and build in a private scratch folder, then rename: a concurrent process never compiles a
    # half-written source nor loads a half-written library, and a failed build leaves nothing behind.
    scratch = Path(tempfile.mkdtemp(dir=folder, prefix=f".build-{os.getpid()}-"))
    try:
        source = f"{fn.name()}.c"
        generator = ca.CodeGenerator(source, {"with_header": False})
        generator.add(fn)
        generator.generate(str(scratch) + os.sep)
        partial = scratch / library.name
        compiler = os.environ.get("CC", "cc")
        try:
            _run_compiler(
                [compiler, *flags.split(), "-fPIC", "-shared", str(scratch / source), "-o", str(partial), "-lm"],
                scratch,
            )
        except FileNotFoundError:
            raise CompileError(
                f"compiling {fn.name()} needs a C compiler, and `{compiler}` was not found on PATH: "
                f"install one (e.g. apt install gcc) or run without --compiled"
            ) from None
        except subprocess.CalledProcessError as exc:
            if exc.returncode < 0:
                raise CompileError(
                    f"compiling {fn.name()} with `{compiler}` failed: the compiler was killed by "
                    f"{signal_name(-exc.returncode)}"
                ) from None
            message = " ".join(exc.stderr.split())[:300]
            raise CompileError(f"compiling {fn.name()} with `{compiler}` failed: {message}") from None
        install(partial, library)
        with contextlib.suppress(OSError):
            shutil.copy(scratch / source, folder / source)  # kept for the curious reader; never compiled from
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


_compiling: dict = {}  # running compiler processes -> their scratch folders (ended at interpreter exit)


def _run_compiler(command: list[str], scratch: Path) -> None:
    """subprocess.run(command, check=True) that a background compile cut short by the interpreter's exit does not
    outlive: the compiler is stopped and its scratch folder removed (see :func:`_stop_compilers`)."""
    with subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        code, out, err = _tracked(proc, scratch)
    if code:
        raise subprocess.CalledProcessError(code, command, out, err)


def _tracked(proc: subprocess.Popen, scratch: Path | None) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of ``proc``, listed in ``_compiling`` while it runs (``scratch`` its folder, or
    None for a background compile's child process) so that the interpreter's exit ends it."""
    _compiling[proc] = scratch
    try:
        out, err = proc.communicate()
    finally:
        _compiling.pop(proc, None)
    return proc.returncode, out, err


@atexit.register
def _stop_compilers() -> None:
    for proc, scratch in list(_compiling.items()):
        if scratch is None:  # a background compile's child process: its own group, with its compiler
            with contextlib.suppress(OSError):
                os.killpg(proc.pid, signal.SIGKILL)
            with contextlib.suppress(Exception):
                proc.wait(5)
            for left in cache_dir("compiled").glob(f"*/.build-{proc.pid}-*"):
                shutil.rmtree(left, ignore_errors=True)
            continue
        with contextlib.suppress(OSError):
            proc.kill()
            proc.wait(5)
        shutil.rmtree(scratch, ignore_errors=True)


def _compile_out_of_process(fn: ca.Function, flags: str = "-O1") -> ca.Function:
    """:func:`compile_function` (``fn``, ``flags``) with the hashing, code generation and compiler in a child process
    (its own process group, ``nice`` +10); the Function reaches it through ``Function.save``."""
    return _load(fn.name(), _library_out_of_process(fn, flags), lambda: _library_out_of_process(fn, flags))


def _library_out_of_process(fn: ca.Function, flags: str) -> Path:
    """:func:`_library` (``fn``, ``flags``) in a child process."""
    with tempfile.TemporaryDirectory(prefix="ocpkit-compile-") as tmp:
        saved = Path(tmp) / f"{fn.name()}.casadi"
        fn.save(str(saved))
        with spawn(
            "ocpkit.codegen.compiled",
            str(saved),
            flags,
            cwd=Path(tmp),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        ) as proc:
            code, out, err = _tracked(proc, None)
    if code:
        raise child_failure(
            code,
            proc.pid,
            err,
            f"the background compile of {fn.name()} failed",
            CompileError,
            (CompileError, CacheReadOnlyError),
        )
    return Path(out.strip().splitlines()[-1])


def _child(saved: str, flags: str) -> None:
    """The background compile's child process: build (or find) the library of the saved Function, print its path."""
    os.nice(10)
    print(_library(ca.Function.load(saved), flags), flush=True)


_background: "weakref.WeakKeyDictionary[ca.Function, Future]" = weakref.WeakKeyDictionary()
_background_lock = threading.Lock()


def compiler_available() -> bool:
    """Whether the C compiler ``$CC`` (default ``cc``) is on PATH."""
    return shutil.which(os.environ.get("CC", "cc")) is not None


def compile_in_background(fn: ca.Function, flags: str = "-O1") -> Future | None:
    """A Future of :func:`compile_function` (``fn``, ``flags``) computed in a daemon thread (done at once where the
    cache holds it), one per Function object (a second call returns the same Future); None, with one warning, where
    no C compiler is on PATH. A compile that fails resolves the Future with its :class:`CompileError` (or OSError);
    :class:`SwitchingFunction` then warns once and stays on the virtual machine."""
    if not isinstance(fn, ca.Function):
        raise TypeError(f"fn must be a casadi.Function, got {type(fn).__name__}")
    with _background_lock:
        future = _background.get(fn)
        if future is not None:
            return future
        # A sound cached library is loaded at once (tens of ms: the key hashes the serialized Function; no compiler
        # needed), so that a controller built on a warm cache starts on compiled code instead of rebuilding itself
        # when a background load lands.
        cached = _cached(fn, flags)
        if cached is not None:
            _background[fn] = future = Future()
            future.set_result(cached)
            return future
        if not compiler_available():
            warnings.warn(
                f"no C compiler (`{os.environ.get('CC', 'cc')}`) on PATH: {fn.name()} stays on CasADi's "
                f"virtual machine (install one, e.g. apt install gcc, for the compiled model)",
                RuntimeWarning,
                stacklevel=3,
            )
            _background[fn] = future = Future()
            future.set_exception(CompileError("no C compiler on PATH"))
            future.warned = True
            return None
        future = Future()
        future.set_running_or_notify_cancel()
        _background[fn] = future

    def work():
        try:
            future.set_result(_compile_out_of_process(fn, flags))
        except BaseException as exc:  # noqa: BLE001 - handed to the Future, reported by SwitchingFunction
            future.set_exception(exc)

    threading.Thread(target=work, name=f"ocpkit-compile-{fn.name()}", daemon=True).start()
    return future


class SwitchingFunction(ca.Function):
    """``fn`` (CasADi's virtual machine) until ``future`` holds its compiled twin, then the twin (through
    ``transform``, e.g. a map of it): same inputs, outputs and results. Calls, :meth:`buffer` (bound once, as
    :class:`ocpkit.numeric.BufferedFunction` does; the switch rebinds the same arrays) and :meth:`map` switch
    by themselves at the first evaluation after the compile finished. A failed compile: one warning, the VM."""

    def __init__(self, fn: ca.Function, future: Future, transform=None):
        ca.Function.__init__(self, fn)
        self._future = future
        self._transform = transform
        self._target = None
        self._failed = False

    def compiled(self) -> ca.Function | None:
        """The compiled twin if the background compile has finished (and succeeded), else None."""
        if self._target is None and not self._failed and self._future.done():
            exc = self._future.exception()
            if exc is not None:
                self._failed = True
                if isinstance(exc, CacheReadOnlyError) and not getattr(self._future, "warned", False):
                    self._future.warned = True
                    warn_read_only(exc, f"{self.name()} stays on CasADi's virtual machine", stacklevel=3)
                if not getattr(self._future, "warned", False):
                    self._future.warned = True
                    warnings.warn(
                        f"{self.name()} stays on CasADi's virtual machine: {exc}", RuntimeWarning, stacklevel=3
                    )
                return None
            target = self._future.result()
            self._target = target if self._transform is None else self._transform(target)
        return self._target

    def wait(self, timeout: float | None = None) -> ca.Function | None:
        """Block until the background compile has finished (tests, benchmarks); the twin or None if it failed."""
        with contextlib.suppress(Exception):
            self._future.exception(timeout)
        return self.compiled()

    def __call__(self, *args, **kwargs):
        target = self.compiled()
        return ca.Function.__call__(self if target is None else target, *args, **kwargs)

    def buffer(self):
        switch = _SwitchingBuffer(self)
        return switch, switch.evaluate

    def map(self, *args):
        target = self.compiled()
        if target is not None:
            return target.map(*args)
        transform = self._transform
        return SwitchingFunction(
            ca.Function.map(self, *args), self._future, lambda f: (f if transform is None else transform(f)).map(*args)
        )

    def __reduce__(self):  # pickled as the plain Function it currently evaluates as
        target = self.compiled()
        return (target if target is not None else ca.Function(self)).__reduce__()


class _SwitchingBuffer:
    """A FunctionBuffer that starts as the VM's and rebinds its arrays to the compiled twin's once it is ready."""

    def __init__(self, owner: SwitchingFunction):
        self._owner = owner
        self._buffer, self._evaluate = ca.Function.buffer(owner)
        self._args, self._res = {}, {}
        self.switched = False

    def set_arg(self, i, view):
        self._args[i] = view
        self._buffer.set_arg(i, view)

    def set_res(self, i, view):
        self._res[i] = view
        self._buffer.set_res(i, view)

    def evaluate(self):
        if not self.switched:
            target = self._owner.compiled()
            if target is not None:
                buffer, evaluate = target.buffer()
                for i, view in self._args.items():
                    buffer.set_arg(i, view)
                for i, view in self._res.items():
                    buffer.set_res(i, view)
                self._buffer, self._evaluate, self.switched = buffer, evaluate, True
            elif self._owner._failed:
                self.switched = True  # the VM for good: no further checks
        self._evaluate()
