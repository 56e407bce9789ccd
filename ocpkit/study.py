"""Studies: a trial function run over a grid of parameter sets, resumably and in parallel.

Trials run in local worker processes (spawn-started) or on a Dask distributed cluster (whose scheduler and
workers must run this process's ocpkit version and code); the parent process writes each finished trial to the
:mod:`ocpkit.store` as it completes (workers never write it), so an interrupted study resumes where it stopped and a
trial that raises is stored as failed.
Before a trial starts, the parent **claims** it in the store (a lease renewed by a heartbeat),
so several processes on one folder share the grid and run each trial once, and the trials of
a claimant that died are taken over. Each trial records the package version and a hash of the
code it runs (its module, the ocpkit and user modules that imports, the user files its parameters name)
and of the numerical libraries' versions (:mod:`ocpkit.provenance`); resuming refuses trials computed by
other code, naming what changed, unless told what to do with them.
"""
from __future__ import annotations

import contextlib
import itertools
import multiprocessing
import os
import pickle
import signal
import sys
import threading
import time
import traceback
from collections import Counter, deque
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import FIRST_COMPLETED, CancelledError, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from . import __version__, provenance
from ._checks import choice, integer
from .kernels import CPU_THREADS
from .store import RESERVED, Store, StoreError, canonical_key, now, owner_id, split_result

STALE = ("refuse", "reuse", "rerun")
_TIMEOUT_EXIT = 124  # exit status of a worker whose trial ignored its timeout
LEASE = 60.0  # seconds a claim lives without a heartbeat


class StaleTrialsError(ValueError):
    """Stored trials were computed by another package version, other code or other dependency versions."""


class TrialTimeout(Exception):
    """Raised inside a trial that ran longer than its timeout."""


class ClusterMismatchError(ValueError):
    """A Dask scheduler or worker cannot import ocpkit or the trial, or runs another ocpkit version, other study code
    or other numerical libraries than the process running the study."""


class SchedulerLostError(ConnectionError):
    """The connection to the Dask scheduler was lost while a study ran on it."""


@dataclass(frozen=True)
class _Provenance:
    """What this process computes trials with: its ocpkit version, each trial's code hash (by canonical key) and
    each code hash's manifest."""

    version: str
    codes: dict
    manifests: dict


def package_version() -> str:
    """The ocpkit version running (``ocpkit.__version__``, which the package metadata is built from)."""
    return __version__


def code_hash(fn, params: Mapping | None = None) -> str:
    """The hash a trial of ``fn`` with ``params`` is stored with: of the code it runs and the numerical
    libraries' versions (see :mod:`ocpkit.provenance`)."""
    return provenance.manifest_hash(provenance.manifest(fn, params))


@dataclass(frozen=True)
class Study:
    """A named experiment: ``fn(**params) -> dict`` of metrics (scalars, and arrays if wanted)
    for every parameter dict in ``trials``.

    ``fn`` must be a module-level function so worker processes can import it.
    """

    name: str
    fn: Callable[..., Mapping]
    trials: tuple[dict, ...]

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name.strip():
            raise TypeError(f"name must be a non-empty string, got {self.name!r}")
        _check_importable(self.fn)
        if isinstance(self.trials, (str, Mapping)) or not isinstance(self.trials, Iterable):
            raise TypeError(f"trials must be a list of parameter dicts, got {self.trials!r}")
        trials, seen = [], {}
        for i, params in enumerate(self.trials):
            key = canonical_key(params) if isinstance(params, Mapping) else None
            if key is None:
                raise TypeError(f"trials[{i}] must be a dict of parameters, got {params!r}")
            for name in params:
                if not name.isidentifier() or name in RESERVED:
                    raise ValueError(f"trials[{i}] parameter name {name!r} must be a Python identifier "
                                     f"and not one of {RESERVED}")
            if key in seen:
                raise ValueError(f"trials[{i}] repeats trials[{seen[key]}]: {key}")
            seen[key] = i
            trials.append(dict(params))
        object.__setattr__(self, "trials", tuple(trials))


def grid(*, seeds=None, **axes) -> list[dict]:
    """All combinations of the ``axes`` values (the last axis varies fastest), then a ``seed``
    axis last: ``seeds=n`` gives seeds 0…n-1, or pass the seeds themselves.

    A string or other non-list value is a fixed parameter: ``grid(robot="puma560", knots=[2, 4])``.
    """
    if seeds is not None:
        if "seed" in axes:
            raise ValueError("give seeds either as seeds= or as a seed axis, not both")
        if isinstance(seeds, (int, np.integer)) and not isinstance(seeds, bool):
            seeds = range(integer(seeds, "seeds", 1))
        axes["seed"] = seeds
    values = {}
    for name, axis in axes.items():
        if isinstance(axis, np.ndarray):
            axis = axis.tolist()
        if isinstance(axis, (str, bytes, Mapping)) or not isinstance(axis, Iterable):
            axis = [axis]
        values[name] = list(axis)
        if not values[name]:
            raise ValueError(f"axis {name!r} has no values")
    return [dict(zip(values, combo)) for combo in itertools.product(*values.values())]


def run(study: Study, out_dir, *, workers: int | None = None, scheduler: str | None = None,
        progress: bool = True, retry_failed: bool = False, trial_timeout: float | None = None,
        stale: str = "refuse", lease: float = LEASE) -> pd.DataFrame:
    """Run the study's trials not yet stored in ``out_dir`` and return all its trials as a table.

    Trials run on ``workers`` local processes (default: one per CPU), or on the Dask cluster
    at ``scheduler`` ("tcp://host:port"; :class:`ClusterMismatchError` if its scheduler or a worker runs another
    ocpkit version or other code, :class:`SchedulerLostError` if the scheduler goes away). Each trial is claimed in
    the store before it starts, so other processes running the same study on the same folder take other trials; a
    claim lives ``lease`` seconds unless renewed (a heartbeat renews it while this process runs), and the
    claims of a process that died on this host are taken over at once. Each finished trial is
    committed as it arrives; a trial that raises (or kills its worker, or runs longer than
    ``trial_timeout`` seconds) is stored as failed and the rest go on. Stored failures are
    skipped like successes unless ``retry_failed``. Stored trials computed by another package
    version, other code or other versions of the numerical libraries (see :func:`code_hash`) make
    the run raise :class:`StaleTrialsError`, naming what changed, unless ``stale`` is "reuse" (keep
    them) or "rerun" (compute them again). On Ctrl-C the workers are stopped and KeyboardInterrupt
    propagates; every trial finished before it stays stored. At the end the store is checkpointed, so ``results.sqlite``
    alone holds every trial. Columns as in :meth:`Store.load`, rows in grid order.
    """
    if not isinstance(study, Study):
        raise TypeError(f"study must be a Study, got {type(study).__name__}")
    if scheduler is not None:
        if not isinstance(scheduler, str) or not scheduler:
            raise TypeError(f"scheduler must be a Dask scheduler address like 'tcp://host:8786', got {scheduler!r}")
        if workers is not None:
            raise ValueError("workers applies to local processes; a Dask cluster (scheduler=) brings its own")
    workers = (os.cpu_count() or 1) if workers is None else integer(workers, "workers", 1)
    choice(stale, STALE, "stale")
    if trial_timeout is not None:
        if isinstance(trial_timeout, bool) or not isinstance(trial_timeout, (int, float)) or \
                not np.isfinite(trial_timeout) or trial_timeout <= 0:
            raise ValueError(f"trial_timeout must be a positive number of seconds, got {trial_timeout!r}")
    if isinstance(lease, bool) or not isinstance(lease, (int, float)) or not lease > 0:
        raise ValueError(f"lease must be a positive number of seconds, got {lease!r}")
    version = package_version()
    keys = {canonical_key(p): p for p in study.trials}
    current = provenance.manifests(study.fn, study.trials)  # hashed once per run, each file read once per process
    codes = {key: code for key, (code, _) in zip(keys, current)}
    manifests = dict(current)
    with Store(out_dir) as store:
        stored = store.provenance(study.name)
        old = {k: row for k, row in stored.items() if k in keys and (row[2], row[3]) != (version, codes[k])}
        if old and stale == "refuse":
            raise StaleTrialsError(_stale_message(study.name, store.path, old, len(stored), version, codes, manifests,
                                                  store.code(row[3] for row in old.values())))
        run_start, owner = now(), owner_id()

        def done(key, row) -> bool:
            if row is None:
                return False
            redo = (row[0] == "failed" and retry_failed) or \
                (stale == "rerun" and (row[2], row[3]) != (version, codes[key]))
            return not (redo and row[1] < run_start)  # redone by any process since this run began: done

        todo = [k for k in keys if not done(k, stored.get(k))]
        if todo and store.readonly:
            store._writable()
        if todo:
            store.record_code({codes[k]: manifests[codes[k]] for k in todo})
        source = _Claims(store, study.name, todo, keys, owner, lease, done)
        executed, t0 = 0, time.perf_counter()
        placement = Counter()  # Dask worker address -> trials of this run it ran
        if not todo:
            finished = iter(())
        elif scheduler is None:
            finished = _run_local(study.fn, source, max(1, min(workers, len(todo))), trial_timeout)
        else:
            finished = _run_dask(study.fn, source, scheduler, trial_timeout, _Provenance(version, codes, manifests),
                                 placement)
        failed = 0
        with tqdm(total=len(study.trials), initial=len(study.trials) - len(todo), desc=study.name,
                  unit="trial", disable=not progress, dynamic_ncols=True) as bar:
            heartbeat = _Heartbeat(store.path.parent, owner, lease) if todo else None
            try:
                for params, outcome in finished:
                    store.write(study.name, params, **outcome, version=version, code=codes[canonical_key(params)],
                                owner=owner)
                    executed += 1
                    if outcome["status"] == "failed":
                        failed += 1
                        bar.set_postfix(failed=failed, refresh=False)
                    bar.update()
            finally:
                with contextlib.suppress(StoreError):
                    finished.close() if hasattr(finished, "close") else None
                if heartbeat is not None:
                    heartbeat.stop()
                if todo:
                    with contextlib.suppress(StoreError):
                        store.release(owner, study.name)
                        if executed:
                            store.record_run(study.name, owner, run_start, time.perf_counter() - t0, executed)
                        store.checkpoint()
        wall = time.perf_counter() - t0
        df = store.load(study.name, trials=study.trials)
    if scheduler is not None:
        df.attrs["cluster"] = {"scheduler": scheduler, "workers": dict(placement), "wall": wall}
    return df


def failure_summary(df: pd.DataFrame, top: int = 5) -> str:
    """A report paragraph counting a study table's failed trials and its most common errors ("" if none)."""
    failed = df[df["status"] == "failed"]
    if not len(failed):
        return ""
    errors = failed["error"].fillna("(no message)").value_counts().head(top)
    return f"\n{len(failed)} of {len(df)} trials failed; most common errors:\n\n" + "\n".join(
        f"- {count}× `{(err.splitlines() or [''])[0][:200]}`" for err, count in errors.items()) + "\n"


def cluster_summary(df: pd.DataFrame) -> str:
    """A report paragraph saying where the trials of the run that returned ``df`` ran when it used a Dask scheduler
    ("" otherwise): each worker's address and how many trials it ran, the wall time and the throughput."""
    cluster = df.attrs.get("cluster")
    if not cluster:
        return ""
    n, wall = sum(cluster["workers"].values()), cluster["wall"]
    if not n:
        return f"\nRun on the Dask cluster at {cluster['scheduler']}: no trial was left to run.\n"
    each = ", ".join(f"{address} {count}" for address, count in sorted(cluster["workers"].items()))
    return (f"\nRun on the Dask cluster at {cluster['scheduler']}: {n} trials on {len(cluster['workers'])} workers in "
            f"{wall:.1f} s ({n / wall:.2f} trials/s); trials per worker: {each}.\n")


def _stale_message(name, path, old, n_stored, version, codes, manifests, recorded) -> str:
    """Why stored trials ``old`` ({key: provenance row}) are stale: the versions, modules, files and dependency
    versions that changed since they were computed (``recorded``: the stored manifests by code hash)."""
    reasons = {}
    for key, row in old.items():
        if row[2] != version:
            reasons[f"ocpkit {row[2] or '?'} → {version}"] = None
        if row[3] != codes[key]:
            reasons.update(dict.fromkeys(provenance.changes(recorded.get(row[3]), manifests[codes[key]])))
    reasons = list(reasons)
    text = "; ".join(reasons[:6]) + (f"; and {len(reasons) - 6} more differences" if len(reasons) > 6 else "")
    return (f"{len(old)} of the {n_stored} stored trials of study {name!r} in {path} were computed by other code "
            f"({text or 'unknown'}): pass --reuse-stale (stale='reuse') to keep them, --rerun-stale (stale='rerun') "
            f"to compute them again, or choose another --out")


class _Claims:
    """The trials this process may run, claimed from the store one at a time as workers free up."""

    def __init__(self, store: Store, study: str, todo: list, params: dict, owner: str, lease: float, done):
        self.store, self.study, self.params, self.owner, self.lease = store, study, params, owner, lease
        self.remaining, self.done, self.others = list(todo), done, 0

    def take(self) -> dict | None:
        """Claim the next trial no process has; None when there is none now (``others`` says how many other
        processes hold, so the caller may wait for them to finish or die)."""
        if not self.remaining:
            self.others = 0
            return None
        finished = set()

        def done(key, row):
            if self.done(key, row):
                finished.add(key)
                return True
            return False
        key, self.others = self.store.claim(self.study, self.remaining, self.owner, self.lease, done=done)
        self.remaining = [k for k in self.remaining if k not in finished and k != key]
        return None if key is None else self.params[key]

    def pause(self) -> None:
        """Wait a little before looking again for trials that other processes hold."""
        time.sleep(min(1.0, self.lease / 10))

    def __len__(self) -> int:
        return len(self.remaining)


class _Heartbeat:
    """Renews this process's claims every lease/4 seconds, on its own thread and database connection."""

    def __init__(self, folder, owner: str, lease: float):
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, args=(folder, owner, lease), daemon=True)
        self._thread.start()

    def _beat(self, folder, owner, lease):
        with contextlib.suppress(Exception), Store(folder) as store:
            while not self._stop.wait(lease / 4):
                store.renew(owner, lease)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def _check_importable(fn) -> None:
    if not callable(fn):
        raise TypeError(f"fn must be a callable trial function, got {fn!r}")
    name = getattr(fn, "__qualname__", "")
    if "<lambda>" in name or "<locals>" in name:
        raise TypeError(f"fn must be a module-level function that worker processes can import, got {name}: "
                        "lambdas and nested functions cannot be sent to them")
    if getattr(fn, "__module__", None) == "__main__" and not hasattr(sys.modules["__main__"], "__file__"):
        raise TypeError(f"fn {name} is defined in an interactive session; worker processes cannot import it. "
                        "Define it in a module (a .py file) instead")
    try:
        pickle.dumps(fn)
    except Exception as exc:
        raise TypeError(f"fn must be picklable by reference (a module-level function), got {fn!r}: {exc}") from None


def _execute(fn, params: dict, timeout: float | None = None) -> dict:
    """Run one trial (in a worker); its outcome as keyword arguments of :meth:`Store.write`.

    With a ``timeout``, :class:`TrialTimeout` is raised inside the trial when it expires (see :func:`_deadline`)."""
    started, t0 = now(), time.perf_counter()
    try:
        with _deadline(timeout):
            metrics, arrays = split_result(params, fn(**params))
        outcome = {"result": {**metrics, **arrays}, "status": "ok"}
    except TrialTimeout:  # raised without its message on a worker thread (an asynchronous exception)
        outcome = {"status": "failed", "error": _timeout_message(timeout), "traceback": traceback.format_exc()}
    except Exception as exc:
        outcome = {"status": "failed", "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
    return {**outcome, "wall_time": time.perf_counter() - t0, "started": started, "finished": now()}


def _timeout_message(timeout: float) -> str:
    return f"TrialTimeout: the trial ran longer than the trial timeout of {timeout:g} s and was stopped"


@contextlib.contextmanager
def _deadline(timeout: float | None):
    """Raise :class:`TrialTimeout` in the trial after ``timeout`` seconds: by SIGALRM on a worker process's main
    thread, where a trial stuck in C code also takes its worker down shortly after (the pool reports it as dead);
    on another thread (a Dask worker's) as an asynchronous exception, which Python raises between two bytecodes,
    so a trial stuck in C code runs on and the client abandons it (:func:`_dask_outcomes`)."""
    if timeout is None:
        yield
    elif threading.current_thread() is threading.main_thread():
        with _alarm(timeout):
            yield
    else:
        with _thread_alarm(timeout):
            yield


@contextlib.contextmanager
def _alarm(timeout: float):
    def expire(signum, frame):
        raise TrialTimeout(_timeout_message(timeout).partition(": ")[2])
    previous = signal.signal(signal.SIGALRM, expire)
    killer = threading.Timer(timeout + _grace(timeout), os._exit, args=(_TIMEOUT_EXIT,))
    killer.daemon = True
    killer.start()
    signal.setitimer(signal.ITIMER_REAL, timeout)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        killer.cancel()
        signal.signal(signal.SIGALRM, previous)


@contextlib.contextmanager
def _thread_alarm(timeout: float):
    import ctypes

    thread, lock, state = ctypes.c_ulong(threading.get_ident()), threading.Lock(), {"running": True, "fired": False}

    def expire():
        with lock:
            if state["running"]:
                state["fired"] = ctypes.pythonapi.PyThreadState_SetAsyncExc(thread, ctypes.py_object(TrialTimeout)) == 1
    timer = threading.Timer(timeout, expire)
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
        with lock:
            state["running"] = False
            if state["fired"]:  # not raised yet (the trial returned first): withdraw it, or it lands in Dask's code
                ctypes.pythonapi.PyThreadState_SetAsyncExc(thread, None)


def _grace(timeout: float) -> float:
    """How long past its timeout a trial that does not return to Python is waited for."""
    return max(2.0, 0.5 * timeout)


def _failure(message: str) -> dict:
    """The outcome of a trial that ended outside the trial function (its worker died, say)."""
    return {"status": "failed", "error": message, "started": now(), "finished": now()}


def _worker_init(parent: int) -> None:
    # The parent handles Ctrl-C and stops the workers; a worker orphaned by a killed parent exits.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=_exit_when_orphaned, args=(parent,), daemon=True).start()


def _exit_when_orphaned(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(1)


def _run_local(fn, source: _Claims, workers: int, timeout: float | None = None):
    """Yield (params, outcome) as trials finish on a pool of spawn-started processes.

    At most ``workers`` trials are in flight, so when a worker dies the culprit is among them:
    alone, it is stored as failed; otherwise they all become suspects and rerun one at a time.
    """
    with _thread_budget(max(1, (os.cpu_count() or 1) // workers)):
        yield from _run_pool(fn, source, workers, timeout)


@contextlib.contextmanager
def _thread_budget(threads: int):
    """Spawned workers inherit this environment: each gets ``threads`` BLAS/OpenMP/Taichi threads, so
    parallel trials do not oversubscribe the cores (and the solve times they measure stay honest).
    Variables the user has set are kept."""
    names = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", CPU_THREADS)
    saved = {name: os.environ.get(name) for name in names}
    for name in names:
        os.environ.setdefault(name, str(threads))
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)


def _run_pool(fn, source: _Claims, workers: int, timeout: float | None = None):
    suspects = deque()
    context = multiprocessing.get_context("spawn")  # fork is unsafe with Taichi/CUDA threads
    while True:
        pool = None
        running = {}  # future -> (params, when it was submitted)
        try:
            broken = False
            while not broken:
                submit = []
                if suspects:
                    if not running:
                        submit.append(suspects.popleft())
                else:
                    while len(running) + len(submit) < workers:
                        params = source.take()
                        if params is None:
                            break
                        submit.append(params)
                if submit and pool is None:
                    pool = ProcessPoolExecutor(workers, mp_context=context, initializer=_worker_init,
                                               initargs=(os.getpid(),))
                for params in submit:
                    running[pool.submit(_execute, fn, params, timeout)] = (params, time.monotonic())
                if not running:
                    if suspects:
                        continue
                    if not source.others:
                        return  # every trial is stored, by this process or another
                    source.pause()  # other processes hold the rest: wait until they store them or die
                    continue
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                if any(isinstance(f.exception(), BrokenProcessPool) for f in done):
                    broken, done = True, wait(running).done
                crashed = []
                for future in done:
                    (params, submitted), exc = running.pop(future), future.exception()
                    if exc is None:
                        yield params, future.result()
                    elif isinstance(exc, BrokenProcessPool):
                        crashed.append((params, submitted))
                    else:  # the trial or its outcome could not be pickled, say
                        yield params, _failure(f"{type(exc).__name__}: {exc}")
                if len(crashed) == 1:
                    params, submitted = crashed[0]
                    if timeout is not None and time.monotonic() - submitted >= timeout:
                        yield params, _failure(_timeout_message(timeout) + " (it did not return to Python, so its "
                                                                          "worker process was ended)")
                    else:
                        yield params, _failure("the worker process died while running this trial "
                                               "(killed by a signal, os._exit, a segfault or out of memory)")
                else:
                    suspects.extend(params for params, _ in crashed)
        except BaseException:
            # Python 3.11 has no public way to stop busy workers; terminate them so Ctrl-C is prompt.
            if pool is not None:
                for process in list((pool._processes or {}).values()):
                    process.terminate()
            raise
        finally:
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)


def _run_dask(fn, source: _Claims, scheduler: str, timeout: float | None, mine: _Provenance, placement: Counter):
    """(params, outcome) pairs as trials finish on the Dask cluster at ``scheduler``, counting in ``placement``
    the trials each worker ran: a generator, but whether distributed is installed and the scheduler answers
    are checked now."""
    try:
        from distributed import Client
    except ImportError:
        raise ImportError('running a study on a Dask cluster needs distributed: pip install "ocpkit[dask]"') from None
    check_scheduler(scheduler)
    return _dask_outcomes(Client, fn, source, scheduler, timeout, mine, placement)


def check_scheduler(scheduler: str, timeout: float = 5.0) -> None:
    """Raise ConnectionError (one line) unless a TCP connection to the Dask scheduler opens within ``timeout`` s."""
    import socket
    from urllib.parse import urlsplit

    if not isinstance(scheduler, str):
        raise TypeError(f"scheduler must be an address like 'tcp://host:8786', got {scheduler!r}")
    address = scheduler if "://" in scheduler else f"tcp://{scheduler}"
    parts = urlsplit(address)
    try:
        host, port = parts.hostname, parts.port
    except ValueError:
        host = port = None
    if parts.scheme not in ("tcp", "tls") or not host or not port:
        raise ValueError(f"scheduler must be an address like 'tcp://host:8786', got {scheduler!r}")
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except OSError as exc:
        reason = exc.strerror or str(exc) or type(exc).__name__
        raise ConnectionError(f"cannot reach the Dask scheduler at {scheduler} ({reason}); start one "
                              f"(`dask scheduler`) or check the address") from None


def _dask_outcomes(Client, fn, source: _Claims, scheduler: str, timeout: float | None, mine: _Provenance,
                   placement: Counter):
    """The generator behind :func:`_run_dask`. The scheduler, then each worker as it joins, is refused unless it
    runs this process's ocpkit version (:func:`_check_versions`); each worker checks its code on its first trial
    (:func:`_execute_remote`). Dask reruns the trials of a worker that died on the others."""
    with _quiet_once_lost() as lost, Client(scheduler, timeout="10s") as client:
        running = {}  # future -> (params, when submitted)
        _check_versions(client, [], mine.version, scheduler)
        checked, slots, looked = set(), 1, -np.inf
        try:
            while True:
                if time.monotonic() - looked > 1.0:  # workers join and leave (an adaptive cluster, a dead worker)
                    threads = client.nthreads()
                    _check_versions(client, [w for w in threads if w not in checked], mine.version)
                    checked.update(threads)
                    # As many trials in flight as the cluster has threads, so a trial's submission is about its start.
                    slots, looked = max(1, sum(threads.values())), time.monotonic()
                while len(running) < slots:
                    params = source.take()
                    if params is None:
                        break
                    code = mine.codes[canonical_key(params)]
                    running[client.submit(_execute_remote, fn, params, timeout, mine.version, code, pure=False)] = \
                        (params, time.monotonic())
                if not running:
                    if not source.others:
                        return
                    source.pause()
                    continue
                wait_s = 1.0
                if timeout is not None:
                    first = min(t for _, t in running.values()) + timeout + _grace(timeout)
                    wait_s = min(wait_s, max(0.05, first - time.monotonic()))
                for future in _dask_wait_or_none(list(running), wait_s):
                    params, _ = running.pop(future)
                    address, outcome = _received(future, params, scheduler, mine)
                    if address is not None:
                        placement[address] += 1
                    yield params, outcome
                if timeout is not None:
                    # A trial that did not return to Python at its timeout (stuck in C code): its worker thread may
                    # run on, the study does not wait for it.
                    clock = time.monotonic()
                    for future in [f for f, (_, t) in running.items() if clock - t >= timeout + _grace(timeout)]:
                        params, _ = running.pop(future)
                        future.cancel()
                        yield params, _failure(_timeout_message(timeout) + " (abandoned on the Dask cluster)")
        except (CancelledError, OSError) as exc:
            if client.status == "running" and "scheduler-connection-lost" not in str(exc):
                raise
            lost.set()
            raise SchedulerLostError(
                f"lost the connection to the Dask scheduler at {scheduler} mid-study ({len(running)} running trials "
                f"not stored; the {sum(placement.values())} finished in this run are): start a scheduler and rerun "
                "the same command to resume") from None


def _received(future, params: dict, scheduler: str, mine: _Provenance) -> tuple[str | None, dict]:
    """A finished Dask future's (worker address, outcome), releasing it; raises :class:`ClusterMismatchError` when
    the scheduler or the worker could not load the trial or the worker runs other code, CancelledError when the
    future was cancelled (the scheduler went away)."""
    try:
        address, outcome = future.result()
    except ImportError as exc:  # unpickling the trial failed on the worker (the trial's import errors are outcomes)
        raise ClusterMismatchError(f"a Dask worker cannot load the trial ({type(exc).__name__}: {exc}); {_SAME}") \
            from None
    except CancelledError:
        raise
    except Exception as exc:  # e.g. KilledWorker: the trial took down its workers repeatedly
        if "deserialization of the task graph" in str(exc):  # Dask's words for it failing on the scheduler
            raise ClusterMismatchError(f"the Dask scheduler at {scheduler} cannot load the trial "
                                       f"({str(exc).splitlines()[0]}): {_SAME}") from None
        return None, _failure(f"{type(exc).__name__}: {exc}")
    finally:
        future.release()
    if "mismatch" in outcome:
        theirs, manifest = outcome["mismatch"]
        raise ClusterMismatchError(_mismatch_message(f"worker {address}", theirs, mine.version, manifest,
                                                     mine.manifests[mine.codes[canonical_key(params)]]))
    return address, outcome


def _check_versions(client, workers: list, version: str, scheduler: str | None = None) -> None:
    """Refuse the Dask ``workers``, and the scheduler at ``scheduler`` if given (it unpickles every trial too), that
    cannot import ocpkit or run another version of it, before they get a trial (it could not be unpickled there, or
    would run other code). Asked of ocpkit itself: the installed package's metadata, which Dask's get_versions
    reads, says nothing of what imports and lags an editable install."""
    found = {}
    if scheduler is not None:
        try:
            found[f"scheduler {scheduler}"] = client.run_on_scheduler(package_version)
        except Exception as exc:  # raised where it could not be unpickled
            found[f"scheduler {scheduler}"] = exc
    if workers:
        found.update((f"worker {address}", theirs) for address, theirs in
                     client.run(package_version, workers=workers, on_error="return").items())
    for where, theirs in found.items():
        if isinstance(theirs, BaseException):
            raise ClusterMismatchError(f"the Dask {where} cannot import ocpkit ({theirs}), this process runs ocpkit "
                                       f"{version}: {_SAME}")
        if theirs != version:
            raise ClusterMismatchError(_mismatch_message(where, theirs, version))


_VERIFIED: set = set()  # (version, code hash) pairs a Dask worker process found its own code to match


def _execute_remote(fn, params: dict, timeout: float | None, version: str, code: str):
    """:func:`_execute` on a Dask worker: (the worker's address, the outcome). A worker first checks, once per code
    hash, that it runs the client's ocpkit version and code: if not, the outcome is ``{"mismatch": (its version,
    its manifest)}`` and the trial is not run."""
    from distributed import get_worker

    address = get_worker().address
    if (version, code) not in _VERIFIED:
        theirs = provenance.manifest(fn, params)
        if package_version() != version or provenance.manifest_hash(theirs) != code:
            return address, {"mismatch": (package_version(), theirs)}
        _VERIFIED.add((version, code))
    return address, _execute(fn, params, timeout)


_SAME = ("install the same ocpkit, study code and numerical libraries on the scheduler and every worker (or stop "
         "that worker) and rerun")


def _mismatch_message(where: str, their_version, version: str, their_manifest=None, manifest=None) -> str:
    """Why the Dask ``where`` ("worker tcp://…") is refused: its ocpkit version, or what differs between the
    manifest of the trial's code there and here (:mod:`ocpkit.provenance`)."""
    if their_version != version:
        return f"the Dask {where} runs ocpkit {their_version}, this process ocpkit {version}: {_SAME}"
    differences = provenance.changes(manifest, their_manifest)
    text = "; ".join(differences[:6]) + (f"; and {len(differences) - 6} more" if len(differences) > 6 else "")
    return f"the Dask {where} runs other code than this process (here → there: {text or 'unknown'}): {_SAME}"


@contextlib.contextmanager
def _quiet_once_lost():
    """An Event to set when the study has lost its scheduler: from then on, the Dask client's own log records (its
    failed reconnection, the traceback of the attempt cancelled as it closes) stay off the terminal, since the study
    reports the loss itself in one line (:class:`SchedulerLostError`)."""
    import logging

    lost = threading.Event()

    def keep(record) -> bool:
        return not lost.is_set()
    logger = logging.getLogger("distributed.client")
    logger.addFilter(keep)
    try:
        yield lost
    finally:
        logger.removeFilter(keep)


def _dask_wait_or_none(futures, timeout: float):
    from distributed import wait

    try:
        return wait(futures, timeout=timeout, return_when="FIRST_COMPLETED").done
    except TimeoutError:
        return set()
