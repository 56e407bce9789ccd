"""LinearMPC's compiled step: the exported C step (:mod:`ocpkit.export`) built without asking, cached by hash.

The Python step of the condensed knot QP spends most of a robot's step in per-call overheads (docs: Benchmarks, "The MPC
step on the CPU"). :func:`start` exports the step of an OCP (condensed form, DAQP, linearization about the input goal)
to a scratch folder — code generation in this process — and keys it by the hash of the generated files. A cached library
is used at once; otherwise a child process in a session of its own builds it with ``make`` at lower priority (``nice``
+10, one compile job, so a running control loop keeps a core) and moves it into the cache atomically with its content
hash beside it (a damaged entry is rebuilt; one that does not load is removed and built once more). The child outlives
this process if need be: a script shorter than the build finds the C step ready on its next run. Several controllers of
one OCP share one build, and so do processes: the builder holds the entry's lock file
(:func:`ocpkit.codegen.cache.entry_lock`), and another process's build child waits for it and finds the library built. A
read-only cache is used as it is: its sound library is loaded, and where it has none the Python step runs (one warning);
``ocpkit build`` fills a cache ahead of deployment.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import threading
import warnings
import weakref
from concurrent.futures import Future
from pathlib import Path

from ocpkit.codegen.builder import build_entry, child_failure, entry_key, loadable, signal_name, spawn, warn_damaged
from ocpkit.codegen.cache import (
    CacheReadOnlyError,
    UnsafeCacheError,
    cache_dir,
    check_trusted,
    entry_ok,
    install,
    load_problem,
    read_only,
    read_only_entry,
    read_only_error,
    scratch_dir,
    warn_read_only,
)
from ocpkit.codegen.compiled import compiler_available
from ocpkit.export import BuildError, check_tools, export
from ocpkit.export.digest import ocp_entries
from ocpkit.model.ocp import BACKGROUND_MIN_INSTRUCTIONS, OCP

NAME = "mpc"
SLOTS = 64  # controllers of one OCP live at once in one process (the library's QP-solver memory slots)
# The generated model and DAQP at -O1: a build far shorter than at the export's -O2, and a C step as fast (docs,
# Benchmarks, "The MPC step on the CPU"); the condensing keeps the export's -O3.
MAKE_VARS = (f"MAX_INSTANCES={SLOTS}", "OPT=-O1")

_builds: dict[str, Future] = {}  # by the hash of the generated files
# The hash of the generated files by (the OCP's digest, the step's settings): an equal OCP met again in this process
# (every trial of a study builds its own) is looked up without generating its code once more (0.1-0.4 s a time).
_keys: dict[tuple, str] = {}
_by_ocp: "weakref.WeakKeyDictionary[OCP, dict]" = weakref.WeakKeyDictionary()  # {settings: Future or None}
_builds_lock = threading.Lock()
_warned = set()


# The default builds the C step for knot QPs up to this many variables (knots × inputs): above it the C step's lead
# over the Python step fades, and the traditional QP is no faster in C (the generated DAQP starts cold and sets up
# every step) for a long code generation at construction and a large library (docs:
# Benchmarks, "The MPC step on the CPU").
MAX_VARIABLES = 256


def wanted(ocp: OCP) -> bool:
    """Whether the OCP's ``compiled`` policy asks for the C step: True, or None (the default) for a model as large as
    :data:`ocpkit.model.ocp.BACKGROUND_MIN_INSTRUCTIONS` (below it the Python step is already fast), a knot QP of at
    most :data:`MAX_VARIABLES` variables and no obstacles. The obstacles are constants of the generated C, so each
    placement is a build of its own, where a study's seeds each place theirs: the C step
    with obstacles is built when asked (``native=True``, ``compiled=True``)."""
    if ocp.compiled is not None:
        return ocp.compiled
    tf = ocp.task_functions
    return (
        not ocp.model.linear
        and ocp.model.jacobian.n_instructions() >= BACKGROUND_MIN_INSTRUCTIONS
        and ocp.knots * ocp.nu <= MAX_VARIABLES
        and (tf is None or not tf.pairs)
    )


def start(
    ocp: OCP,
    *,
    eps: float,
    max_iter: int,
    wait: bool = False,
    linearization: str = "goal",
    iterations: int = 1,
    tol: float = 0.0,
) -> Future | None:
    """A Future of the folder holding ``lib<NAME>.so``, the exported condensed DAQP step of ``ocp`` (DAQP tolerance
    ``eps``, ``max_iter`` iterations; ``linearization``, ``iterations`` and ``tol`` as :func:`ocpkit.export.export`
    takes them: "trajectory" is the real-time iteration's step).

    A sound cached library that loads is used as it is: no compiler needed, and the cache may be read-only. One
    whose hash matches but which does not load (another machine's, a damaged one) is removed and built once more.
    Otherwise it is built — ``wait``: here and now (BuildError if it cannot be, :class:`ocpkit.codegen.cache.
    CacheReadOnlyError` where the cache is read-only); else in the background — and the result is None where
    it cannot be: ``cc`` or ``make`` missing (one warning for ``make``: a missing compiler is said once by
    :mod:`ocpkit.codegen.compiled` when the Python step's model cannot be compiled either), or a read-only cache (one
    warning per process, :func:`ocpkit.codegen.cache.warn_read_only`)."""
    runs = _by_ocp.setdefault(ocp, {})
    settings = (eps, max_iter, linearization, iterations, tol)
    known = runs.get(settings, False)
    if known is None and not wait:
        return None
    if known and not (wait and known.done() and known.exception() is not None):
        if wait:
            known.result()
        return known
    future = runs[settings] = _start(ocp, settings, wait)
    return future


def built(ocp: OCP) -> list[Path]:
    """The cache folders of the C steps built (or found) for ``ocp`` in this process, each holding ``lib<NAME>.so``."""
    return [
        f.result()
        for f in _by_ocp.get(ocp, {}).values()
        if f is not None and f.done() and not f.cancelled() and f.exception() is None
    ]


def _start(ocp: OCP, settings: tuple, wait: bool) -> Future | None:
    """:func:`start` for an OCP met the first time: export, hash, then the cached library or a build; an equal OCP's
    build or library in this process without exporting again."""
    identity = (tuple(ocp_entries(ocp)), settings)
    with _builds_lock:
        known = _builds.get(_keys.get(identity))
    if known is not None and not (known.done() and known.exception() is not None):
        if wait:
            known.result()
        return known
    root = cache_dir("native")
    try:
        scratch, key, unwritable = _generate(ocp, settings, root)
        _keys[identity] = key
    except CacheReadOnlyError as error:  # not even generated: a read-only (or full) cache and temporary folder
        if wait:
            raise
        warn_read_only(error, "LinearMPC runs its Python step", stacklevel=4)
        return None
    folder = root / key
    with _builds_lock:
        future = _builds.get(key)
        shared = future is not None and not (wait and future.done() and future.exception() is not None)
        if not shared:
            future = _builds[key] = Future()
            future.set_running_or_notify_cancel()
    if shared:
        shutil.rmtree(scratch, ignore_errors=True)
        if wait:
            future.result()
        return future
    try:
        check_trusted(folder / f"lib{NAME}.so")  # refused before anything is loaded from it or built into it
        if unwritable is not None:
            shutil.rmtree(scratch, ignore_errors=True)
            read_only_entry(
                folder / f"lib{NAME}.so", f"{NAME}_step_timed", "LinearMPC's C step for this OCP", unwritable
            )
            future.set_result(folder)
            return future
        if not entry_ok(folder / f"lib{NAME}.so"):
            check_tools()  # a sound cached library needs neither cc nor make
    except (CacheReadOnlyError, BuildError, UnsafeCacheError) as exc:
        shutil.rmtree(scratch, ignore_errors=True)
        with _builds_lock:
            if _builds.get(key) is future:
                del _builds[key]
        future.set_exception(exc)
        if wait or isinstance(exc, UnsafeCacheError):
            raise
        if isinstance(exc, CacheReadOnlyError):
            warn_read_only(exc, "LinearMPC runs its Python step", stacklevel=4)
        elif compiler_available() and str(exc) not in _warned:
            _warned.add(str(exc))
            warnings.warn(f"LinearMPC keeps its Python step: {exc}", RuntimeWarning, stacklevel=4)
        return None
    if wait:
        _build(scratch, folder, future, background=False)
        future.result()
    else:
        # The build's child process starts here, not in the thread: a script that exits right after the
        # constructor ends its daemon threads, and one that had not spawned the child yet left the build undone.
        child = None if entry_ok(folder / f"lib{NAME}.so") else _spawn(scratch, folder)
        threading.Thread(
            target=_build, args=(scratch, folder, future, True, child), name=f"ocpkit-native-{key[:8]}", daemon=True
        ).start()
    return future


def _generate(ocp: OCP, settings: tuple, root: Path) -> tuple[Path, str, OSError | None]:
    """Export the C step of ``ocp`` to a scratch folder and key it: (scratch, key, None) with the scratch folder in
    the cache, where a build is installed by a rename; where the cache cannot be written (read-only, or full: the
    export's files do not fit), generated all the same to a temporary folder, its key naming the entry to look for,
    with the cache's error last. :class:`ocpkit.codegen.cache.CacheReadOnlyError` where no temporary folder can be
    written either."""
    try:
        scratch = scratch_dir(root, f".build-{os.getpid()}-")
        return scratch, _export(ocp, settings, scratch), None
    except OSError as exc:
        if not read_only(exc):
            raise
        unwritable = exc
    try:
        scratch = Path(tempfile.mkdtemp(prefix="ocpkit-native-"))
        return scratch, _export(ocp, settings, scratch), unwritable
    except OSError as exc:  # a read-only or full cache without a writable temporary folder
        raise read_only_error(
            f"LinearMPC's C step cannot be looked up: its code is generated to a temporary "
            f"folder, and none can be written ({exc.strerror or exc}; set TMPDIR)",
            root,
            unwritable,
        ) from None


def _export(ocp: OCP, settings: tuple, scratch: Path) -> str:
    """The key of the C step of ``ocp`` exported to ``scratch``/src (``scratch`` removed if that fails)."""
    eps, max_iter, linearization, iterations, tol = settings
    try:
        export(
            ocp,
            scratch / "src",
            name=NAME,
            qp="daqp",
            eps=eps,
            max_iter=max_iter,
            linearization=linearization,
            iterations=iterations,
            tol=tol,
        )
        return _key(scratch / "src")
    except BaseException:
        shutil.rmtree(scratch, ignore_errors=True)
        raise


def _key(source: Path) -> str:
    """The cache key of the generated files and the build's settings (:func:`ocpkit.codegen.builder.entry_key`)."""
    files = (path.name.encode() + b"\0" + path.read_bytes() for path in sorted(source.iterdir()))
    return entry_key(" ".join(MAKE_VARS).encode(), *files)


def _load_problem(library: Path) -> str | None:
    """None if ``library`` loads in this process and has the C step's entry point, else why not."""
    return load_problem(library, f"{NAME}_step_timed")


def _build(
    scratch: Path, folder: Path, future: Future, background: bool = True, child: subprocess.Popen | None = None
) -> None:
    """Resolve ``future`` with ``folder`` once it holds a sound library that loads: the cached one, or one built
    from ``scratch``; a cached library that does not load is removed and built once more.

    In the background the build is a child process in a session of its own at lower priority: it finishes and
    fills the cache even when this process exits first (a short script's next run finds the C step ready). A
    caller that waits builds here at full priority (niced, a busy machine would slow its build manyfold).
    ``child``: that child, already started (:func:`_spawn`)."""
    library = folder / f"lib{NAME}.so"
    try:
        if child is None and entry_ok(library):  # cached: loaded as it is, or removed and built once more

            def rebuild() -> Path:
                _make(scratch, folder, background)
                return library

            loadable(library, f"{NAME}_step_timed", rebuild, "LinearMPC's C step", BuildError)
        else:
            if child is None:
                warn_damaged(library, "LinearMPC's C step")
            _make(scratch, folder, background, child)
            problem = _load_problem(library) if entry_ok(library) else "no sound library after the build"
            if problem is not None:
                raise BuildError(f"LinearMPC's C step {library}, built again, does not load: {problem}")
    except BaseException as exc:  # noqa: BLE001 - handed to the Future; LinearMPC warns and keeps its Python step
        shutil.rmtree(scratch, ignore_errors=True)
        future.set_exception(exc)
        return
    shutil.rmtree(scratch, ignore_errors=True)  # before the Future resolves: its waiter may exit at once
    future.set_result(folder)


def _spawn(scratch: Path, folder: Path) -> subprocess.Popen:
    """The background build's child process (:func:`_child`), in a session of its own so that it outlives us."""
    return spawn(
        "ocpkit.export.native",
        str(scratch),
        str(folder),
        cwd=scratch,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


def _make(scratch: Path, folder: Path, background: bool, child: subprocess.Popen | None = None) -> None:
    """Build the library of ``scratch`` into the cache ``folder`` (:func:`_install`): here, or in a child process
    at ``nice`` +10 in a session of its own (``child``, if already started). BuildError naming what failed, or
    which signal killed what."""
    check_tools()
    if not background:
        try:
            _install(scratch, folder)
        except BuildError as exc:
            raise BuildError(f"building LinearMPC's C step failed: {exc}") from None
        return
    child = child or _spawn(scratch, folder)
    code = child.wait()
    if code:
        error, log = scratch / "error", scratch / "build.log"
        output = error.read_text() if error.exists() else log.read_text() if log.exists() else ""
        raise child_failure(code, child.pid, output, "building LinearMPC's C step failed", BuildError)


def _child(scratch: str, folder: str) -> None:
    """The background build's child process: :func:`_install` at ``nice`` +10; a failure's one line in
    ``scratch``/error for the parent."""
    try:
        _install(scratch, folder, nice=True)
    except BaseException as exc:
        Path(scratch, "error").write_text(f"{exc}\n" if str(exc) else f"{type(exc).__name__}\n")
        raise SystemExit(1) from None


def _install(scratch: str | Path, folder: str | Path, nice: bool = False) -> None:
    """Build the exported step in ``scratch`` (``make``, niced if ``nice``) and move the library into the cache
    ``folder`` with its content hash beside it; then remove ``scratch``. Under the entry's lock: where another
    process built the library meanwhile, nothing is built. A failure leaves make's output in ``scratch``/build.log
    and raises BuildError with its last line, or naming the signal that killed make."""
    scratch, folder = Path(scratch), Path(folder)
    library = folder / f"lib{NAME}.so"

    def make():
        if nice:
            os.nice(10)
        with open(scratch / "build.log", "w") as log:
            code = subprocess.run(
                ["make", "-s", "-C", str(scratch / "src"), "-j1", "lib", *MAKE_VARS],
                stdout=log,
                stderr=subprocess.STDOUT,
            ).returncode
        if code < 0:
            raise BuildError(f"make was killed by {signal_name(-code)}")
        if code:
            lines = (scratch / "build.log").read_text().strip().splitlines()
            raise BuildError(lines[-1] if lines else f"make exit status {code}")
        install(scratch / "src" / f"lib{NAME}.so", library)

    build_entry(library, make)
    shutil.rmtree(scratch, ignore_errors=True)
