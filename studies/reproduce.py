"""`ocpkit reproduce`: run every study and write one Markdown report with figures, tables and provenance."""
from __future__ import annotations

import os
import platform
import sys
import time
from importlib import metadata
from pathlib import Path

from ocpkit import study as study_runner
from ocpkit.store import Store
from ocpkit.studies import NAMES, get

PACKAGES = ("ocpkit", "casadi", "numpy", "proxsuite", "osqp", "pin", "taichi", "control", "matplotlib")


def run_study(name: str, size: str, out_dir, *, workers=None, scheduler=None, progress=True, **options) -> str:
    """Run one study (resuming from its store in ``out_dir``), write its table as ``name``.csv and return its
    report section. ``options`` go to :func:`ocpkit.study.run` (trial_timeout, retry_failed, stale, lease)."""
    module = get(name)
    out_dir = Path(out_dir)
    df = study_runner.run(module.study(size), out_dir, workers=workers, scheduler=scheduler, progress=progress,
                          **options)
    df.to_csv(out_dir / f"{name}.csv", index=False)
    return module.report(df, out_dir) + study_runner.failure_summary(df)


def reproduce(size: str = "quick", out_dir="results/reproduce", *, names=NAMES, workers=None, scheduler=None,
              progress=True, **options) -> Path:
    """Run the studies ``names`` at ``size`` ("quick" or "full") and write ``out_dir``/report.md.

    The report gives this run's wall time and the compute time summed over every run that stored trials in
    ``out_dir`` (a resumed study counts the runs before it)."""
    if size not in ("quick", "full"):
        raise ValueError(f"size must be 'quick' or 'full', got {size!r}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    sections, timings = [], {}
    for name in names:
        t0 = time.perf_counter()
        sections.append(run_study(name, size, out_dir, workers=workers, scheduler=scheduler, progress=progress,
                                  **options))
        timings[name] = time.perf_counter() - t0
    wall = time.perf_counter() - start
    with Store(out_dir) as store:
        runs = store.runs()
    runs = runs[runs["study"].isin(list(names))]
    compute = {name: float(runs.loc[runs["study"] == name, "wall"].sum()) for name in names}
    report = out_dir / "report.md"
    report.write_text(_header(size, scheduler, workers, timings, wall, compute, len(runs)) + "\n" + "\n".join(sections))
    return report


def _header(size, scheduler, workers, timings, wall, compute, n_runs) -> str:
    versions = ", ".join(f"{p} {_version(p)}" for p in PACKAGES)
    lines = [
        "# ocpkit: reproduction of Hyatt, Williams, Killpack — Parameterized and GPU-Parallelized Real-Time MPC",
        "",
        f"- command: `ocpkit reproduce --{size}`" + (f" --scheduler {scheduler}" if scheduler else ""),
        f"- machine: {platform.node()}, {platform.machine()}, {os.cpu_count()} CPUs, Python {sys.version.split()[0]}"
        f", {platform.platform()}",
        f"- workers: {workers or ('dask ' + scheduler if scheduler else os.cpu_count())}",
        f"- packages: {versions}",
        "- seeds: trial seeds 0 … n−1 per configuration (see each study's size); every start/goal is drawn from"
        " its seed",
        f"- compute time: {sum(compute.values()):.1f} s summed over the {n_runs} study runs that stored trials here ("
        + ", ".join(f"{k} {v:.1f} s" for k, v in compute.items()) + ")",
        f"- wall time of this run: {wall:.1f} s (" + ", ".join(f"{k} {v:.1f} s" for k, v in timings.items()) + ")",
        "- results are resumable: each finished trial is in results.sqlite; rerunning skips them",
    ]
    return "\n".join(lines) + "\n"


def _version(package: str) -> str:
    if package == "ocpkit":  # the running source's version (an editable install's metadata may lag it)
        return study_runner.package_version()
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "?"
