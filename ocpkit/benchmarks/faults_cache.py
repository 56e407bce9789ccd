"""The cache rows of `ocpkit bench faults`: a read-only cache with and without the C step, four scripts that want
one entry at once, another user's planted entry, and a cache on a full file system."""

from __future__ import annotations

from ocpkit.benchmarks.faults_realtime import RealTimeRow, _counts
from ocpkit.status import SUCCESS

# One default LinearMPC of nlink:13 (5 knots) from a script: construction and first step timed, its warnings, as JSON.
_CACHE_SCRIPT = """
import json, time, warnings
from ocpkit import problems
from ocpkit.solvers.qp import LinearMPC
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    p = problems.make("nlink:13")
    x, goal = p.sample(0)
    t0 = time.perf_counter()
    c = LinearMPC(p.ocp(knots=5))
    native = c.native
    status = c.solve(x, goal).status
    wall = time.perf_counter() - t0
    ready = c.wait_compiled(WAIT)
print(json.dumps({"native": native, "status": status, "wall": wall, "ready": ready, "now_native": c.native,
                  "warnings": [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]}))
"""


def _cache_script(wait: float) -> list[str]:
    import sys

    return [sys.executable, "-c", _CACHE_SCRIPT.replace("WAIT", repr(wait))]


def _script_options(root, cwd) -> dict:
    """How the script runs with its cache at ``root``: its output captured as text, in ``cwd`` (outside any
    checkout, which would shadow the installed ocpkit)."""
    import os

    return {
        "env": {**os.environ, "OCPKIT_CACHE_DIR": str(root)},
        "capture_output": True,
        "text": True,
        "timeout": 600,
        "cwd": cwd,
    }


def _script_row(
    what: str, label: str, where: str, r: dict, says: str | None, criterion: str, written: bool = False
) -> RealTimeRow:
    """The row of the script's result ``r`` (:func:`_script_result`): which step ran first and its warnings, passed
    where nothing was ``written`` to the cache and the first step ran in C with no warning (``says`` None) or in
    Python with one warning that says ``says``; or what the script raised (failed: nothing may raise)."""
    if "error" in r:
        return RealTimeRow(
            what, label, f"raised: {r['error'][:100]}", float("nan"), "exception", False, "nothing raised"
        )
    warned = not r["warnings"] if says is None else len(r["warnings"]) == 1 and says in r["warnings"][0]
    ok = bool(r["native"]) == (says is None) and r["status"] == SUCCESS and warned and not written
    return RealTimeRow(
        what,
        label,
        f"nlink:13 p=5 ({where}): "
        f"{'C step' if r['native'] else 'Python step'}, {len(r['warnings'])} warnings"
        f"{': ' + _gist(r['warnings'][0]) if r['warnings'] else ''}",
        r["wall"],
        r["status"],
        bool(ok),
        criterion,
    )


def _script_result(run) -> dict:
    """The script's JSON line, or {"error": its last stderr line} where it raised."""
    import json

    lines = run.stdout.strip().splitlines()
    if run.returncode or not lines:
        err = run.stderr.strip().splitlines()
        return {"error": err[-1] if err else f"exit status {run.returncode}"}
    return json.loads(lines[-1])


def cache_rows(out=print) -> list[RealTimeRow]:
    """A read-only cache (:mod:`ocpkit.benchmarks.readonly`: a read-only bind mount as root, write permission
    removed otherwise) holding nlink:13's C step (from ``ocpkit build``): the first step must run in C with no
    warning and nothing raised; without it: the Python step, one warning, nothing raised; and four scripts
    started together on an empty cache: one build (``make`` counted through a wrapper on PATH), all four in C."""
    import os
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    from ocpkit.benchmarks import readonly

    rows = []
    with tempfile.TemporaryDirectory(prefix="ocpkit-bench-cache-") as tmp:
        tmp = Path(tmp)
        if readonly.method() is None:
            out(
                "cache rows: the read-only ones skipped (this machine cannot make a folder read-only: root without "
                "mount namespaces)"
            )
        else:
            filled, empty = tmp / "filled", tmp / "empty"
            empty.mkdir(mode=0o700)
            subprocess.run(
                [sys.executable, "-m", "ocpkit.cli", "build", "nlink:13", "--knots", "5"],
                check=True,
                env={**os.environ, "OCPKIT_CACHE_DIR": str(filled)},
                capture_output=True,
                timeout=900,
                cwd=tmp,
            )  # the scripts run outside any checkout, which would shadow the installed ocpkit
            for label, root in (("sound entry", filled), ("no entry", empty)):
                before = sorted(p.name for p in root.rglob("*"))
                r = _script_result(readonly.run(root, _cache_script(0), **_script_options(root, tmp)))
                written = sorted(p.name for p in root.rglob("*")) != before
                if label == "sound entry":
                    says, criterion = None, "first step in C, success, no warning, nothing written"
                else:
                    says, criterion = "read-only", "Python step, success, one warning, nothing raised or written"
                rows.append(_script_row("read-only cache", label, readonly.method(), r, says, criterion, written))
        rows.append(_concurrent_row(tmp))
    return rows + [planted_entry_row()] + full_disk_rows(out)


def _gist(warning: str) -> str:
    """A cache warning without its paths (they name a temporary folder): its start and what runs instead."""
    import re

    return re.sub(r"\s*\(?/\S+\)?", "", warning.split(": prebuild")[0])[:70] + " …"


def _concurrent_row(tmp, scripts: int = 4) -> RealTimeRow:
    """``scripts`` processes wanting one C step at once on an empty cache: builds counted by a `make` wrapper."""
    import os
    import shutil
    import subprocess
    import time

    root, bin_dir, log = tmp / "concurrent", tmp / "bin", tmp / "make.log"
    bin_dir.mkdir()
    (bin_dir / "make").write_text(f'#!/bin/sh\necho build >> {log}\nexec {shutil.which("make")} "$@"\n')
    (bin_dir / "make").chmod(0o755)
    env = {**os.environ, "OCPKIT_CACHE_DIR": str(root), "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}
    t0 = time.perf_counter()
    procs = [
        subprocess.Popen(
            _cache_script(300), env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp
        )
        for _ in range(scripts)
    ]
    results = []
    for proc in procs:
        stdout, stderr = proc.communicate(timeout=900)
        results.append(_script_result(subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)))
    wall = time.perf_counter() - t0
    builds = log.read_text().count("build") if log.exists() else 0
    in_c = sum(bool(r.get("now_native")) for r in results)
    errors = sum("error" in r for r in results)
    return RealTimeRow(
        "concurrent builds",
        f"{scripts} scripts, one entry",
        f"nlink:13 p=5: {builds} build(s), {in_c}/{scripts} scripts then in C, {errors} raised",
        wall,
        _counts(r.get("status", "exception") for r in results),
        builds == 1 and in_c == scripts,
        "one build machine-wide, every script then in C",
    )


def planted_entry_row() -> RealTimeRow:
    """Another user's planted C step: nlink:13's default entry folder opened to everyone (mode 777), its libmpc.so
    and content hash replaced by a library whose constructor leaves a marker. A script's default LinearMPC must not
    load it (no marker) and refuse in one line (``UnsafeCacheError``)."""
    import os
    import shutil
    import subprocess
    import tempfile
    import time
    from pathlib import Path

    from ocpkit import problems
    from ocpkit.export import native
    from ocpkit.codegen.cache import write_entry
    from ocpkit.solvers.qp import LinearMPC

    with tempfile.TemporaryDirectory(prefix="ocpkit-bench-planted-") as tmp:
        tmp = Path(tmp)
        root, marker = tmp / "cache", tmp / "constructor-ran"
        ocp = problems.make("nlink:13").ocp(knots=5)
        python = LinearMPC(ocp, native=False)  # the settings a default LinearMPC hands to ocpkit.export.native
        settings = (python._backend.tolerance, python.max_iter, python.linearization, 1, 0.0)
        root.mkdir(mode=0o700)
        scratch, key, _ = native._generate(ocp, settings, root / "native")  # the entry's key; nothing built
        shutil.rmtree(scratch)
        entry = root / "native" / key
        entry.mkdir(mode=0o777)
        entry.chmod(0o777)
        (tmp / "planted.c").write_text(
            "#include <stdio.h>\n__attribute__((constructor)) static void planted(void) "
            f'{{ FILE *f = fopen("{marker}", "w"); if (f) fclose(f); }}\n'
        )
        subprocess.run(
            [os.environ.get("CC", "cc"), "-shared", "-fPIC", str(tmp / "planted.c"), "-o", str(tmp / "planted.so")],
            check=True,
        )
        write_entry(entry / f"lib{native.NAME}.so", (tmp / "planted.so").read_bytes())
        t0 = time.perf_counter()
        run = subprocess.run(_cache_script(0), **_script_options(root, tmp))
        wall = time.perf_counter() - t0
        r = _script_result(run)
        refused = r.get("error", "").startswith("ocpkit.codegen.cache.UnsafeCacheError: ")
        planted_ran = marker.exists()
    return RealTimeRow(
        "planted cache entry",
        "qp condensed daqp (default)",
        f"nlink:13 p=5, entry folder 777: {'not loaded' if not planted_ran else 'LOADED'}, "
        f"{_gist(r['error']) if refused else 'not refused'}",
        wall,
        "refused" if refused else r.get("status", "exception"),
        refused and not planted_ran,
        "the planted library never loaded; one-line refusal",
    )


def full_disk_rows(out=print) -> list[RealTimeRow]:
    """A script's default LinearMPC of nlink:13 with its cache on a full file system (a filled tmpfs,
    :func:`ocpkit.benchmarks.readonly.run_full`; root with mount namespaces only): the Python step, success, one
    warning naming the folder as full, nothing raised."""
    import tempfile
    from pathlib import Path

    from ocpkit.benchmarks import readonly

    if readonly.method() != readonly.BIND_MOUNT:
        out("cache rows: the full-disk one skipped (a full file system needs root with mount namespaces)")
        return []
    with tempfile.TemporaryDirectory(prefix="ocpkit-bench-full-") as tmp:
        root = Path(tmp) / "cache"
        root.mkdir(mode=0o700)
        r = _script_result(readonly.run_full(root, _cache_script(0), **_script_options(root, tmp)))
    return [
        _script_row(
            "full disk",
            "qp condensed daqp (default)",
            "filled tmpfs",
            r,
            f"{root}/native is full",
            "Python step, success, one warning naming the folder as full, nothing raised",
        )
    ]
