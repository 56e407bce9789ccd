"""The export's folder: refused when it would overwrite a user's files or write through a symbolic link, and every
file placed by one rename (a link or hard link already there is replaced, never written through)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def check_out_dir(out: Path, force: bool) -> None:
    """``out`` must be absent or an empty folder unless ``force``: a user's files are never overwritten silently.

    ``out`` itself must not be a symbolic link (links above it are ordinary paths) and, with ``force``, must hold
    none: the export and ``make`` replace files by name, and a link there would lead them elsewhere."""
    if out.is_symlink():
        target = Path(os.path.realpath(out))
        kind = "a folder" if target.is_dir() else "a file" if target.exists() else "nothing (a dangling link)"
        raise ValueError(
            f"out_dir {str(out)!r} is a symbolic link to {target} ({kind}); the export replaces the "
            f"files of the folder it names and never follows a link there: to export into {target}, "
            f"name it (--out {target})"
        )
    if out.exists() and not out.is_dir():
        raise ValueError(f"out_dir {str(out)!r} is a file, not a folder; name a new or empty folder")
    if out.is_dir():
        refuse_links(out)
    if out.is_dir() and not force:
        held = sorted(p.name for p in out.iterdir())
        if held:
            shown = ", ".join(held[:5]) + (f" and {len(held) - 5} more" if len(held) > 5 else "")
            raise ValueError(
                f"out_dir {str(out)!r} is not empty (holds {shown}); name a new or empty folder, "
                "or pass force=True (--force) to overwrite the exported files in it"
            )


def refuse_links(out: Path) -> None:
    """A ValueError naming the symbolic links directly in ``out``: nothing is exported or built through a link."""
    links = sorted(p for p in out.iterdir() if p.is_symlink())
    if links:
        shown = ", ".join(f"{p.name} -> {os.readlink(p)}" for p in links[:3])
        more = f" and {len(links) - 3} more" if len(links) > 3 else ""
        raise ValueError(
            f"out_dir {str(out)!r} holds symbolic links ({shown}{more}); ocpkit never writes through "
            "a link, even with --force: remove them or name a new folder"
        )


def _umask() -> int:
    """This process' umask, read without changing it (os.umask would, for every thread): Linux /proc, else 022."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    return 0o022


def place(source: Path, target: Path) -> None:
    """Move the new file ``source`` onto ``target`` (same folder or file system) in one rename: an existing
    ``target`` — a file, a hard link, a symbolic link — is replaced, never opened or written."""
    os.chmod(source, 0o666 & ~_umask())
    os.replace(source, target)


def write(path: Path, text: str) -> None:
    """Write ``text`` as the file ``path`` by creating a new file beside it and renaming it into place."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        place(Path(tmp), path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
