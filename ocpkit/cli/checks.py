"""Checks made before any work starts, so that a run is not lost at its end: output paths writable, and an MPC
problem's dense matrices within memory."""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

from ocpkit.cli.options import QP_SOLVERS, knot_count


def check_output_folder(path, option: str) -> None:
    """``path`` is (or can be created as) a folder this process can write into."""
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{option} {path}: is a file; give a folder")
    existing = next((p for p in (folder, *folder.parents) if p.exists()), None)
    if existing is not None and not existing.is_dir():
        raise ValueError(f"{option} {path}: {existing} is a file, so the folder cannot be created")
    _probe(folder if folder.exists() else existing, option, path, folder.exists())


def check_output_file(path, option: str) -> None:
    """``path`` names a file this process can create or replace."""
    target = Path(path)
    if target.is_dir():
        raise ValueError(f"{option} {path}: is a folder; give a file name")
    if target.exists() and not os.access(target, os.W_OK):
        raise ValueError(f"{option} {path}: the file cannot be written; choose another path")
    existing = next((p for p in target.parents if p.exists()), None)
    if existing is not None and not existing.is_dir():
        raise ValueError(f"{option} {path}: {existing} is a file, so no file can be created below it")
    _probe(existing, option, path, False)


def _probe(folder, option, path, is_target) -> None:
    """Create and delete a scratch file in ``folder`` (file modes alone do not tell: root, /proc, read-only mounts)."""
    folder = Path(folder) if folder is not None else Path(".")
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".ocpkit-probe-"):
            pass
    except OSError as exc:
        where = "" if is_target else f" (nothing can be created in {folder})"
        raise ValueError(f"{option} {path}: not writable{where}: {exc.strerror or exc}; choose another path") from None


def _available_memory() -> float | None:
    """Bytes of memory available now (Linux /proc/meminfo), or None where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return 1024.0 * int(line.split()[1])
    except OSError:
        return None
    return None


def check_size(problem, args) -> None:
    """Refuse an MPC problem whose dense matrices cannot fit in memory; warn when one solve will take long (solve and
    simulate, whose arguments were checked by _solver_options).

    Dense storage (8-byte floats): the T×p basis, and for the condensed QP the (T·nx)×(p·nu) prediction matrix
    and the (p·nu)² Hessian. Time (condensed, the default): about 2 ns × ((p·nu)³ + T·nx·(p·nu)²), fitted to
    pendulum solves at T = 250…3000 here (one-off build included), so an order of magnitude only."""
    T = problem.horizon if args.horizon is None else args.horizon
    if T < 1:
        return  # the OCP's own check names the bad value
    model = problem.model()
    nx, nu = model.nx, model.nu
    knots = knot_count(problem, args)
    p = T if knots is None else max(1, knots)
    qp_based = args.solver in QP_SOLVERS
    condensed = qp_based and (args.form or "condensed") == "condensed"
    entries = T * p + (T * nx * p * nu + (p * nu) ** 2 if condensed or not qp_based else 0)
    need = 8.0 * entries
    have = _available_memory()
    size = f"horizon T = {T}, p = {p} knots, nx = {nx}, nu = {nu}"
    if have is not None and need > 0.5 * have:
        raise ValueError(
            f"{size} needs about {_gib(need)} for its dense matrices, more than half the "
            f"{_gib(have)} available: shorten --horizon or give --knots"
        )
    if condensed:
        seconds = 2e-9 * ((p * nu) ** 3 + T * nx * (p * nu) ** 2)
        if seconds > 30:
            print(
                f"ocpkit: warning: {size}: one solve may take around {seconds:.0f} s "
                f"(memory about {_gib(need)}); --knots makes it smaller",
                file=sys.stderr,
            )
    elif qp_based and (args.qp or "proxqp") == "proxqp" and p < T:
        # Sparse ProxQP with knots: its factorization fills in along the knots' columns, about 2.5 ns × (T·nx)³ a
        # solve (pendulum, 5 knots: 1.9 s at T = 600, 168 s at T = 2000; traditional MPC 0.1 and 1.8 s; OSQP 0.3 s).
        seconds = 2.5e-9 * (T * nx) ** 3
        if seconds > 30:
            from ocpkit.solvers.qp import LinearMPC

            ceiling = max(LinearMPC.CEILING_MIN, LinearMPC.CEILING_PER_VARIABLE * ((T + 1) * nx + p * nu))
            print(
                f"ocpkit: warning: {size}: sparse ProxQP with knots may take around {seconds:.3g} s a solve "
                f"(a step stops at LinearMPC's default budget, {ceiling:.0f} s here); --qp osqp or --form "
                f"condensed is far faster",
                file=sys.stderr,
            )


def _gib(n: float) -> str:
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB"
