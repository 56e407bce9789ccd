"""Studies: a trial function run over a grid of parameter sets, resumably and in parallel.

Trials run in local worker processes (spawn-started) or on a Dask distributed cluster (whose scheduler and
workers must run this process's ocpkit version and code); the parent process writes each finished trial to the
:mod:`ocpkit.runs.store` as it completes (workers never write it), so an interrupted study resumes where it stopped
and a trial that raises is stored as failed.
Before a trial starts, the parent **claims** it in the store (a lease renewed by a heartbeat),
so several processes on one folder share the grid and run each trial once, and the trials of
a claimant that died are taken over. Each trial records the package version and a hash of the
code it runs (its module, the ocpkit and user modules that imports, the user files its parameters name),
of the numerical libraries' versions and of the environment variables that change results (thread counts, Taichi's
settings: :mod:`ocpkit.runs.provenance`); resuming refuses trials computed by other code or under other settings, naming
what changed, unless told what to do with them.
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
from collections import Counter, deque
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from ocpkit.runs import provenance
from ocpkit._checks import choice, integer
from ocpkit.codegen.kernels import CPU_THREADS
from ocpkit.runs.cluster import check_scheduler, run_dask
from ocpkit.runs.provenance import package_version
from ocpkit.runs.claims import Claims, Heartbeat, OwnProvenance
from ocpkit.runs.rows import RESERVED, canonical_key, now
from ocpkit.runs.store import Store, StoreError, owner_id
from ocpkit.runs.trial import execute, failure, timeout_message

STALE = ("refuse", "reuse", "rerun")
LEASE = 60.0  # seconds a claim lives without a heartbeat


class StaleTrialsError(ValueError):
    """Stored trials were computed by another package version, other code, other dependency versions or under other
    result-changing environment variables."""


def code_hash(fn, params: Mapping | None = None) -> str:
    """The hash a trial of ``fn`` with ``params`` is stored with: of the code it runs, the numerical libraries'
    versions and the environment variables that change results (see :mod:`ocpkit.runs.provenance`)."""
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
                    raise ValueError(
                        f"trials[{i}] parameter name {name!r} must be a Python identifier and not one of {RESERVED}"
                    )
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


def run(
    study: Study,
    out_dir,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
    retry_failed: bool = False,
    trial_timeout: float | None = None,
    stale: str = "refuse",
    lease: float = LEASE,
) -> pd.DataFrame:
    """Run the study's trials not yet stored in ``out_dir`` and return all its trials as a table.

    Trials run on ``workers`` local processes (default: one per CPU), or on the Dask cluster at ``scheduler``
    ("tcp://host:port"; :mod:`ocpkit.runs.cluster`: :class:`~ocpkit.runs.cluster.ClusterMismatchError` if its scheduler
    or a worker runs another ocpkit version or other code, :class:`~ocpkit.runs.cluster.SchedulerLostError` if the
    scheduler goes away; ConnectionError, before ``out_dir`` is created, where no Dask scheduler answers there). Each
    trial is claimed in the store before it starts, so other processes running the same study on the same folder take
    other trials; a claim lives ``lease`` seconds unless renewed (a heartbeat renews it while this process runs), and
    the claims of a process that died on this host are taken over at once. Each finished trial is committed as it
    arrives; a trial that raises (or kills its worker, or runs longer than ``trial_timeout`` seconds) is stored as
    failed and the rest go on. Stored failures are skipped like successes unless ``retry_failed``. Stored trials
    computed by another package version, other code, other versions of the numerical libraries or under other thread
    counts or Taichi settings (see :func:`code_hash`) make the run raise :class:`StaleTrialsError`, naming what changed,
    unless ``stale`` is "reuse" (keep them) or "rerun" (compute them again). On Ctrl-C the workers are stopped and
    KeyboardInterrupt propagates; every trial finished before it stays stored. At the end the store is checkpointed, so
    ``results.sqlite`` alone holds every trial. Columns as in :meth:`Store.load`, rows in grid order.
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
        if (
            isinstance(trial_timeout, bool)
            or not isinstance(trial_timeout, (int, float))
            or not np.isfinite(trial_timeout)
            or trial_timeout <= 0
        ):
            raise ValueError(f"trial_timeout must be a positive number of seconds, got {trial_timeout!r}")
    if isinstance(lease, bool) or not isinstance(lease, (int, float)) or not lease > 0:
        raise ValueError(f"lease must be a positive number of seconds, got {lease!r}")
    version = package_version()
    keys = {canonical_key(p): p for p in study.trials}
    current = provenance.manifests(study.fn, study.trials)  # hashed once per run, each file read once per process
    codes = {key: code for key, (code, _) in zip(keys, current)}
    manifests = dict(current)
    if scheduler is not None:  # before the store is created: a server that is no Dask scheduler leaves nothing
        check_scheduler(scheduler)
    with Store(out_dir) as store:
        stored = store.provenance(study.name)
        old = {k: row for k, row in stored.items() if k in keys and (row[2], row[3]) != (version, codes[k])}
        if old and stale == "refuse":
            raise StaleTrialsError(
                _stale_message(
                    study.name,
                    store.path,
                    old,
                    len(stored),
                    version,
                    codes,
                    manifests,
                    store.code(row[3] for row in old.values()),
                )
            )
        run_start, owner = now(), owner_id()

        def done(key, row) -> bool:
            if row is None:
                return False
            redo = (row[0] == "failed" and retry_failed) or (
                stale == "rerun" and (row[2], row[3]) != (version, codes[key])
            )
            return not (redo and row[1] < run_start)  # redone by any process since this run began: done

        todo = [k for k in keys if not done(k, stored.get(k))]
        if todo and store.readonly:
            store._writable()
        if todo:
            store.record_code({codes[k]: manifests[codes[k]] for k in todo})
        source = Claims(store, study.name, todo, keys, owner, lease, done)
        executed, t0 = 0, time.perf_counter()
        placement = Counter()  # Dask worker address -> trials of this run it ran
        if not todo:
            finished = iter(())
        elif scheduler is None:
            finished = _run_local(study.fn, source, max(1, min(workers, len(todo))), trial_timeout)
        else:
            finished = run_dask(
                study.fn, source, scheduler, trial_timeout, OwnProvenance(version, codes, manifests), placement
            )
        failed = 0
        with tqdm(
            total=len(study.trials),
            initial=len(study.trials) - len(todo),
            desc=study.name,
            unit="trial",
            disable=not progress,
            dynamic_ncols=True,
        ) as bar:
            heartbeat = Heartbeat(store.path.parent, owner, lease) if todo else None
            try:
                for params, outcome in finished:
                    store.write(
                        study.name, params, **outcome, version=version, code=codes[canonical_key(params)], owner=owner
                    )
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
    return (
        f"\n{len(failed)} of {len(df)} trials failed; most common errors:\n\n"
        + "\n".join(f"- {count}× `{(err.splitlines() or [''])[0][:200]}`" for err, count in errors.items())
        + "\n"
    )


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
    return (
        f"\nRun on the Dask cluster at {cluster['scheduler']}: {n} trials on {len(cluster['workers'])} workers in "
        f"{wall:.1f} s ({n / wall:.2f} trials/s); trials per worker: {each}.\n"
    )


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
    return (
        f"{len(old)} of the {n_stored} stored trials of study {name!r} in {path} were computed by other code or "
        f"settings ({text or 'unknown'}): pass --reuse-stale (stale='reuse') to keep them, --rerun-stale "
        f"(stale='rerun') to compute them again, or choose another --out"
    )


def _check_importable(fn) -> None:
    if not callable(fn):
        raise TypeError(f"fn must be a callable trial function, got {fn!r}")
    name = getattr(fn, "__qualname__", "")
    if "<lambda>" in name or "<locals>" in name:
        raise TypeError(
            f"fn must be a module-level function that worker processes can import, got {name}: "
            "lambdas and nested functions cannot be sent to them"
        )
    if getattr(fn, "__module__", None) == "__main__" and not hasattr(sys.modules["__main__"], "__file__"):
        raise TypeError(
            f"fn {name} is defined in an interactive session; worker processes cannot import it. "
            "Define it in a module (a .py file) instead"
        )
    try:
        pickle.dumps(fn)
    except Exception as exc:
        raise TypeError(f"fn must be picklable by reference (a module-level function), got {fn!r}: {exc}") from None


def _worker_init(parent: int) -> None:
    # The parent handles Ctrl-C and stops the workers; a worker orphaned by a killed parent exits.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=_exit_when_orphaned, args=(parent,), daemon=True).start()


def _exit_when_orphaned(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(1)


def _run_local(fn, source: Claims, workers: int, timeout: float | None = None):
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


def _run_pool(fn, source: Claims, workers: int, timeout: float | None = None):
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
                    pool = ProcessPoolExecutor(
                        workers, mp_context=context, initializer=_worker_init, initargs=(os.getpid(),)
                    )
                for params in submit:
                    running[pool.submit(execute, fn, params, timeout)] = (params, time.monotonic())
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
                        yield params, failure(f"{type(exc).__name__}: {exc}")
                if len(crashed) == 1:
                    params, submitted = crashed[0]
                    if timeout is not None and time.monotonic() - submitted >= timeout:
                        yield (
                            params,
                            failure(
                                timeout_message(timeout) + " (it did not return to Python, so its "
                                "worker process was ended)"
                            ),
                        )
                    else:
                        yield (
                            params,
                            failure(
                                "the worker process died while running this trial "
                                "(killed by a signal, os._exit, a segfault or out of memory)"
                            ),
                        )
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
