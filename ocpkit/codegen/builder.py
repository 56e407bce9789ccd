"""Building generated code into the cache, one path for compiled models (:mod:`ocpkit.codegen.compiled`) and LinearMPC's
C steps (:mod:`ocpkit.export.native`).

An entry is keyed by the hash of what it is built from, the build's settings and the platform (:func:`entry_key`: a
cache shared by machines of two architectures keeps one library for each). It is built at most once machine-wide
(:func:`build_entry`, under the entry's lock; a damaged entry is rebuilt with a warning), built in the background by a
child process of ocpkit's own (:func:`spawn`, its failure read back by :func:`child_failure`) at lower priority, checked
against its recorded content hash (:func:`ocpkit.codegen.cache.entry_ok`) and loaded only once it proves loadable
(:func:`loadable`: one that does not load is removed and built once more).
"""

from __future__ import annotations

import hashlib
import os
import platform
import signal
import subprocess
import sys
import warnings
from pathlib import Path

from ocpkit.codegen.cache import CacheReadOnlyError, entry_lock, entry_ok, evict, load_problem, read_only_error

_PLATFORM = f"|{sys.platform}|{platform.machine()}"


def entry_key(*parts: bytes) -> str:
    """The cache key of an entry built from ``parts`` (sources, settings) on this platform."""
    h = hashlib.sha256()
    for part in parts:
        h.update(part)
    h.update(_PLATFORM.encode())
    return h.hexdigest()[:20]


def signal_name(number: int) -> str:
    """``SIGKILL`` for 9: how a killed build is named."""
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"


def build_entry(library: Path, build, what: str | None = None) -> None:
    """Run ``build()`` to make ``library`` unless a sound one is there, under the entry's lock: where another process
    built it meanwhile, nothing is built. With ``what``, a damaged library is named in a warning
    (:func:`warn_damaged`) before it is rebuilt. :class:`ocpkit.codegen.cache.CacheReadOnlyError` where the cache is
    read-only."""
    if entry_ok(library):
        return
    with entry_lock(library.parent):
        if entry_ok(library):
            return
        if what is not None:
            warn_damaged(library, what, stacklevel=4)
        library.parent.mkdir(mode=0o700, exist_ok=True)
        build()


def warn_damaged(library: Path, what: str, stacklevel: int = 3) -> None:
    """A warning where ``library`` is there but damaged (its content does not match the hash recorded beside it)."""
    recorded = library.with_name(library.name + ".sha256")
    if library.exists() and (recorded.exists() or library.stat().st_size == 0):  # not from before hashes
        warnings.warn(
            f"damaged cache entry {library} ({what}): its content does not match the hash recorded "
            f"beside it; rebuilding it",
            RuntimeWarning,
            stacklevel=stacklevel,
        )


def loadable(library: Path, symbol: str, rebuild, what: str, error: type[Exception]) -> Path:
    """``library`` if it loads and has ``symbol``; else it is removed (a warning naming ``what``), ``rebuild()`` builds
    it once more and returns its path, and that one is returned, or ``error`` says why it does not load either. Where
    the cache is read-only the entry cannot be removed: :class:`ocpkit.codegen.cache.CacheReadOnlyError`."""
    seen = library.stat()
    problem = load_problem(library, symbol)
    if problem is None:
        return library
    try:
        evict(library, seen)
    except CacheReadOnlyError as exc:
        raise read_only_error(f"{what} ({library}) does not load ({problem})", library.parent.parent) from exc
    warnings.warn(
        f"cache entry {library} ({what}) does not load ({problem}): removed, building it again",
        RuntimeWarning,
        stacklevel=3,
    )
    library = rebuild()
    problem = load_problem(library, symbol)
    if problem is not None:
        raise error(f"{what}, built again into {library}, does not load: {problem}")
    return library


def spawn(module: str, *args: str, cwd: Path, **popen) -> subprocess.Popen:
    """A child process running ``module``'s ``_child(*args)`` with this ocpkit on its path, in a session of its own
    (its process group ends with it, and a child that should outlive this process does)."""
    path = [str(Path(__file__).resolve().parents[1]), os.environ.get("PYTHONPATH", "")]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in path if p)}
    command = [sys.executable, "-c", f"import sys; from {module} import _child; _child(*sys.argv[1:])", *args]
    return subprocess.Popen(command, env=env, cwd=cwd, start_new_session=True, stdin=subprocess.DEVNULL, **popen)


def child_failure(code: int, pid: int, output: str, what: str, error: type[Exception], kinds=()) -> Exception:
    """The exception of the build child ``pid`` that ended with status ``code``: killed by a signal, or the last line
    of its ``output`` (raised as one of ``kinds`` where the child printed one, e.g. ``ocpkit.codegen.cache.
    CacheReadOnlyError: …``), as ``error`` prefixed by ``what`` ("building X failed")."""
    if code < 0:
        return error(f"{what}: its build process (pid {pid}) was killed by {signal_name(-code)}")
    lines = [line for line in output.strip().splitlines() if line.strip()]
    last = lines[-1] if lines else f"exit status {code}"
    for kind in kinds:
        prefix = f"{kind.__module__}.{kind.__name__}: "
        if last.startswith(prefix):
            return kind(last.removeprefix(prefix))
    return error(f"{what}: {last[:300]}")
