"""Run a command with a folder read-only, as a deployment sees its cache (a shared install, a container image, a
read-only root file system), or on a full file system (:func:`run_full`): for `ocpkit bench faults` and the tests.

Root ignores permission bits, so as root the folder is bind-mounted read-only onto itself in a private mount
namespace (``unshare -m``) that only the command sees: writes fail with EROFS, as on a read-only file system, and
nothing outside changes. Other users get the folder's write permissions removed for the run (EACCES), then
restored. :func:`method` says which one this machine allows (None: neither, e.g. root in a container without
CAP_SYS_ADMIN).
"""

from __future__ import annotations

import contextlib
import functools
import os
import shutil
import stat
import subprocess
import tempfile
from pathlib import Path

BIND_MOUNT, PERMISSIONS = "read-only bind mount", "write permission removed"
# $0 is the folder, "$@" the command: the mount exists in the new namespace only, and goes with it.
_MOUNT = 'mount --bind "$0" "$0" && mount -o remount,bind,ro "$0" "$0" && exec "$@"'
# A 1 MiB tmpfs on the folder, filled up (dd stops at "No space left on device").
_FULL = (
    'mount -t tmpfs -o size=1m,mode=700 tmpfs "$0" && { dd if=/dev/zero of="$0/.fill" bs=4k 2>/dev/null; exec "$@"; }'
)


@functools.lru_cache(maxsize=None)
def method() -> str | None:
    """How this machine can make a folder read-only for one command: BIND_MOUNT, PERMISSIONS or None."""
    if os.getuid() != 0:
        return PERMISSIONS
    if shutil.which("unshare") is None or shutil.which("mount") is None:
        return None
    with tempfile.TemporaryDirectory(prefix="ocpkit-ro-probe-") as folder:
        probe = subprocess.run(
            [
                "unshare",
                "-m",
                "--propagation",
                "private",
                "sh",
                "-c",
                _MOUNT,
                folder,
                "sh",
                "-c",
                'touch "$0/x" 2>/dev/null && echo writable || echo read-only',
                folder,
            ],
            capture_output=True,
            text=True,
        )
        return BIND_MOUNT if probe.returncode == 0 and probe.stdout.strip() == "read-only" else None


def run(folder, command: list[str], **kwargs) -> subprocess.CompletedProcess:
    """``subprocess.run(command, **kwargs)`` with ``folder`` (and everything below it) read-only to the command."""
    how = method()
    folder = str(Path(folder).resolve())
    if how == BIND_MOUNT:
        return subprocess.run(
            ["unshare", "-m", "--propagation", "private", "sh", "-c", _MOUNT, folder, *command], **kwargs
        )
    if how == PERMISSIONS:
        with _without_write_permission(Path(folder)):
            return subprocess.run(command, **kwargs)
    raise RuntimeError("this machine cannot make a folder read-only for a command (root without mount namespaces)")


def run_full(folder, command: list[str], **kwargs) -> subprocess.CompletedProcess:
    """``subprocess.run(command, **kwargs)`` with ``folder`` a full, empty file system to the command (an ENOSPC on
    every write): a small tmpfs mounted on it and filled, in a private mount namespace as :func:`run` does (so as
    root only: where :func:`method` is BIND_MOUNT); the folder itself is left as it was."""
    if method() != BIND_MOUNT:
        raise RuntimeError("only root with mount namespaces can give a command a full file system")
    return subprocess.run(
        ["unshare", "-m", "--propagation", "private", "sh", "-c", _FULL, str(Path(folder).resolve()), *command],
        **kwargs,
    )


@contextlib.contextmanager
def _without_write_permission(folder: Path):
    modes = {}
    for path in [folder, *folder.rglob("*")]:
        if not path.is_symlink():
            modes[path] = stat.S_IMODE(path.stat().st_mode)
            path.chmod(modes[path] & ~0o222)
    try:
        yield
    finally:
        for path, mode in modes.items():
            path.chmod(mode)
