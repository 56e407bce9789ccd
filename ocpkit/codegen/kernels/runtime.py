"""The Taichi runtime: started once per process, on CUDA or the CPU.

``ti.init`` may run only once: a second call would destroy every field and compiled kernel
that live controllers hold. So the first caller picks the arch and later callers must agree.
Precision is not a process-wide setting here: every field and generated function carries
its own float type, so float32 and float64 controllers can coexist.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
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


_staged: list = []  # (field, numpy array) pairs waiting for upload()
_staged_lock = threading.Lock()


def stage(field, values) -> None:
    """Queue ``values`` (the field's shape) for ``field``; :func:`upload` copies every queued array in one kernel
    launch. Taichi's own ``from_numpy`` compiles a kernel per field at its first call, even from a warm cache: most
    of a sampling planner's construction, where six fields of constants were filled that way."""
    values = np.asarray(values, dtype=np.float64)
    if values.shape != tuple(field.shape):
        raise ValueError(f"values must have the field's shape {tuple(field.shape)}, got {values.shape}")
    with _staged_lock:
        _staged.append((field, values))


def upload() -> None:
    """Copy the arrays :func:`stage` queued into their fields, in one launch (nothing when none is queued): call it
    before the first kernel that reads them."""
    if not _staged:  # every step of a planner asks; only the first after a construction finds any
        return
    with _staged_lock:
        pairs = list(_staged)
        _staged.clear()
    if not pairs:
        return
    fields = [field for field, _ in pairs]
    shapes = [tuple(field.shape) for field in fields]
    offsets = np.cumsum([0] + [values.size for _, values in pairs]).tolist()

    def copy(flat):
        for q in ti.static(range(len(fields))):
            ti.loop_config(serialize=True)  # a range-for: Taichi ignores (and warns about) serialize on a struct-for
            for I in ti.grouped(ti.ndrange(*shapes[q])):
                index = 0
                for d in ti.static(range(len(shapes[q]))):
                    index = index * shapes[q][d] + I[d]
                fields[q][I] = ti.cast(flat[offsets[q] + index], fields[q].dtype)

    copy.__annotations__ = {"flat": ti.types.ndarray()}  # this module's annotations are strings (__future__)
    ti.kernel(copy)(np.concatenate([values.ravel() for _, values in pairs]))


def sync() -> None:
    """Wait for queued kernels, so host timings include the device's work."""
    ti.sync()
