"""`ocpkit reproduce`: run every study and write one Markdown report with figures, tables and provenance."""

from __future__ import annotations

import importlib.util
import os
import platform
import sys
import time
from importlib import metadata
from pathlib import Path

from ocpkit.runs import study as study_runner
from ocpkit.runs.store import Store
from ocpkit.studies import NAMES, get, motion
from ocpkit.studies.report import markdown_table, per_seed_section

PACKAGES = ("ocpkit", "casadi", "numpy", "proxsuite", "osqp", "pin", "taichi", "control", "matplotlib")


# Seconds per trial and worker of each study's quick grid, measured on the idle 2-core development machine
# (`reproduce --quick` from a fresh clone and an empty cache, 2 workers, 2026-12-05, 0.17.0: 1,882 s in all, load
# 1-2 from its own workers): what the start-up estimate scales. Nonconvex: one trial (IPOPT ×8 on the limits case,
# every step refused after 8 starts of 500 iterations) took 642 s of its 768.
SECONDS_PER_TRIAL = {
    "knots": 0.71,
    "horizon": 0.92,
    "robustness": 0.61,
    "solve_times": 2.5,
    "comparison": 6.8,
    "keepout": 2.1,
    "baxter": 2.9,
    "reach": 11.6,
    "tracking": 1.43,
    "robustness_mujoco": 0.85,
    "nonconvex": 23.6,
}
# Seconds per trial (mean wall time) of each study's full grid, measured on the same machine with 2 workers beside
# other work (load 2-5), 2026-12-04, 0.14.0-0.15.0: the full size's start-up estimate. Nonconvex: EMPC and RTI
# only (IPOPT ×8 took 2-11 min a run, so the whole grid takes longer). A study missing here counts at its quick
# figure, and the estimate says so.
FULL_SECONDS_PER_TRIAL = {
    "knots": 0.94,
    "horizon": 2.3,
    "robustness": 0.86,
    "robustness_mujoco": 3.1,
    "baxter": 6.0,
    "comparison": 25.0,
    "solve_times": 67.0,
    "nonconvex": 92.0,
    "keepout": 3.5,  # 2026-12-05, 0.16.0, load 4.5: 60 trials in 108 s
}
# Studies whose claims are about time: run one trial at a time (locally), so two trials never share the 2 cores.
TIMING_STUDIES = ("solve_times",)
VERDICTS = (
    "How verdicts are decided: each claim is tested on per-seed data (paired by start and goal where it "
    "compares two controllers). The evidence column gives the median, its distribution-free interval "
    "(order statistics; with few seeds the whole range, with its coverage: 75 % at n = 3) and n. Held: the "
    "whole interval is on the claimed side of the threshold; not held: it is on the other side; inconclusive: "
    "it straddles it; not tested: this run lacks the data or the hardware (GPU claims on a CPU run). Timing "
    "verdicts are marked unreliable where the median load exceeded the CPUs."
)


def run_study(
    name: str, size: str, out_dir, *, workers=None, scheduler=None, progress=True, plant: str = "ocpkit", **options
) -> str:
    """Run one study (resuming from its store in ``out_dir``), write its table as <the study's name>.csv and return
    its report section. ``plant="mujoco"``: the robustness study's MuJoCo variant. ``options`` go to
    :func:`ocpkit.runs.study.run` (trial_timeout, retry_failed, stale, lease)."""
    if plant != "ocpkit" and name != "robustness":
        raise ValueError(f"plant {plant!r} applies to the robustness study only, not {name!r}")
    study_options = {} if plant == "ocpkit" else {"plant": plant}
    return _run_study(
        name, size, out_dir, study_options, workers=workers, scheduler=scheduler, progress=progress, **options
    )[0]


def _run_study(name, size, out_dir, study_options=None, **options):
    """(report section, the study's table); ``study_options`` go to the module's ``study(size, …)``."""
    module = get(name)
    out_dir = Path(out_dir)
    study = module.study(size, **(study_options or {}))
    df = study_runner.run(study, out_dir, **options)
    df.to_csv(out_dir / f"{study.name}.csv", index=False)
    return module.report(df, out_dir) + study_runner.failure_summary(df) + study_runner.cluster_summary(df), df


def estimate(names, size: str, out_dir, workers=None) -> float:
    """Seconds the trials of ``names`` not yet stored in ``out_dir`` should take on ``workers`` local processes, from
    :data:`SECONDS_PER_TRIAL` (quick: an idle 2-core machine; a busy one takes longer) or, at the full size,
    :data:`FULL_SECONDS_PER_TRIAL` where it has the study (:func:`unmeasured` names the others)."""
    per_trial = {**SECONDS_PER_TRIAL, **(FULL_SECONDS_PER_TRIAL if size == "full" else {})}
    parts = [(label, module, options) for label, module, options in _parts(names) if module]
    stored = {}
    if (Path(out_dir) / "results.sqlite").exists():
        with Store(out_dir) as store:
            stored = {label: len(store.provenance(label)) for label, _, _ in parts}
    parallel = max(1, min(workers or os.cpu_count() or 1, os.cpu_count() or 1))
    total = 0.0
    for name, module, options in parts:
        todo = max(0, len(get(module).study(size, **options).trials) - stored.get(name, 0))
        total += todo * per_trial.get(name, 5.0) / (1 if name in TIMING_STUDIES else parallel)
    return total


def unmeasured(names, size: str) -> list:
    """The studies of ``names`` whose per-trial time at ``size`` is not measured (counted at the quick size's)."""
    if size != "full":
        return []
    return [name for name, module, _ in _parts(names) if module and name not in FULL_SECONDS_PER_TRIAL]


def _parts(names) -> list:
    """The report's parts in order, as (name, study module or None, its study() options): each study of ``names``
    and, after robustness, its MuJoCo variant (issue 34) — None where MuJoCo is not installed: the report says so."""
    out = []
    for name in names:
        out.append((name, name, {}))
        if name == "robustness":
            from ocpkit.studies.robustness import MUJOCO_NAME

            found = importlib.util.find_spec("mujoco") is not None
            out.append((MUJOCO_NAME, "robustness" if found else None, {"plant": "mujoco"}))
    return out


def per_seed(name: str, df, out_dir=None) -> str:
    """The study's per-seed values as a Markdown table (rows: configurations, columns: seeds): in its verdicts' units
    where its module has ``per_seed_rows(df)`` (also written to ``out_dir``), else of the metric it names in
    ``PER_SEED`` (default the actual cost); ``name`` is the study module's (its table's study names the heading)."""
    heading = df["study"].iloc[0] if "study" in df and len(df) else name
    if hasattr(get(name), "per_seed_rows") and out_dir is not None and (df["status"] == "ok").any():
        return per_seed_section(heading, get(name).per_seed_rows(df), out_dir)
    metric = getattr(get(name), "PER_SEED", "actual_cost")
    ok = df[df["status"] == "ok"]
    if metric not in ok or "seed" not in ok or ok.empty:
        return ""
    axes = [p for p in df.attrs.get("params", []) if p != "seed" and ok[p].nunique(dropna=False) > 1]
    table = (
        ok.pivot_table(index=axes or None, columns="seed", values=metric, aggfunc="first", dropna=False)
        if axes
        else ok.set_index("seed")[[metric]].T
    )
    table.index = [" / ".join(map(str, i)) if isinstance(i, tuple) else str(i) for i in table.index]
    table.index.name = " / ".join(axes) or "metric"
    table.columns = [f"seed {c}" for c in table.columns]
    return f"### {heading}: {metric} per seed\n\n" + markdown_table(table) + "\n"


def reproduce(
    size: str = "quick",
    out_dir="results/reproduce",
    *,
    names=NAMES,
    workers=None,
    scheduler=None,
    progress=True,
    pictures=True,
    **options,
) -> Path:
    """Run the studies ``names`` at ``size`` ("quick" or "full") and write ``out_dir``/report.md.

    The report gives this run's wall time and the compute time summed over every run that stored trials in
    ``out_dir`` (a resumed study counts the runs before it). ``pictures``: also animate a short closed loop per robot
    family into ``out_dir``/motion (:mod:`ocpkit.studies.motion`, about 5 s), shown before the studies."""
    if size not in ("quick", "full"):
        raise ValueError(f"size must be 'quick' or 'full', got {size!r}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if progress and scheduler is None:
        guessed = unmeasured(names, size)
        basis = (
            "the quick size's per-trial times on an idle 2-core machine; a busy one takes longer"
            if size == "quick"
            else "the full size's per-trial times on a busy 2-core machine with 2 workers"
            + (
                f"; {', '.join(guessed)} not measured at this size: counted at the quick size's, so longer"
                if guessed
                else ""
            )
        )
        minutes = estimate(names, size, out_dir, workers) / 60
        print(
            f"reproduce --{size}: about {f'{minutes / 60:.1f} h' if minutes > 120 else f'{minutes:.0f} min'} of "
            "trials to run on "
            f"{workers or os.cpu_count()} worker(s) ({basis})",
            flush=True,
        )
    start, load_start = time.perf_counter(), os.getloadavg()[0]
    sections, appendix, timings = [], [], {}
    parts = _parts(names)
    for name, module, study_options in parts:
        if module is None:
            sections.append(f'## {name}\n\nNot run: MuJoCo is not installed (pip install "ocpkit[mujoco]").\n')
            continue
        t0 = time.perf_counter()
        serial = name in TIMING_STUDIES and scheduler is None  # timed trials must not compete for the cores
        section, df = _run_study(
            module,
            size,
            out_dir,
            study_options,
            workers=1 if serial else workers,
            scheduler=scheduler,
            progress=progress,
            **options,
        )
        sections.append(section)
        appendix.append(per_seed(module, df, out_dir))
        timings[name] = time.perf_counter() - t0
    if pictures:  # not a study: nothing stored, drawn again on every run
        t0 = time.perf_counter()
        sections.insert(0, motion.section(out_dir))
        timings["pictures of motion"] = time.perf_counter() - t0
    wall = time.perf_counter() - start
    with Store(out_dir) as store:
        runs = store.runs()
    ran = [name for name, module, _ in parts if module]
    runs = runs[runs["study"].isin(ran)]
    compute = {name: float(runs.loc[runs["study"] == name, "wall"].sum()) for name in ran}
    report = out_dir / "report.md"
    loads = (load_start, os.getloadavg()[0])
    report.write_text(
        _header(size, names, scheduler, workers, timings, wall, compute, len(runs), loads)
        + "\n"
        + VERDICTS
        + "\n\n"
        + "\n".join(sections)
        + "\n## Appendix: per-seed values\n\n"
        + "\n".join(filter(None, appendix))
    )
    return report


def _header(size, names, scheduler, workers, timings, wall, compute, n_runs, loads) -> str:
    versions = ", ".join(f"{p} {_version(p)}" for p in PACKAGES)
    lines = [
        "# ocpkit: reproduction of Hyatt, Williams, Killpack — Parameterized and GPU-Parallelized Real-Time MPC",
        "",
        f"- command: `ocpkit reproduce --{size}"
        + ("" if tuple(names) == NAMES else "".join(f" --only {name}" for name in names))
        + (f" --scheduler {scheduler}" if scheduler else "")
        + "`",
        f"- machine: {platform.node()}, {platform.machine()}, {os.cpu_count()} CPUs, Python {sys.version.split()[0]}"
        f", {platform.platform()}",
        f"- workers: {workers or ('dask ' + scheduler if scheduler else os.cpu_count())}"
        + ("" if scheduler else f" ({', '.join(TIMING_STUDIES)}: one, so that timed trials never share the cores)"),
        f"- packages: {versions}",
        "- seeds: trial seeds 0 … n−1 per configuration (see each study's size); every start/goal is drawn from"
        " its seed",
        f"- compute time: {sum(compute.values()):.1f} s summed over the {n_runs} study runs that stored trials here ("
        + ", ".join(f"{k} {v:.1f} s" for k, v in compute.items())
        + ")",
        f"- wall time of this run: {wall:.1f} s (" + ", ".join(f"{k} {v:.1f} s" for k, v in timings.items()) + ")"
        f"; 1-min load average {loads[0]:.1f} at its start, {loads[1]:.1f} at its end on {os.cpu_count()} CPUs",
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
