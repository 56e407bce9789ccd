"""The study runner and its store: resume after SIGKILL, failures, parallel = serial, exports."""

import contextlib
import json
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from ocpkit.runs.rows import canonical_key
from ocpkit.runs.store import FILENAME, Store
from ocpkit.runs.study import Study, cluster_summary, grid, run

LOG = "OCPKIT_TEST_TRIAL_LOG"  # folder where trials leave one file per execution
TIMING = ["wall_time", "started", "finished"]


# Trial functions live at module level so spawned workers can import them.
def square(x, seed, pause=0.0, crash=None, fail=None):
    """y = x² + seed, plus an array; logs each execution; raises if x == fail, dies if x == crash."""
    if os.environ.get(LOG):
        Path(os.environ[LOG], f"{x}-{seed}-{time.time_ns()}-{os.getpid()}").touch()
    time.sleep(pause)
    if x == fail:
        raise RuntimeError(f"bad x={x}")
    if x == crash:
        os._exit(3)
    return {"y": x * x + seed, "name": f"t{x}", "traj": np.arange(3.0) * x}


def thread_budget(seed):
    """The thread settings a worker process sees."""
    return {name: os.environ.get(name, "") for name in ("OPENBLAS_NUM_THREADS", "OCPKIT_CPU_THREADS")}


def executions(log: Path) -> dict:
    counts = {}
    for f in log.iterdir():
        x, seed = f.name.split("-")[:2]
        counts[(int(x), int(seed))] = counts.get((int(x), int(seed)), 0) + 1
    return counts


def kill_study(out, n, pause) -> None:
    """Entry point of the subprocess that the tests kill or interrupt midway."""
    run(Study("slow", square, grid(x=range(n), seeds=1, pause=pause)), out, workers=2, progress=False)


def spawn_study(out, n, pause=0.3) -> subprocess.Popen:
    code = f"import test_study; test_study.kill_study({str(out)!r}, {n}, {pause})"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), *sys.path])}
    # cwd outside the checkout: `python -c` puts the cwd first on sys.path, and the checkout's ocpkit/ (without
    # problems/, solvers/, studies/) would shadow the installed package, so this process would hash other files
    return subprocess.Popen([sys.executable, "-c", code], env=env, cwd=Path(out).parent)


def stored_keys(out) -> set:
    if not (Path(out) / FILENAME).exists():
        return set()
    try:
        with sqlite3.connect(Path(out) / FILENAME) as con:
            return {r[0] for r in con.execute("SELECT key FROM trials WHERE status = 'ok'")}
    except sqlite3.OperationalError:  # the table is not created yet
        return set()


HANG_GUARD = 300  # seconds: only a hang reaches it, however busy the machine


def wait_for(condition, timeout=HANG_GUARD):
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.05)


def test_grid_is_the_cartesian_product_with_seeds_last():
    trials = grid(robot="puma560", knots=[2, 4], error=np.array([0.5, 1.5]), seeds=2)
    assert len(trials) == 8
    assert trials[0] == {"robot": "puma560", "knots": 2, "error": 0.5, "seed": 0}
    assert trials[1] == {"robot": "puma560", "knots": 2, "error": 0.5, "seed": 1}
    assert trials[-1] == {"robot": "puma560", "knots": 4, "error": 1.5, "seed": 1}
    assert [t["seed"] for t in grid(x=1, seeds=[7, 9])] == [7, 9]
    assert grid(x=[1, 2]) == [{"x": 1}, {"x": 2}]
    with pytest.raises(ValueError, match="'x'"):
        grid(x=[])
    with pytest.raises(ValueError, match="seeds"):
        grid(seed=[1], seeds=2)
    with pytest.raises(ValueError, match="seeds"):
        grid(x=1, seeds=0)


def test_canonical_key_is_stable():
    a = canonical_key({"b": 0.1, "a": (1, 2), "c": {"z": None, "y": True}})
    b = canonical_key({"c": {"y": np.bool_(True), "z": None}, "a": np.array([1, 2]), "b": np.float64(0.1)})
    assert a == b == '{"a":[1,2],"b":0.1,"c":{"y":true,"z":null}}'
    assert canonical_key({"x": -0.0}) == canonical_key({"x": 0.0})
    assert canonical_key({"x": 0.1 + 0.2}) != canonical_key({"x": 0.3})
    assert json.loads(canonical_key({"x": 1 / 3}))["x"] == 1 / 3
    with pytest.raises(ValueError, match=r"params\['x'\]"):
        canonical_key({"x": float("nan")})
    with pytest.raises(TypeError, match=r"params\['x'\]"):
        canonical_key({"x": object()})
    with pytest.raises(TypeError, match="params"):
        canonical_key([1, 2])


def nested_factory():
    def inner(x):
        return {}

    return inner


def test_study_rejects_bad_input(tmp_path):
    with pytest.raises(TypeError, match="module-level"):
        Study("s", lambda x: {}, [{"x": 1}])
    with pytest.raises(TypeError, match="module-level"):
        Study("s", nested_factory(), [{"x": 1}])
    with pytest.raises(TypeError, match="name"):
        Study("", square, [{"x": 1}])
    with pytest.raises(ValueError, match=r"trials\[1\] repeats trials\[0\]"):
        Study("s", square, [{"x": 1.0}, {"x": np.float64(1.0)}])
    with pytest.raises(ValueError, match="status"):
        Study("s", square, [{"status": 1}])
    with pytest.raises(TypeError, match=r"trials\[0\]"):
        Study("s", square, [3])
    study = Study("s", square, grid(x=1, seeds=1))
    with pytest.raises(ValueError, match="workers"):
        run(study, tmp_path, workers=0)
    with pytest.raises(TypeError, match="workers"):
        run(study, tmp_path, workers=1.5)
    with pytest.raises(ValueError, match="workers"):
        run(study, tmp_path, workers=2, scheduler="tcp://127.0.0.1:1")
    with pytest.raises(TypeError, match="study"):
        run("s", tmp_path)


def test_one_and_two_workers_store_the_same_results_and_export_csv(tmp_path, capsys):
    study = Study("sq", square, grid(x=range(4), seeds=2))
    one = run(study, tmp_path / "one", workers=1)
    two = run(study, tmp_path / "two", workers=2, progress=False)
    assert "sq: 100%" in capsys.readouterr().err  # the progress bar
    pd.testing.assert_frame_equal(one.drop(columns=TIMING), two.drop(columns=TIMING))
    assert list(one.columns[:6]) == ["study", "seed", "x", "y", "name", "status"]
    assert one.attrs == {"params": ["seed", "x"], "metrics": ["y", "name"]}
    assert (one.status == "ok").all() and (one.wall_time > 0).all()
    assert one.y.tolist() == [x * x + s for x in range(4) for s in range(2)]
    with Store(tmp_path / "two") as store:
        np.testing.assert_array_equal(store.arrays("sq", {"x": 3, "seed": 1})["traj"], [0.0, 3.0, 6.0])
        csv = pd.read_csv(store.to_csv(tmp_path / "sq.csv"))
    assert len(csv) == 8 and set(csv.columns) == set(one.columns)
    assert sorted(csv.y) == sorted(one.y)


def test_workers_share_the_cores_without_oversubscribing(tmp_path, monkeypatch):
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OCPKIT_CPU_THREADS"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 8)
    df = run(Study("threads", thread_budget, grid(seeds=2)), tmp_path / "a", workers=2, progress=False)
    assert (df["OPENBLAS_NUM_THREADS"] == "4").all() and (df["OCPKIT_CPU_THREADS"] == "4").all()
    assert "OPENBLAS_NUM_THREADS" not in os.environ  # the parent's environment is restored
    monkeypatch.setenv("OCPKIT_CPU_THREADS", "3")  # the user's own setting wins
    df = run(Study("threads", thread_budget, grid(seeds=4)), tmp_path / "b", workers=4, progress=False)
    assert (df["OPENBLAS_NUM_THREADS"] == "2").all() and (df["OCPKIT_CPU_THREADS"] == "3").all()


def test_failures_are_recorded_and_the_study_goes_on(tmp_path, monkeypatch):
    log = tmp_path / "log"
    log.mkdir()
    monkeypatch.setenv(LOG, str(log))
    trials = grid(x=range(5), seeds=1, fail=2, crash=4)
    df = run(Study("f", square, trials), tmp_path / "out", workers=2, progress=False)
    assert df.status.tolist() == ["ok", "ok", "failed", "ok", "failed"]
    raised, died = df.iloc[2], df.iloc[4]
    assert raised.error == "RuntimeError: bad x=2" and "raise RuntimeError" in raised.traceback
    assert "worker process died" in died.error
    assert df.y.isna().tolist() == [False, False, True, False, True]
    # a stored failure is not retried unless asked
    before = sum(executions(log).values())
    run(Study("f", square, trials), tmp_path / "out", workers=1, progress=False)
    assert sum(executions(log).values()) == before
    again = run(Study("f", square, trials), tmp_path / "out", workers=1, progress=False, retry_failed=True)
    assert executions(log)[(2, 0)] == 2 and executions(log)[(0, 0)] == 1
    assert again.status.tolist()[2] == "failed"


def test_resume_after_sigkill_neither_redoes_nor_loses_finished_trials(tmp_path, monkeypatch):
    log, out, n = tmp_path / "log", tmp_path / "out", 16
    log.mkdir()
    monkeypatch.setenv(LOG, str(log))
    process = spawn_study(out, n)
    try:
        wait_for(lambda: len(stored_keys(out)) >= 4)
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait()
    finished = stored_keys(out)
    assert 4 <= len(finished) < n
    wait_for(lambda: not any(_alive(pid) for pid in _worker_pids(log)))  # orphans exit
    df = run(Study("slow", square, grid(x=range(n), seeds=1, pause=0.3)), out, workers=2, progress=False)
    assert df.x.tolist() == list(range(n)) and (df.status == "ok").all()
    counts = executions(log)
    for key in finished:
        assert counts[(json.loads(key)["x"], 0)] == 1, key
    assert set(counts) == {(x, 0) for x in range(n)}


def blocked(x, seed):
    """Trials 0 and 1 return at once; the others log their start and then never return."""
    if x >= 2:
        Path(os.environ[LOG], f"{x}-{seed}-{time.time_ns()}-{os.getpid()}").touch()
        threading.Event().wait()
    return {"y": x}


def interrupted_study(out):
    """Entry point of the subprocess that the Ctrl-C test interrupts.

    Ctrl-C in a terminal reaches a Python whose SIGINT handler raises KeyboardInterrupt. A process started in
    the background by a non-interactive shell (`nohup pytest &`, CI runners) inherits SIGINT as *ignored*, and
    Python then leaves it ignored: the test's SIGINT would do nothing. So the handler is set here, explicitly,
    before any worker starts (the workers' log files, which the test waits for, come after it)."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    run(Study("slow", blocked, grid(x=range(6), seeds=1)), out, workers=2, progress=False)


def test_ctrl_c_stops_workers_promptly_and_keeps_finished_trials(tmp_path, monkeypatch):
    log, out = tmp_path / "log", tmp_path / "out"
    log.mkdir()
    monkeypatch.setenv(LOG, str(log))
    code = f"import test_study; test_study.interrupted_study({str(out)!r})"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), *sys.path])}
    # Its own process group (the study process, its workers, multiprocessing's resource tracker), so that
    # whatever it started is killed on every way out of this test, a failed assertion included.
    process = subprocess.Popen([sys.executable, "-c", code], env=env, start_new_session=True)
    try:
        # Events, not clocks: trials 0 and 1 are stored and both workers are inside trials that never return.
        wait_for(lambda: len(stored_keys(out)) == 2 and len(_worker_pids(log)) == 2)
        workers = _worker_pids(log)
        process.send_signal(signal.SIGINT)
        # The process can end only if it stops its busy workers instead of waiting for them (the timeout is a
        # hang guard, not a speed limit).
        assert process.wait(timeout=HANG_GUARD) != 0
        assert stored_keys(out) == {canonical_key({"x": x, "seed": 0}) for x in (0, 1)}
        # The study process joins its workers before it exits: none outlives it (no wait needed).
        assert not [pid for pid in workers if _alive(pid)]
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
        process.wait()


def _worker_pids(log: Path) -> set:
    return {int(f.name.split("-")[3]) for f in log.iterdir()}


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z" if Path("/proc").exists() else True


def test_parquet_export_error_without_pyarrow(tmp_path):
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        with Store(tmp_path) as store, pytest.raises(ImportError, match="pip install pyarrow"):
            store.to_parquet(tmp_path / "r.parquet")
    else:
        with Store(tmp_path) as store:
            store.write("s", {"x": 1}, {"y": 2.0})
            assert pd.read_parquet(store.to_parquet(tmp_path / "r.parquet")).y.tolist() == [2.0]


def test_dask_local_cluster_matches_local_processes(tmp_path, monkeypatch):
    distributed = pytest.importorskip("distributed")
    # The BLAS threads Dask's nanny sets in this process's environment for its workers, set for both runs: they are
    # part of a trial's provenance, so the two runs store the same code hash.
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        monkeypatch.setenv(name, "1")
    study = Study("sq", square, grid(x=range(4), seeds=2, fail=3))
    local = run(study, tmp_path / "local", workers=2, progress=False)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        remote = run(study, tmp_path / "dask", scheduler=cluster.scheduler_address, progress=False)
        workers = set(cluster.scheduler_info["workers"])
    columns = TIMING + ["traceback"]  # tracebacks name the worker's frames
    pd.testing.assert_frame_equal(local.drop(columns=columns), remote.drop(columns=columns))
    with Store(tmp_path / "dask") as store:
        np.testing.assert_array_equal(store.arrays("sq", study.trials[5])["traj"], [0.0, 2.0, 4.0])
    # Where they ran: each of the cluster's workers, their counts summing to the grid; said in the report.
    where = remote.attrs["cluster"]["workers"]
    assert set(where) <= workers and sum(where.values()) == len(study.trials)
    assert f"on the Dask cluster at {cluster.scheduler_address}: {len(study.trials)} trials on " in cluster_summary(
        remote
    )
    assert cluster_summary(local) == ""
