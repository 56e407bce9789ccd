"""Where the acados peer lives: acados (SQP-RTI, HPIPM, BLASFEO) from the PyPI wheel ``comma-deps-acados``, kept
in a folder of its own outside the project's environment.

The wheel ships libacados, blasfeo, hpipm and qpOASES (``acados/install``), the Python interface
``acados_template`` and a slim CasADi 3.7 built for CPython 3.12. That CasADi must never shadow the project's, so
the wheel is unpacked with ``pip install --no-deps --target`` into :func:`folder` (``$OCPKIT_ACADOS_DIR``, by
default ``~/.local/share/ocpkit/peers/acados``) and :func:`require` puts only ``<folder>/acados`` on ``sys.path``
(``acados_template`` then imports the project's CasADi), points ``ACADOS_SOURCE_DIR`` at ``acados/install`` (its
headers, libraries and template renderer ``t_renderer``) and loads the four libraries into the process, so the
solvers acados generates and links against them load without ``LD_LIBRARY_PATH``. ``acados_template`` looks for its
layout file under ``$ACADOS_SOURCE_DIR/interfaces/acados_template/acados_template``: :func:`install` makes that
a link to the unpacked ``acados_template``.

Install (repeatable; it replaces an older copy): ``python -m ocpkit.benchmarks.acados_install``.

acados' HPIPM and BLASFEO have the sonames of those CasADi's HPIPM plugin loads (``libhpipm.so``,
``libblasfeo.so.0``), and a process that has loaded both crashed (a segmentation fault, whichever came first): the
peer runs in a process of its own (:func:`isolated`), :func:`require` refuses a process where CasADi's plugin is
loaded, and :mod:`ocpkit.qp.hpipm` one where acados is.
"""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys
from pathlib import Path

PACKAGE = "comma-deps-acados==0.2.2.post104"
ENV = "OCPKIT_ACADOS_DIR"
INSTALL = "python -m ocpkit.benchmarks.acados_install"
# The libraries of acados/install/lib, each before those that need it.
LIBRARIES = ("libblasfeo.so", "libhpipm.so", "libqpOASES_e.so.3.1", "libacados.so")


def folder() -> Path:
    """The peer's folder: ``$OCPKIT_ACADOS_DIR``, or ``~/.local/share/ocpkit/peers/acados``."""
    given = os.environ.get(ENV)
    return Path(given).expanduser() if given else Path.home() / ".local" / "share" / "ocpkit" / "peers" / "acados"


def missing(where: Path | None = None) -> str | None:
    """Why the acados peer cannot be used from ``where`` (default :func:`folder`), or None."""
    where = folder() if where is None else where
    root = where / "acados"
    needed = [root / "acados_template" / "__init__.py", root / "install" / "bin" / "t_renderer"]
    needed += [root / "install" / "lib" / name for name in LIBRARIES]
    absent = [path for path in needed if not path.exists()]
    if absent:
        return f"acados not installed in {where} (no {absent[0].relative_to(where)}): {INSTALL} (or set ${ENV})"
    return None


def install(where: Path | None = None) -> Path:
    """Unpack ``comma-deps-acados`` into ``where`` (default :func:`folder`) without its dependencies and link its
    layout file where ``acados_template`` looks; returns the folder. The project's site-packages is not touched."""
    where = folder() if where is None else Path(where)
    where.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "pip", "install", "--no-deps", "--only-binary=:all:", "--python-version", "3.12"]
    command += ["--upgrade", "--target", str(where), PACKAGE]
    subprocess.run(command, check=True)
    link = where / "acados" / "install" / "interfaces" / "acados_template" / "acados_template"
    link.parent.mkdir(parents=True, exist_ok=True)
    if link.is_symlink() or link.exists():
        link.unlink()
    link.symlink_to(Path("..", "..", "..", "acados_template"))
    reason = missing(where)
    if reason:
        raise RuntimeError(reason)
    return where


def require():
    """The ``acados_template`` module, set up as the module docstring says, or an ImportError with the command
    that installs it."""
    if "acados_template" in sys.modules:
        return sys.modules["acados_template"]
    reason = missing()
    if reason:
        raise ImportError(reason)
    if casadi_hpipm_loaded():
        raise RuntimeError(
            "acados cannot be loaded into a process that has loaded CasADi's HPIPM plugin (their HPIPM and BLASFEO "
            "libraries share names, and the process crashes): run it in a process of its own (acados_install.isolated)"
        )
    root = folder() / "acados"
    lib = root / "install" / "lib"
    for name in LIBRARIES:  # RTLD_GLOBAL: the generated solvers find their dependencies already loaded
        ctypes.CDLL(str(lib / name), mode=ctypes.RTLD_GLOBAL)
    os.environ["ACADOS_SOURCE_DIR"] = str(root / "install")
    sys.path.insert(0, str(root))
    import acados_template

    return acados_template


def loaded() -> bool:
    """Whether this process has loaded acados' libraries."""
    return "acados_template" in sys.modules


def casadi_hpipm_loaded() -> bool:
    """Whether this process has loaded CasADi's HPIPM plugin (read from /proc/self/maps; False where there is none)."""
    try:
        return "libcasadi_conic_hpipm" in Path("/proc/self/maps").read_text()
    except OSError:
        return False


def isolated(function, *args, **kwargs):
    """``function(*args, **kwargs)`` run in a new process (spawned: nothing of this one's libraries), its result
    returned and its exception raised here: where the acados peer runs, so that this process never loads it."""
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as pool:
        return pool.submit(function, *args, **kwargs).result()


def available() -> bool:
    """Whether the acados peer can be used."""
    try:
        require()
    except ImportError:
        return False
    return True


if __name__ == "__main__":
    print(f"acados peer installed in {install()}")
