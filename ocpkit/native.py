"""LinearMPC's compiled step: the exported C step (:mod:`ocpkit.export`) built without asking, cached by hash.

The Python step of the condensed knot QP spends most of a robot's step in per-call overheads (nlink:13, T = 100:
0.8 ms in Python, 0.3 ms as the exported C step). :func:`start` exports the step of an OCP (condensed form,
DAQP, linearization about the input goal) to a scratch folder — code generation in this process, 0.1 s at
nlink:13 — and keys it by the hash of the generated files. A cached library is used at once; otherwise a child
process in a session of its own builds it with ``make`` at lower priority (``nice`` +10, one compile job, so a
running control loop keeps a core) and moves it into the cache atomically with its content hash beside it (a
damaged entry is rebuilt). The child outlives this process if need be: a script shorter than the build finds the
C step ready on its next run. Several controllers of one OCP share one build.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import warnings
import weakref
from concurrent.futures import Future
from pathlib import Path

from ocpkit.cache import cache_dir, entry_ok, install
from ocpkit.compiled import compiler_available
from ocpkit.export import BuildError, check_tools, export
from ocpkit.ocp import BACKGROUND_MIN_INSTRUCTIONS, OCP

NAME = "mpc"
SLOTS = 64  # controllers of one OCP live at once in one process (the library's QP-solver memory slots)
# The generated model and DAQP at -O1: nlink:13 builds in 3.6 s instead of 8.8 s at the export's -O2, and its
# C step ran as fast (0.222 vs 0.222 ms); the condensing keeps the export's -O3.
MAKE_VARS = (f"MAX_INSTANCES={SLOTS}", "OPT=-O1")

_builds: dict[str, Future] = {}  # by the hash of the generated files
_by_ocp: "weakref.WeakKeyDictionary[OCP, dict]" = weakref.WeakKeyDictionary()  # {(eps, max_iter): Future}
_builds_lock = threading.Lock()
_warned = set()


# The default builds the C step for knot QPs up to this many variables (knots × inputs). nlink:13, T = 100, C step
# against the Python step: 65 variables 0.29 vs 0.81 ms, 130: 1.14 vs 1.55, 260: 6.0 vs 7.1, 520: 40 vs 46; the
# traditional QP (p = T = 100, 1300 variables) no faster (the generated DAQP starts cold and sets up every step)
# and 2.5 s of code generation at construction, a 27 MB library.
MAX_VARIABLES = 256


def wanted(ocp: OCP) -> bool:
    """Whether the OCP's ``compiled`` policy asks for the C step: True, or None (the default) for a model as large as
    :data:`ocpkit.ocp.BACKGROUND_MIN_INSTRUCTIONS` (below it the Python step is already fast) and a knot QP of at
    most :data:`MAX_VARIABLES` variables."""
    if ocp.compiled is not None:
        return ocp.compiled
    return (not ocp.model.linear and ocp.model.jacobian.n_instructions() >= BACKGROUND_MIN_INSTRUCTIONS
            and ocp.knots * ocp.nu <= MAX_VARIABLES)


def start(ocp: OCP, *, eps: float, max_iter: int, wait: bool = False) -> Future | None:
    """A Future of the folder holding ``lib<NAME>.so``, the exported condensed DAQP step of ``ocp`` (DAQP tolerance
    ``eps``, ``max_iter`` iterations). ``wait``: built here and now (BuildError if it cannot be); otherwise built in
    the background, and None where ``cc`` or ``make`` is missing (one warning for ``make``: a missing compiler is
    said once by :mod:`ocpkit.compiled` when the Python step's model cannot be compiled either)."""
    try:
        check_tools()
    except BuildError as exc:
        if wait:
            raise
        if compiler_available() and str(exc) not in _warned:
            _warned.add(str(exc))
            warnings.warn(f"LinearMPC keeps its Python step: {exc}", RuntimeWarning, stacklevel=3)
        return None
    known = _by_ocp.get(ocp, {}).get((eps, max_iter))
    if known is not None and not (wait and known.done() and known.exception() is not None):
        if wait:
            known.result()
        return known
    future = _start(ocp, eps, max_iter, wait)
    _by_ocp.setdefault(ocp, {})[(eps, max_iter)] = future
    return future


def _start(ocp: OCP, eps: float, max_iter: int, wait: bool) -> Future:
    """:func:`start` for an OCP met the first time: export, hash, and build unless a build of that hash exists."""
    root = cache_dir("native")
    scratch = Path(tempfile.mkdtemp(dir=root, prefix=f".build-{os.getpid()}-"))
    try:
        export(ocp, scratch / "src", name=NAME, qp="daqp", eps=eps, max_iter=max_iter, linearization="goal")
    except BaseException:
        shutil.rmtree(scratch, ignore_errors=True)
        raise
    key = _key(scratch / "src")
    with _builds_lock:
        future = _builds.get(key)
        if future is None or (future.done() and future.exception() is not None and wait):
            future = _builds[key] = Future()
            future.set_running_or_notify_cancel()
            owner = True
        else:
            owner = False
    if not owner:
        shutil.rmtree(scratch, ignore_errors=True)
    elif wait:
        _build(scratch, root / key, future, background=False)
    else:
        threading.Thread(target=_build, args=(scratch, root / key, future), name=f"ocpkit-native-{key[:8]}",
                         daemon=True).start()
    if wait:
        future.result()
    return future


def _key(source: Path) -> str:
    """The hash of the generated files and of the build's settings."""
    h = hashlib.sha256(" ".join(MAKE_VARS).encode())
    for path in sorted(source.iterdir()):
        h.update(path.name.encode() + b"\0" + path.read_bytes())
    return h.hexdigest()[:20]


def _build(scratch: Path, folder: Path, future: Future, background: bool = True) -> None:
    """Resolve ``future`` with ``folder`` once it holds a sound library: the cached one, or one built from ``scratch``.

    In the background the build is a child process in a session of its own at lower priority: it finishes and
    fills the cache even when this process exits first (a short script's next run finds the C step ready). A
    caller that waits builds here at full priority (niced on a busy machine the Panda's build took 33 s, not 4)."""
    try:
        library = folder / f"lib{NAME}.so"
        if not entry_ok(library):
            if library.exists():
                warnings.warn(f"damaged cache entry {library} (its content does not match the hash recorded beside "
                              f"it): rebuilding it", RuntimeWarning, stacklevel=2)
            if not background:
                _install(str(scratch), str(folder), "")
            else:
                path = [str(Path(__file__).resolve().parents[1]), os.environ.get("PYTHONPATH", "")]
                env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in path if p)}
                command = [sys.executable, "-c", "import sys; from ocpkit.native import _install; "
                           "_install(*sys.argv[1:])", str(scratch), str(folder), "nice"]
                code = subprocess.run(command, env=env, cwd=scratch, start_new_session=True,
                                      stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL).returncode
                if code:
                    log = scratch / "build.log"
                    lines = log.read_text().strip().splitlines() if log.exists() else []
                    raise BuildError(f"building LinearMPC's C step failed: {lines[-1] if lines else code}")
    except BaseException as exc:  # noqa: BLE001 - handed to the Future; LinearMPC warns and keeps its Python step
        shutil.rmtree(scratch, ignore_errors=True)
        future.set_exception(exc)
        return
    shutil.rmtree(scratch, ignore_errors=True)  # before the Future resolves: its waiter may exit at once
    future.set_result(folder)


def _install(scratch: str, folder: str, nice: str) -> None:
    """Build the exported step in ``scratch`` (``make``, niced if ``nice``) and move the library into the cache
    ``folder`` with its content hash beside it; then remove ``scratch``. A failure leaves its last line in
    ``scratch``/build.log."""
    scratch, folder = Path(scratch), Path(folder)
    if nice:
        os.nice(10)
    with open(scratch / "build.log", "w") as log:
        code = subprocess.run(["make", "-s", "-C", str(scratch / "src"), "-j1", "lib", *MAKE_VARS],
                              stdout=log, stderr=subprocess.STDOUT).returncode
    if code:
        lines = (scratch / "build.log").read_text().strip().splitlines()
        raise BuildError(lines[-1] if lines else f"make exit status {code}")
    folder.mkdir(mode=0o700, exist_ok=True)
    install(scratch / "src" / f"lib{NAME}.so", folder / f"lib{NAME}.so")
    shutil.rmtree(scratch, ignore_errors=True)
