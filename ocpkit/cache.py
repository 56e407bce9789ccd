"""Where ocpkit keeps generated files: ``$OCPKIT_CACHE_DIR`` or ``$XDG_CACHE_HOME/ocpkit`` (~/.cache/ocpkit).

Files in the cache are loaded as code (compiled libraries, generated kernels), so the cache refuses a folder
that other users can write to, and entries are written atomically with a content hash beside them
(:func:`write_entry`) that :func:`entry_ok` checks before use: a damaged entry is rebuilt, not loaded.
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import stat
import tempfile
from pathlib import Path

_HASH_SUFFIX = ".sha256"


class UnsafeCacheError(PermissionError):
    """The cache folder can be written by other users, so code loaded from it could have been planted."""


def cache_dir(kind: str) -> Path:
    """The cache folder for one kind of generated file ("taichi" kernels, "compiled" C functions).

    Created private (mode 0700) when missing; raises :class:`UnsafeCacheError` when it or the cache root is
    writable by group or others, or owned by another user."""
    root = os.environ.get("OCPKIT_CACHE_DIR")
    if not root:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        root = os.path.join(base, "ocpkit")
    folder = Path(root) / kind
    for path in (Path(root), folder):
        with contextlib.suppress(FileExistsError):
            path.mkdir(mode=0o700, parents=True, exist_ok=True)
        _check_private(path)
    return folder


def _check_private(path: Path) -> None:
    info = path.stat()
    if not stat.S_ISDIR(info.st_mode):
        raise NotADirectoryError(f"cache folder {path} is not a folder; remove it or set OCPKIT_CACHE_DIR")
    if info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise UnsafeCacheError(f"cache folder {path} is writable by other users (mode {stat.S_IMODE(info.st_mode):o}), "
                               f"so code loaded from it could have been planted: chmod go-w {path}, or set "
                               f"OCPKIT_CACHE_DIR to a private folder")
    if hasattr(os, "getuid") and info.st_uid != os.getuid():
        raise UnsafeCacheError(f"cache folder {path} belongs to another user (uid {info.st_uid}): set "
                               f"OCPKIT_CACHE_DIR to a folder of your own")


def digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def write_entry(path: Path, data: bytes) -> Path:
    """Write a cache entry atomically (temporary file, then rename), its content hash beside it."""
    path = Path(path)
    _atomic_write(path.with_name(path.name + _HASH_SUFFIX), digest(data).encode())
    _atomic_write(path, data)
    return path


def install(built: Path, path: Path) -> Path:
    """Move a file built elsewhere (a compiler's output, in a scratch folder on the same file system) into the
    cache as entry ``path``: its content hash first, then the file, each atomically (a reader in between sees a
    hash without its file, or the old file with the new hash: not sound, so rebuilt, never loaded)."""
    path = Path(path)
    _atomic_write(path.with_name(path.name + _HASH_SUFFIX), digest(Path(built).read_bytes()).encode())
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


def _atomic_write(path: Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
