"""Where ocpkit keeps generated files: ``$OCPKIT_CACHE_DIR`` or ``$XDG_CACHE_HOME/ocpkit`` (~/.cache/ocpkit).

Files in the cache are loaded as code (compiled libraries, generated kernels), so the cache refuses a folder
that other users can write to, and nothing is loaded before every folder from the cache root down to the file, and
the file, proved to be this user's (or root's) and writable by no one else (:func:`check_trusted`). Entries are
written atomically with a content hash beside them (:func:`write_entry`) that :func:`entry_ok` checks before use: a
damaged entry is rebuilt, not loaded.

One build per entry machine-wide: a builder holds :func:`entry_lock` (``fcntl.flock`` on ``<entry>.lock``), and a
second process that wants the same entry waits for it, then finds the entry built. The kernel releases a flock
when its holder exits however it ends (SIGKILL included), so a dead builder never blocks the next one.

A read-only cache (a shared install, a container image, a read-only root file system) is used as it is: sound
entries are loaded, and a missing one is not built (:class:`CacheReadOnlyError`, said once per process by
:func:`warn_read_only` where the caller falls back to slower code). ``ocpkit build`` fills a cache ahead of time.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import os
import stat
import tempfile
import time
import warnings
from pathlib import Path

_HASH_SUFFIX = ".sha256"
_LOCK_SUFFIX = ".lock"
# errno values of a write refused by the file system or its permissions: the cache is read-only to this process.
READ_ONLY_ERRNOS = frozenset({errno.EROFS, errno.EACCES, errno.EPERM})
# errno values of a write refused for room (the file system, or this user's disk quota): the cache is full.
FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})
_UNWRITABLE = READ_ONLY_ERRNOS | FULL_ERRNOS
# How long a build waits for another process's build of the same entry (a hung compiler, a stopped process).
LOCK_TIMEOUT = 600.0


class UnsafeCacheError(PermissionError):
    """The cache folder can be written by other users, so code loaded from it could have been planted."""


class CacheReadOnlyError(OSError):
    """An entry is missing (or unusable) and the cache folder cannot be written (read-only, or full), so it cannot be
    built there; ``errno`` is EROFS, or the full file system's ENOSPC or EDQUOT."""


def cache_root() -> Path:
    """The cache's root folder: ``$OCPKIT_CACHE_DIR``, else ``$XDG_CACHE_HOME/ocpkit`` (~/.cache/ocpkit)."""
    root = os.environ.get("OCPKIT_CACHE_DIR")
    if not root:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        root = os.path.join(base, "ocpkit")
    return Path(root)


def cache_dir(kind: str) -> Path:
    """The cache folder for one kind of generated file ("taichi" kernels, "compiled" C functions).

    Created private (mode 0700) when missing; raises :class:`UnsafeCacheError` when it or the cache root is
    writable by group or others, or owned by another user than this one or root. Where it cannot be created (a
    read-only file system) its path is returned all the same: it holds no entry, and writing there raises."""
    root = cache_root()
    folder = root / kind
    for path in (root, folder):
        try:
            path.mkdir(mode=0o700, parents=True, exist_ok=True)
        except FileExistsError:
            pass
        except OSError as exc:
            if exc.errno not in _UNWRITABLE or path.exists():
                raise
            return folder  # read-only (or full) and absent: nothing to load from it, nothing to check
        _check_private(path)
    return folder


def check_trusted(path, tree: bool = False) -> Path:
    """``path`` resolved, once it is safe to load as code: it and every folder above it up to the cache root (for a
    path outside the cache: its own folder) belong to this user or root and are writable by no one else; otherwise
    :class:`UnsafeCacheError` naming the first that is not and what is wrong. Call it before every ``dlopen``,
    ``ctypes.CDLL`` or import of a file, and load the path it returns (what was checked). Missing parts are skipped:
    nothing below them can be loaded. ``tree``: ``path`` is a folder loaded from as a whole (Taichi's kernel
    cache), and everything in it is checked too."""
    path = Path(os.path.realpath(path))
    root = Path(os.path.realpath(cache_root()))
    top = root if path.is_relative_to(root) else path.parent
    for part in [*reversed(path.parents[: len(path.parents) - len(top.parents)]), path]:
        try:
            _check_private(part, folder=part != path or tree)
        except FileNotFoundError:
            return path
    for folder, folders, files in os.walk(path) if tree else ():
        for name in folders + files:
            with contextlib.suppress(FileNotFoundError):  # removed meanwhile (Taichi's own clean-up)
                _check_private(Path(folder, name), folder=name in folders)
    return path


def _check_private(path: Path, folder: bool = True) -> None:
    """:class:`UnsafeCacheError` unless ``path`` (a folder, or with ``folder=False`` a file) is this user's or root's
    and writable by no one else."""
    info = path.stat()
    what = "cache folder" if folder else "cache file"
    if folder and not stat.S_ISDIR(info.st_mode):
        raise NotADirectoryError(f"cache folder {path} is not a folder; remove it or set OCPKIT_CACHE_DIR")
    if info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise UnsafeCacheError(
            f"{what} {path} is writable by other users (mode {stat.S_IMODE(info.st_mode):o}), "
            f"so code loaded from it could have been planted: chmod go-w {path}, or set "
            f"OCPKIT_CACHE_DIR to a private folder"
        )
    # Root's folders are trusted as ssh trusts them (root can change any file anyway): a cache prebuilt into a
    # shared install or a container image by root serves every user, read-only.
    if hasattr(os, "getuid") and info.st_uid not in (os.getuid(), 0):
        raise UnsafeCacheError(
            f"{what} {path} belongs to another user (uid {info.st_uid}), so code loaded from it "
            f"could have been planted: set OCPKIT_CACHE_DIR to a folder of your own"
        )


def read_only(exc: BaseException) -> bool:
    """Whether ``exc`` is a write refused because the file system or folder is read-only to this process, or full."""
    return isinstance(exc, CacheReadOnlyError) or (isinstance(exc, OSError) and exc.errno in _UNWRITABLE)


def full(exc: BaseException) -> bool:
    """Whether ``exc`` is a write refused for room: no space left on the file system, or the disk quota spent."""
    return isinstance(exc, OSError) and exc.errno in FULL_ERRNOS


def read_only_error(what: str, folder: Path, exc: OSError | None = None) -> CacheReadOnlyError:
    """The error of an entry ``what`` that the read-only (or, as ``exc`` says, full) cache ``folder`` lacks, saying
    how to fill the cache."""
    if exc is not None and full(exc):
        why = exc.strerror or os.strerror(exc.errno)  # a CacheReadOnlyError passed on carries only its errno
        error = CacheReadOnlyError(
            f"{what}, and the cache folder {folder} is full ({why}): make room there, or set "
            f"OCPKIT_CACHE_DIR to a folder with room"
        )
        error.errno = exc.errno
        return error
    # A CacheReadOnlyError passed on says no more than "read-only".
    why = "" if exc is None or isinstance(exc, CacheReadOnlyError) else f" ({exc.strerror or exc})"
    error = CacheReadOnlyError(
        f"{what}, and the cache folder {folder} is read-only{why}: prebuild the cache with "
        f"`ocpkit build PROBLEM …` where it is writable, or set OCPKIT_CACHE_DIR to a writable "
        f"folder"
    )
    error.errno = errno.EROFS
    return error


_warned_read_only = False


def warn_read_only(exc: BaseException, then: str, stacklevel: int = 2) -> None:
    """Say once per process that the read-only (or full) cache lacks what this run wanted (a C step, a compiled
    model) and what runs instead (``then``): one warning, whatever else it lacks later (the cure is one)."""
    global _warned_read_only
    if not _warned_read_only:
        _warned_read_only = True
        warnings.warn(f"{exc}; {then}", RuntimeWarning, stacklevel=stacklevel + 1)


def scratch_dir(folder: Path, prefix: str) -> Path:
    """A new private folder inside ``folder`` (created if missing), on the cache's file system so a build there
    is installed by a rename; :class:`CacheReadOnlyError` where nothing can be created."""
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(dir=folder, prefix=prefix))
    except OSError as exc:
        if exc.errno in _UNWRITABLE:
            raise read_only_error("nothing can be built", folder, exc) from None
        raise


def digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def write_entry(path: Path, data: bytes) -> Path:
    """Write a cache entry atomically (temporary file, then rename), its content hash beside it."""
    path = Path(path)
    write_atomically(path.with_name(path.name + _HASH_SUFFIX), digest(data).encode())
    write_atomically(path, data)
    return path


def install(built: Path, path: Path) -> Path:
    """Move a file built elsewhere (a compiler's output, in a scratch folder on the same file system) into the
    cache as entry ``path``: its content hash first, then the file, each atomically (a reader in between sees a
    hash without its file, or the old file with the new hash: not sound, so rebuilt, never loaded)."""
    path = Path(path)
    write_atomically(path.with_name(path.name + _HASH_SUFFIX), digest(Path(built).read_bytes()).encode())
    os.replace(built, path)
    return path


def entry_ok(path: Path) -> bool:
    """Whether the entry exists, is not empty and matches the content hash recorded beside it."""
    path = Path(path)
    try:
        data = path.read_bytes()
        recorded = path.with_name(path.name + _HASH_SUFFIX).read_text().strip()
    except OSError:
        return False
    return bool(data) and recorded == digest(data)


def evict(path: Path, seen: os.stat_result | None = None) -> None:
    """Remove the entry ``path`` and its hash (a sound entry that does not load), so that it is built again.
    ``seen``: the entry as it was found unusable; a file replaced since (rebuilt by another process) is kept.
    :class:`CacheReadOnlyError` where the cache cannot be written."""
    path = Path(path)
    try:
        if seen is not None:
            now = path.stat()
            if (now.st_ino, now.st_dev, now.st_mtime_ns) != (seen.st_ino, seen.st_dev, seen.st_mtime_ns):
                return
        for victim in (path, path.with_name(path.name + _HASH_SUFFIX)):
            with contextlib.suppress(FileNotFoundError):
                victim.unlink()
    except FileNotFoundError:
        return
    except OSError as exc:
        if exc.errno in _UNWRITABLE:
            raise read_only_error(f"cache entry {path} cannot be removed", path.parent, exc) from None
        raise


def load_problem(library: Path, symbol: str) -> str | None:
    """None if the cached shared library loads in this process and defines ``symbol``; otherwise why not (the
    dynamic loader's message: "wrong ELF class", "invalid ELF header", …). A library that loads stays loaded (a
    later load of the path is the same handle); one without ``symbol`` is unloaded, so that a library rebuilt
    under its path is loaded afresh. :class:`UnsafeCacheError`, before anything is loaded, where another user could
    have planted it (:func:`check_trusted`)."""
    import ctypes

    path = check_trusted(library)
    try:
        lib = ctypes.CDLL(str(path))
    except OSError as exc:
        return str(exc)
    if not hasattr(lib, symbol):
        import _ctypes

        _ctypes.dlclose(lib._handle)
        return f"it does not define {symbol}"
    return None


def entry_problem(library: Path, symbol: str) -> str | None:
    """None where the cached shared library is sound (:func:`entry_ok`) and loads with ``symbol``
    (:func:`load_problem`); otherwise what is wrong, said of the entry: "is not in the cache", "is damaged (…)",
    "does not load (…)"."""
    library = Path(library)
    if not entry_ok(library):
        if library.exists():
            return "is damaged (its content does not match the hash recorded beside it)"
        return "is not in the cache"
    problem = load_problem(library, symbol)
    return None if problem is None else f"does not load ({problem})"


def read_only_entry(library: Path, symbol: str, what: str, unwritable: OSError) -> Path:
    """``library``, the entry ``what`` of a cache that cannot be written (as ``unwritable`` says: read-only, or full),
    where it is sound and loads (:func:`entry_problem`); else :class:`CacheReadOnlyError` saying what is wrong and
    how to fill the cache."""
    problem = entry_problem(library, symbol)
    if problem is not None:
        raise read_only_error(f"{what} ({library}) {problem}", Path(library).parent.parent, unwritable) from None
    return library


@contextlib.contextmanager
def entry_lock(entry: Path, timeout: float | None = LOCK_TIMEOUT, poll: float = 0.05):
    """Hold the build lock of cache entry ``entry`` (a file or folder): ``fcntl.flock`` on ``<entry>.lock``.

    Yields whether it had to wait for another holder (who may have built the entry meanwhile: check it again).
    The lock is released when the block ends or the holder exits however it ends; the lock file (empty but for
    its last holder's pid) stays. :class:`CacheReadOnlyError` where the lock file cannot be created; TimeoutError
    after ``timeout`` seconds of waiting (None: wait as long as it takes)."""
    entry = Path(entry)
    lock = entry.with_name(entry.name + _LOCK_SUFFIX)
    try:
        lock.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | getattr(os, "O_NOFOLLOW", 0), 0o600)
    except OSError as exc:
        if exc.errno in _UNWRITABLE:
            raise read_only_error(f"cache entry {entry} cannot be built", lock.parent, exc) from None
        raise
    try:
        waited = False
        start = time.monotonic()
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                waited = True
                if timeout is not None and time.monotonic() - start > timeout:
                    holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
                    raise TimeoutError(
                        f"another process (pid {holder}) has been building cache entry {entry} for "
                        f"over {timeout:.0f} s; if it hangs, end it or remove {lock}"
                    ) from None
                time.sleep(poll)
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except OSError as exc:  # a full file system: not even the pid fits, nor would the build
            if exc.errno in _UNWRITABLE:
                raise read_only_error(f"cache entry {entry} cannot be built", lock.parent, exc) from None
            raise
        yield waited
    finally:
        os.close(fd)  # releases the lock


def write_atomically(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file beside it and a rename: a reader sees the old file or the
    new one, never half of it; nothing is left where the write fails (a full file system)."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
