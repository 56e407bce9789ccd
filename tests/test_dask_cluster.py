"""Studies on a real Dask cluster: `dask scheduler` and `dask worker` processes on 127.0.0.1, `ocpkit study`
against them, and a cluster's faults (a worker killed, the scheduler killed, a worker with other code, a trial
past its timeout). Each trial must be stored exactly once and equal to what local worker processes store."""

import http.server
import json
import math
import os
import re
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import pandas as pd
import pytest

pytest.importorskip("distributed")

from ocpkit.runs import cluster as ocpkit_cluster  # noqa: E402
from ocpkit.cli import main  # noqa: E402
from ocpkit.runs.store import Store  # noqa: E402
from ocpkit.runs.study import Study, grid, run  # noqa: E402

# The scheduler and the workers unpickle trials: this module's trial functions by name, as pytest imported it.
IMPORTABLE = {
    "PYTHONPATH": os.pathsep.join(filter(None, [str(Path(__file__).resolve().parent), os.environ.get("PYTHONPATH")]))
}
# One BLAS/OpenMP/Taichi thread per trial, as `--workers 2` gives each local worker on 2 cores.
THREADS = {name: "1" for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OCPKIT_CPU_THREADS")}
# The smallest robustness grid the CLI runs: a user's problem gets 3 error multipliers × 4 controllers × 2 seeds.
STUDY = ["study", "robustness", "--problem", "pendulum"]
TRIALS = 24
PARAMS = ["error_multiplier", "knots", "problem", "seed"]
# Columns that differ between two runs of the same trial: when and how long it ran, the load, measured times, and
# the code hash (which changes when the checkout is edited between the module's local run and a test's).
MEASURED = [
    "wall_time",
    "started",
    "finished",
    "traceback",
    "load",
    "solve_median",
    "total_median",
    "total_p90",
    "code_hash",
]


def spin(x, seed, seconds=0.0, in_c=False):
    """A trial that runs ``seconds`` in Python (short sleeps, so an exception can reach it) or in one C call."""
    if in_c:
        time.sleep(seconds)
        return {"y": x + seed}
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        time.sleep(0.01)
    return {"y": x + seed}


class Cluster:
    """A Dask scheduler and workers started as the `dask` command line starts them, each in its own process group
    (a worker's nanny and worker process die together), all killed by :meth:`close`."""

    def __init__(self, folder: Path):
        self.folder, self.processes, self.address, self.scheduler_process = folder, [], None, None
        folder.mkdir(parents=True, exist_ok=True)

    def _start(self, command: str, name: str, *args):
        log = open(self.folder / f"{name}.log", "w")
        process = subprocess.Popen(
            [sys.executable, "-m", f"distributed.cli.dask_{command}", *map(str, args)],
            cwd=self.folder,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env={**os.environ, **THREADS, **IMPORTABLE},
        )
        log.close()
        self.processes.append(process)
        return process

    def scheduler(self) -> str:
        """Start a scheduler on a free port (it writes its address to a file); its address."""
        name = f"scheduler{len(self.processes)}"
        file = self.folder / f"{name}.json"
        process = self._start(
            "scheduler",
            name,
            "--host",
            "127.0.0.1",
            "--port",
            "0",
            "--no-dashboard",
            "--scheduler-file",
            file,
            "--idle-timeout",
            "600",
        )
        self.address = _wait_for(lambda: _read_json(file).get("address"), process, "scheduler")
        self.scheduler_process = process
        return self.address

    def workers(self, n: int = 2, preload=None) -> list:
        """Start ``n`` workers (one thread each; trial functions of this module importable) for the current
        scheduler, and wait until it has them."""
        started = []
        for _ in range(n):
            name = f"worker{len(self.processes)}"
            started.append(
                self._start(
                    "worker",
                    name,
                    self.address,
                    "--host",
                    "127.0.0.1",
                    "--nthreads",
                    "1",
                    "--name",
                    name,
                    "--no-dashboard",
                    "--death-timeout",
                    "60",
                    "--local-directory",
                    self.folder,
                    *(["--preload", preload] if preload else []),
                )
            )
            started[-1].name = name
        self._until(lambda names: {p.name for p in started} <= names, started[-1], "workers")
        return started

    def kill(self, process) -> None:
        """SIGKILL a process group (a worker's nanny and worker) and, for a worker, wait until the scheduler has
        let it go."""
        try:
            os.killpg(process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        process.wait()
        if hasattr(process, "name") and self.scheduler_process.poll() is None:  # a worker, its scheduler alive
            self._until(lambda names: process.name not in names, self.scheduler_process, "scheduler")

    def _until(self, condition, process, what: str) -> None:
        """Wait until ``condition`` holds of the names of the scheduler's workers."""
        from distributed import Client

        with Client(self.address, timeout="30s") as client:
            _wait_for(
                lambda: condition({w["name"] for w in client.scheduler_info()["workers"].values()}), process, what
            )

    def close(self) -> None:
        for process in self.processes:
            self.kill(process)


def _read_json(path: Path) -> dict:
    """The JSON object in ``path``; {} while it is missing or half written."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _wait_for(ready, process, what: str, timeout: float = 120):
    deadline = time.monotonic() + timeout
    while not (value := ready()):
        if process.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"the {what} did not start (exit status {process.poll()})")
        time.sleep(0.05)
    return value


@pytest.fixture
def cluster(tmp_path):
    """Processes of a Dask cluster, torn down whatever the test does."""
    cluster = Cluster(tmp_path / "cluster")
    yield cluster
    cluster.close()


def ocpkit(*args, cwd: Path) -> subprocess.Popen:
    """The `ocpkit` command line as a process (in ``cwd``: a checkout as the working directory would shadow the
    installed package)."""
    return subprocess.Popen(
        [sys.executable, "-c", "import sys; from ocpkit.cli import main; sys.exit(main())", *map(str, args)],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, **THREADS},
    )


def finish(process: subprocess.Popen, timeout: float = 300) -> tuple[int, str, str]:
    out, err = process.communicate(timeout=timeout)
    return process.returncode, out, err


def stored(folder: Path) -> int:
    """Trials in the store now (read while a study writes it)."""
    try:
        with sqlite3.connect(f"file:{folder / 'results.sqlite'}?mode=ro", uri=True, timeout=10) as con:
            return con.execute("SELECT count(*) FROM trials").fetchone()[0]
    except sqlite3.Error:
        return 0


def when_stored(folder: Path, n: int, process) -> None:
    """Return once ``n`` trials are stored (fails if the study ended first)."""
    deadline = time.monotonic() + 300
    while stored(folder) < n:
        assert process.poll() is None and time.monotonic() < deadline, finish(process)
        time.sleep(0.05)


def table(folder: Path) -> pd.DataFrame:
    """The stored robustness trials without what differs between two runs of one trial, in a fixed order."""
    with Store(folder) as store:
        df = store.load("robustness")
    return df.drop(columns=MEASURED).sort_values(df.attrs["params"]).reset_index(drop=True)


def writes(folder: Path) -> int:
    """Trials written to the store, summed over every run that wrote there (the runs table counts them)."""
    with Store(folder) as store:
        return int(store.runs()["trials"].sum())


def errors(stderr: str) -> list[str]:
    """The lines of stderr other than the progress bar's."""
    return [
        line for line in stderr.replace("\r", "\n").splitlines() if line.strip() and not line.startswith("robustness:")
    ]


@pytest.fixture(scope="module")
def local(tmp_path_factory):
    """The study's store from 2 local worker processes."""
    folder = tmp_path_factory.mktemp("local")
    code, out, err = finish(ocpkit(*STUDY, "--workers", 2, "--out", folder, cwd=folder))
    assert code == 0, err
    return table(folder)


def test_study_on_a_cluster_stores_what_local_processes_store(cluster, local, tmp_path):
    address = cluster.scheduler()
    cluster.workers(2)
    code, out, err = finish(ocpkit(*STUDY, "--scheduler", address, "--out", tmp_path / "dask", cwd=tmp_path))
    assert code == 0, err
    remote = table(tmp_path / "dask")
    assert len(remote) == TRIALS and (remote["status"] == "ok").all()
    pd.testing.assert_frame_equal(remote, local, check_exact=True)  # bit for bit on CPU
    assert f"{TRIALS}/{TRIALS}" in err  # the progress bar counted the remote trials
    # Where the trials ran, in the report: both workers, their counts summing to the grid.
    line = next(line for line in out.splitlines() if line.startswith("Run on the Dask cluster"))
    assert line.startswith(f"Run on the Dask cluster at {address}: {TRIALS} trials on 2 workers in "), line
    counts = dict(part.rsplit(" ", 1) for part in line.split("trials per worker: ")[1].rstrip(".").split(", "))
    assert len(counts) == 2 and all(a.startswith("tcp://127.0.0.1:") for a in counts)
    assert sum(map(int, counts.values())) == TRIALS
    assert writes(tmp_path / "dask") == TRIALS


@pytest.mark.slow  # 5 s: a worker process is killed mid-trial
def test_a_killed_worker_s_trials_rerun_on_the_other(cluster, local, tmp_path):
    address = cluster.scheduler()
    victim, _ = cluster.workers(2)
    study = ocpkit(*STUDY, "--scheduler", address, "--out", tmp_path / "dask", cwd=tmp_path)
    when_stored(tmp_path / "dask", 4, study)
    cluster.kill(victim)  # nanny and worker, mid-trial: each worker always has one trial in flight
    code, out, err = finish(study)
    assert code == 0, err
    pd.testing.assert_frame_equal(table(tmp_path / "dask"), local, check_exact=True)
    assert writes(tmp_path / "dask") == TRIALS  # each trial stored once


@pytest.mark.slow  # 8 s: the scheduler is killed and a second cluster started
def test_a_lost_scheduler_is_one_line_and_a_new_one_resumes(cluster, local, tmp_path):
    out_dir = tmp_path / "dask"
    first = cluster.scheduler()
    old = cluster.workers(2)
    study = ocpkit(*STUDY, "--scheduler", first, "--out", out_dir, cwd=tmp_path)
    when_stored(out_dir, 4, study)
    cluster.kill(cluster.scheduler_process)
    code, out, err = finish(study)
    assert code == 2 and "Traceback" not in err, err
    lines = errors(err)
    assert len(lines) == 1 and lines[0].startswith(
        f"ocpkit: error: lost the connection to the Dask scheduler at {first} mid-study"
    ), err
    kept = table(out_dir)
    assert 4 <= len(kept) < TRIALS and (kept["status"] == "ok").all()
    # (the dtype of knots is int64 until a traditional MPC trial, knots None, is stored)
    pd.testing.assert_frame_equal(kept, local.merge(kept[PARAMS]), check_exact=True, check_dtype=False)
    with Store(out_dir) as store:
        assert store.claims().empty  # released: a rerun need not wait out their leases
    for process in old:
        cluster.kill(process)
    second = cluster.scheduler()
    cluster.workers(2)
    code, out, err = finish(ocpkit(*STUDY, "--scheduler", second, "--out", out_dir, cwd=tmp_path))
    assert code == 0, err
    pd.testing.assert_frame_equal(table(out_dir), local, check_exact=True)
    assert writes(out_dir) == TRIALS  # the rerun ran only the trials the first run did not store


def test_a_worker_without_ocpkit_or_with_another_version_or_other_code_is_refused(cluster, tmp_path, capsys):
    address = cluster.scheduler()
    preloads = {  # a worker's preload module: what it does to the worker's ocpkit, what the refusal must say
        "lacks": ("import sys\nsys.modules['ocpkit'] = None  # import ocpkit fails\n", "cannot import ocpkit ("),
        "version": ("import ocpkit\nocpkit.__version__ = '0.0.1'\n", "runs ocpkit 0.0.1, this process ocpkit "),
        "numpy": (
            "from ocpkit.runs import provenance\n\n\ndef versions(real=provenance.dependency_versions):\n"
            "    return {**real(), 'numpy': '1.0.0'}\n\n\nprovenance.dependency_versions = versions\n",
            "runs other code than this process (here → there: numpy ",
        ),
    }
    for name, (source, message) in preloads.items():
        preload = tmp_path / f"preload_{name}.py"
        preload.write_text(source)
        workers = cluster.workers(1, preload=preload)
        assert main([*STUDY, "--scheduler", address, "--out", str(tmp_path / name)]) == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err
        (line,) = errors(err)
        assert line.startswith("ocpkit: error: the Dask worker tcp://127.0.0.1:") and message in line, line
        assert stored(tmp_path / name) == 0
        for process in workers:
            cluster.kill(process)


@pytest.mark.slow  # 8 s; its local twin: test_study_claims.py, a trial that never returns is stopped
def test_the_trial_timeout_holds_on_remote_workers(cluster, tmp_path):
    address = cluster.scheduler()
    cluster.workers(2)
    # The timeout from a measured baseline, not a fixed second: a study of trivial trials on this cluster (connecting,
    # checking the scheduler and workers, each worker's first trial checking its code), however busy the machine.
    t0 = time.monotonic()
    warm = run(Study("warm", spin, grid(x=range(4), seeds=1)), tmp_path / "warm", scheduler=address, progress=False)
    assert (warm["status"] == "ok").all()
    timeout = float(math.ceil(3 * (time.monotonic() - t0)))
    # x = 10 runs long in Python: its worker raises the timeout inside it and goes on with the next trial;
    # x = 11 runs long in C: the client abandons it after a grace period. The rest are quick.
    study = Study(
        "spin",
        spin,
        grid(x=range(6), seeds=1, seconds=0.0)
        + [{"x": 10, "seed": 0, "seconds": 20 * timeout}, {"x": 11, "seed": 0, "seconds": 20 * timeout, "in_c": True}],
    )
    df = run(study, tmp_path / "dask", scheduler=address, trial_timeout=timeout, progress=False).set_index("x")
    assert (
        df.loc[10, "status"] == "failed"
        and df.loc[10, "error"]
        == f"TrialTimeout: the trial ran longer than the trial timeout of {timeout:g} s and was stopped"
    )
    assert df.loc[11, "status"] == "failed" and df.loc[11, "error"].endswith("(abandoned on the Dask cluster)")
    assert (df.loc[range(6), "status"] == "ok").all() and df.loc[range(6), "y"].tolist() == list(range(6))
    assert writes(tmp_path / "dask") == len(study.trials)


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):  # off the stderr the test reads
        pass


@pytest.fixture(params=["web server", pytest.param("silent listener", marks=pytest.mark.slow)])  # 4 s each
def not_dask(request):
    """The address of a server that is no Dask scheduler: a web server (``python -m http.server``), or a listener
    whose connections the kernel accepts and nothing ever answers."""
    if request.param == "web server":
        server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _QuietHandler)
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        yield f"tcp://127.0.0.1:{server.server_address[1]}"
        server.shutdown()
        server.server_close()
    else:
        with socket.socket() as listener:
            listener.bind(("127.0.0.1", 0))
            listener.listen()
            yield f"tcp://127.0.0.1:{listener.getsockname()[1]}"


NOT_DASK = r"the server at {} is not a Dask scheduler \(no answer to the Dask handshake within {:g} s\)"


def _closed_port() -> str:
    """An address nothing listens on: refused at once."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return f"tcp://127.0.0.1:{probe.getsockname()[1]}"


def test_a_server_that_is_not_a_dask_scheduler_is_refused_in_time_leaving_nothing(
    not_dask, tmp_path, monkeypatch, capsys
):
    monkeypatch.setattr(ocpkit_cluster, "HANDSHAKE_S", 2.0)

    def refused(address: str, folder: Path) -> float:
        """Seconds that run() then the command line take to refuse ``address``; neither leaves ``folder``."""
        t0 = time.monotonic()
        with pytest.raises(ConnectionError, match=re.escape(f" at {address} ")):
            run(Study("spin", spin, grid(x=range(2), seeds=1)), folder / "api", scheduler=address, progress=False)
        assert (
            main(["study", "robustness", "--problem", "pendulum", "--scheduler", address, "--out", str(folder / "cli")])
            == 2
        )
        assert not (folder / "api").exists() and not (folder / "cli").exists()
        return time.monotonic() - t0

    baseline = refused(_closed_port(), tmp_path / "closed")  # what the two refusals cost without a handshake
    capsys.readouterr()
    assert refused(not_dask, tmp_path) < 2 * 2.0 + 2 * baseline + 1
    (line,) = errors(capsys.readouterr().err)
    assert re.match("ocpkit: error: " + NOT_DASK.format(re.escape(not_dask), 2.0), line), line


@pytest.mark.slow
def test_the_command_line_refuses_a_web_server_as_scheduler_within_its_timeout(tmp_path):
    port = int(_closed_port().rpartition(":")[2])  # free for `python -m http.server`, as a user would start it
    server = subprocess.Popen(
        [sys.executable, "-m", "http.server", str(port), "--bind", "127.0.0.1"],
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )

    def refused(address: str) -> tuple[float, int, str]:
        t0 = time.monotonic()
        code, out, err = finish(
            ocpkit(*STUDY, "--scheduler", address, "--out", tmp_path / "out", cwd=tmp_path), timeout=300
        )
        assert not (tmp_path / "out").exists()
        return time.monotonic() - t0, code, err

    try:
        baseline, code, err = refused(_closed_port())  # the command's start and refusal without a handshake
        assert code == 2 and "cannot reach the Dask scheduler" in err, err
        _wait_for(lambda: socket.socket().connect_ex(("127.0.0.1", port)) == 0, server, "web server")
        elapsed, code, err = refused(f"tcp://127.0.0.1:{port}")
    finally:
        server.kill()
        server.wait()
    assert code == 2 and errors(err) == [
        f"ocpkit: error: the server at tcp://127.0.0.1:{port} is not a Dask "
        "scheduler (no answer to the Dask handshake within 10 s): start one "
        "(`dask scheduler`) or check the address"
    ], err
    assert elapsed < ocpkit_cluster.HANDSHAKE_S + 2 * baseline + 1, (elapsed, baseline)
