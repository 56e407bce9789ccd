"""Several processes on one study folder, trial timeouts and stale trials.

No test here waits on a clock: trials block on a gate file that the test creates once the state it needs is
reached (both processes hold claims, say); timeouts only guard against hangs.
"""

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ocpkit.runs.store import Store
from ocpkit.runs.study import StaleTrialsError, Study, code_hash, grid, package_version, run

LOG = "OCPKIT_TEST_TRIAL_LOG"
HANG_GUARD = 300  # seconds: only a hang reaches it, however busy the machine


def gated(x, seed, gate):
    """Logs its start, then waits until the file ``gate`` exists."""
    Path(os.environ[LOG], f"{x}-{seed}-{time.time_ns()}-{os.getpid()}").touch()
    while not os.path.exists(gate):
        time.sleep(0.02)
    return {"y": x + seed}


def sleeper(seconds):
    time.sleep(seconds)
    return {"slept": seconds}


def stuck(seconds):
    """Sleeps with SIGALRM blocked: like C code that never returns to Python."""
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGALRM})
    time.sleep(seconds)
    return {"slept": seconds}


def shared_study(out, n, gate):
    """Entry point of the competing subprocesses."""
    run(Study("shared", gated, grid(x=range(n), seeds=1, gate=gate)), out, workers=2, progress=False)


def spawn(out, n, gate, log) -> subprocess.Popen:
    code = f"import test_study_claims as t; t.shared_study({str(out)!r}, {n}, {str(gate)!r})"
    env = {**os.environ, LOG: str(log), "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), *sys.path])}
    return subprocess.Popen([sys.executable, "-c", code], env=env)


def until(condition, what):
    end = time.monotonic() + HANG_GUARD
    while not condition():
        assert time.monotonic() < end, f"hang guard: {what}"
        time.sleep(0.05)


def owners(out) -> dict:
    """{owner pid: claimed x values}"""
    if not (Path(out) / "results.sqlite").exists():
        return {}
    try:
        with Store(out) as store:
            claims = store.claims("shared")
    except Exception:  # the schema is being created
        return {}
    result = {}
    for owner, key in zip(claims.owner, claims.key):
        result.setdefault(int(owner.split(":")[1]), set()).add(json.loads(key)["x"])
    return result


def executions(log: Path) -> dict:
    counts = {}
    for f in log.iterdir():
        x = int(f.name.split("-")[0])
        counts[x] = counts.get(x, 0) + 1
    return counts


@pytest.fixture
def folders(tmp_path):
    log = tmp_path / "log"
    log.mkdir()
    return tmp_path / "out", tmp_path / "gate", log


@contextlib.contextmanager
def competing(out, n, gate, log):
    """Two study processes on one folder, yielded once both hold claims; killed on the way out."""
    a, b = spawn(out, n, gate, log), spawn(out, n, gate, log)
    try:
        until(lambda: {a.pid, b.pid} <= set(owners(out)), "both processes hold claims")
        yield a, b
    finally:
        for p in (a, b):
            p.kill()
            p.wait()


def test_two_processes_share_the_grid_and_run_every_trial_once(folders):
    out, gate, log = folders
    n = 12
    with competing(out, n, gate, log) as (a, b):
        held = owners(out)
        assert not held[a.pid] & held[b.pid]  # a trial is claimed by one process only
        gate.touch()
        assert a.wait(HANG_GUARD) == 0 and b.wait(HANG_GUARD) == 0
    assert executions(log) == {x: 1 for x in range(n)}  # every trial ran exactly once
    with Store(out) as store:
        df = store.load("shared")
        runs = store.runs("shared")
        assert store.claims().empty  # released when done
    assert sorted(df.x) == list(range(n)) and (df.status == "ok").all()
    assert len(runs) == 2 and runs.trials.sum() == n and (runs.trials > 0).all()  # both did part of the grid


def test_a_killed_claimants_trials_are_taken_over(folders):
    out, gate, log = folders
    n = 12
    with competing(out, n, gate, log) as (a, b):
        lost = owners(out)[a.pid]
        until(lambda: lost <= set(executions(log)), "a's workers started its trials")
        a.send_signal(signal.SIGKILL)
        a.wait()
        gate.touch()
        assert b.wait(HANG_GUARD) == 0  # b finishes the grid, a's trials included
    with Store(out) as store:
        df = store.load("shared")
    assert sorted(df.x) == list(range(n)) and (df.status == "ok").all()
    counts = executions(log)
    assert set(counts) == set(range(n))
    # a's workers had started its trials before it died; b ran them again; every other trial ran once
    assert all(counts[x] == (2 if x in lost else 1) for x in range(n)), (counts, lost)


def test_a_trial_that_never_returns_is_stopped_by_the_timeout(tmp_path):
    df = run(
        Study("t", sleeper, [{"seconds": 0.0}, {"seconds": 1e6}]),
        tmp_path,
        workers=2,
        progress=False,
        trial_timeout=1.0,
    )
    assert df.status.tolist() == ["ok", "failed"]
    assert df.error.iloc[1].startswith("TrialTimeout: the trial ran longer than the trial timeout of 1 s")
    # stuck where Python cannot interrupt it: its worker is ended, the trial stored as timed out
    df = run(Study("c", stuck, [{"seconds": 1e6}]), tmp_path, workers=1, progress=False, trial_timeout=0.5)
    assert df.status.tolist() == ["failed"] and "did not return to Python" in df.error.iloc[0]
    with pytest.raises(ValueError, match="trial_timeout"):
        run(Study("t", sleeper, [{"seconds": 0.0}]), tmp_path, trial_timeout=0)


def test_resume_refuses_trials_of_other_code_unless_told(tmp_path, monkeypatch):
    module = tmp_path / "mod" / "stale_trial.py"
    module.parent.mkdir()
    module.write_text(
        "import os, pathlib, time\n"
        "def trial(x):\n"
        "    pathlib.Path(os.environ['LOG'], f'{x}-{time.time_ns()}').touch()\n"
        "    return {'y': 2 * x}\n"
    )
    monkeypatch.syspath_prepend(str(module.parent))
    log = tmp_path / "log"
    log.mkdir()
    monkeypatch.setenv("LOG", str(log))
    import stale_trial

    study = Study("s", stale_trial.trial, grid(x=range(3)))
    df = run(study, tmp_path / "out", workers=1, progress=False)
    assert (df.ocpkit_version == package_version()).all() and (df.code_hash == code_hash(stale_trial.trial)).all()
    assert len(list(log.iterdir())) == 3
    module.write_text(module.read_text() + "# changed\n")
    with pytest.raises(StaleTrialsError, match=r"3 of the 3 stored trials of study 's'.*--reuse-stale"):
        run(study, tmp_path / "out", workers=1, progress=False)
    run(study, tmp_path / "out", workers=1, progress=False, stale="reuse")
    assert len(list(log.iterdir())) == 3  # kept, not recomputed
    df = run(study, tmp_path / "out", workers=1, progress=False, stale="rerun")
    assert len(list(log.iterdir())) == 6 and (df.code_hash == code_hash(stale_trial.trial)).all()
    run(study, tmp_path / "out", workers=1, progress=False)  # now current: nothing to refuse or redo
    assert len(list(log.iterdir())) == 6
