"""Building an exported folder with its own Makefile."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

from ocpkit._checks import integer
from ocpkit.export.folder import refuse_links


class BuildError(RuntimeError):
    """The exported folder could not be built: a tool is missing or ``make`` failed (message is one line
    naming the tool, or make's output)."""


def check_tools() -> None:
    """Raise :class:`BuildError` naming the first of the C compiler (``$CC`` or ``cc``) and ``make`` not on PATH."""
    cc = os.environ.get("CC", "cc").split()[0] if os.environ.get("CC", "").strip() else "cc"
    for tool, why in ((cc, "a C compiler (install gcc or clang, or set CC)"), ("make", "GNU make")):
        if shutil.which(tool) is None:
            raise BuildError(f"`{tool}` not found on PATH: building the exported C step needs {why}")


def build(out_dir, *, target: str = "lib", jobs: int = 2) -> Path:
    """Run the folder's own Makefile (``make lib`` by default, ``jobs`` compiles in parallel); return the folder.

    Raises ValueError if the folder holds no exported Makefile or holds a symbolic link (make would write through
    it), :class:`BuildError` if ``cc`` or ``make`` is missing or the build fails.
    """
    out = Path(out_dir)
    if not (out / "Makefile").is_file():
        raise ValueError(f"out_dir {str(out)!r} holds no exported Makefile")
    refuse_links(out)  # make writes its objects and library by name
    check_tools()
    proc = subprocess.run(
        ["make", "-s", "-C", str(out), f"-j{integer(jobs, 'jobs', 1)}", target], capture_output=True, text=True
    )
    if proc.returncode:
        raise BuildError(f"make {target} failed in {out}:\n{proc.stdout}\n{proc.stderr}")
    return out
