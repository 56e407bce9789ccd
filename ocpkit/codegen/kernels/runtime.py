"""The Taichi runtime: started once per process, on CUDA or the CPU.

``ti.init`` may run only once: a second call would destroy every array and compiled kernel
that live controllers hold. So the first caller picks the arch and later callers must agree.
Precision is not a process-wide setting here: every array and generated function carries
its own float type, so float32 and float64 controllers can coexist.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
import os
import sys
import threading
from pathlib import Path

import numpy as np
import taichi as ti
from taichi.lang import impl

from ocpkit._checks import choice
from ocpkit.codegen.kernels import CPU_THREADS

ARCHS = ("auto", "cpu", "cuda")


class ArchUnavailable(RuntimeError):
    """The asked-for arch does not exist on this machine (``cuda`` without a GPU)."""


PRECISIONS = ("float64", "float32")


def init(arch: str = "auto") -> str:
    """Start Taichi if needed and return the arch it runs on ("cpu" or "cuda").

    ``arch="auto"`` takes CUDA when Taichi finds it, else the CPU. Asking for an arch other
    than the one already running raises ``RuntimeError``; asking for "cuda" where there is
    none raises :class:`ArchUnavailable` (a ``RuntimeError``) saying so, before Taichi starts
    when no CUDA driver is installed.
    """
    choice(arch, ARCHS, "arch")
    started_before = impl.get_runtime().prog is not None
    if not started_before:
        if arch == "cuda" and not _cuda_driver_present():
            raise ArchUnavailable(
                "arch 'cuda' needs an NVIDIA GPU and its CUDA driver, and this machine has none "
                "(libcuda.so.1 does not load): use --arch cpu, or --arch auto to take a GPU "
                "only where there is one"
            )
        use_cuda = arch == "cuda" or (arch == "auto" and _cuda_driver_present())
        # ti.init prints "[Taichi] Starting on arch=…" to stdout: keep stdout for results (--json).
        with contextlib.redirect_stdout(sys.stderr), _floating_point_kept():
            threads = {"cpu_max_num_threads": _cpu_threads()} if os.environ.get(CPU_THREADS) else {}
            ti.init(
                arch=ti.cuda if use_cuda else ti.cpu,
                default_fp=ti.f64,
                log_level=ti.WARN,
                unrolling_limit=0,
                **_offline_cache(),
                **threads,
            )
    running = current_arch()
    if arch == "cuda" and running != "cuda" and not started_before:
        raise ArchUnavailable(
            "arch 'cuda' was asked for, but Taichi found no usable CUDA GPU (the driver loads, "
            "no device starts) and started on the CPU: use --arch cpu or --arch auto"
        )
    if arch != "auto" and arch != running:
        raise RuntimeError(
            f"arch={arch!r} requested but Taichi already runs on {running!r} in "
            f"this process (it can be started only once)"
        )
    return running


@contextlib.contextmanager
def _floating_point_kept():
    """The calling thread's floating-point environment (fenv: rounding, exception masks, and on x86 the SSE
    flush-to-zero and denormals-are-zero flags) as it was before the block, restored after it. ``ti.init`` turns
    flush-to-zero on in the thread that calls it: every later float in the process — CasADi, IPOPT, qrqp, numpy —
    then read 1e-310 as 0, and CasADi's SQP on nlink:3 from a start inside a ball slowed by two orders of magnitude
    after any sampling planner had started Taichi in the process."""
    try:
        libm = ctypes.CDLL(ctypes.util.find_library("m") or "libm.so.6")
    except OSError:  # no C maths library to ask (not a glibc/musl system): nothing to keep
        yield
        return
    env = ctypes.create_string_buffer(256)  # fenv_t is 28-32 bytes on glibc x86-64 and aarch64
    saved = libm.fegetenv(env) == 0
    try:
        yield
    finally:
        if saved:
            libm.fesetenv(env)


def _offline_cache() -> dict:
    """ti.init's offline-cache settings: Taichi's compiled kernels kept in ocpkit's cache (``taichi-kernels`` under
    :func:`ocpkit.codegen.cache.cache_root`, so ``OCPKIT_CACHE_DIR`` and ``ocpkit build`` cover them with the rest), or
    in ``$TI_OFFLINE_CACHE_FILE_PATH`` where that is set. Taichi loads compiled code from that folder, so it is refused
    (:class:`ocpkit.codegen.cache.UnsafeCacheError`) where another user could have planted anything in it. On a
    read-only folder Taichi cannot take its lock, so it neither loads nor stores kernels, and warns three times a run to
    "run 'ti cache clean'" (even with the cache off); on a full one it cannot store them: there, the cache is off and
    pointed at a folder of this process's own, removed at exit (a full one said once,
    :func:`ocpkit.codegen.cache.warn_read_only`: every run compiles its kernels again until room is made)."""
    import atexit
    import shutil
    import tempfile

    from ocpkit.codegen.cache import cache_dir, check_trusted, full, read_only_error, warn_read_only

    path = os.environ.get("TI_OFFLINE_CACHE_FILE_PATH") or str(cache_dir("taichi-kernels"))
    try:
        os.makedirs(path, exist_ok=True)
        with tempfile.TemporaryFile(dir=path) as probe:  # a page written: a full file system refuses it
            probe.write(bytes(4096))
            probe.flush()
    except OSError as exc:
        if full(exc):
            warn_read_only(
                read_only_error("Taichi's compiled kernels cannot be cached", Path(path), exc),
                "they are compiled again each run",
                stacklevel=4,
            )
        private = tempfile.mkdtemp(prefix="ocpkit-ticache-")
        atexit.register(shutil.rmtree, private, True)
        return {"offline_cache": False, "offline_cache_file_path": private}
    return {"offline_cache": True, "offline_cache_file_path": str(check_trusted(path, tree=True))}


def _cpu_threads() -> int:
    """The thread count set in the environment variable OCPKIT_CPU_THREADS."""
    value = os.environ[CPU_THREADS]
    if not value.isdigit() or int(value) < 1:
        raise ValueError(f"environment variable {CPU_THREADS} must be a positive integer, got {value!r}")
    return int(value)


def _cuda_driver_present() -> bool:
    """Whether the CUDA driver library loads (checked before Taichi tries, to spare its fallback warnings)."""
    try:
        ctypes.CDLL("libcuda.so.1")
    except OSError:
        return False
    return True


def current_arch() -> str | None:
    """The arch Taichi runs on ("cpu" or "cuda"), or None before ``init``."""
    if impl.get_runtime().prog is None:
        return None
    return "cuda" if impl.current_cfg().arch == ti.cuda else "cpu"


def float_types(precision: str):
    """(Taichi dtype, numpy dtype) for ``precision`` ("float64" or "float32")."""
    if precision == "float64":
        return ti.f64, np.float64
    if precision == "float32":
        return ti.f32, np.float32
    raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")


_shared: dict = {}
_shared_lock = threading.RLock()


def shared(key: tuple, build):
    """``build()``, once per ``key`` in the process: the kernels of one shape (sizes, float type, translated
    functions, data layout), which take every array as an argument, so every controller of that shape launches the
    same compiled code. Taichi compiles a kernel at its first launch and keys its offline cache by the kernel's code,
    so another process with the same shapes loads what this one compiled, whatever else it built first (kernels
    that read fields were keyed by the fields' ids: a trial's planner compiled again when fields had come before)."""
    with _shared_lock:
        if key not in _shared:
            _shared[key] = build()
        return _shared[key]


def serial_transfers() -> bool:
    """Whether kernels that move a few hundred numbers run as one thread: on the CPU one thread does that in
    microseconds, while a parallel loop waits for the pool's threads to wake, which on a busy machine took
    milliseconds (on CUDA, never)."""
    return current_arch() != "cuda"


@functools.cache
def _writer():
    serial = serial_transfers()

    def write(values, data, start):
        ti.loop_config(serialize=serial)
        for r in range(values.shape[0]):
            data[start + r] = values[r]

    # this module's annotations are strings (__future__): Taichi reads them as types
    write.__annotations__ = {"values": ti.types.ndarray(), "data": ti.types.ndarray(), "start": ti.i32}
    return ti.kernel(write)


def write(data, values: np.ndarray, start: int = 0) -> None:
    """Copy the host array ``values`` (1-D, ``data``'s dtype) into the device array ``data`` (a 1-D Taichi ndarray)
    from index ``start``, in one launch of a kernel compiled once per process."""
    _writer()(values, data, start)


def sync() -> None:
    """Wait for queued kernels, so host timings include the device's work."""
    ti.sync()
