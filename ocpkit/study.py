"""Studies: a trial function run over a grid of parameter sets, resumably and in parallel.

Trials run in local worker processes (spawn-started) or on a Dask distributed cluster; the
parent process writes each finished trial to the :mod:`ocpkit.store` as it completes, so an
interrupted study resumes where it stopped and a trial that raises is stored as failed.
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
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from ._checks import integer
from .kernels import CPU_THREADS
from .store import RESERVED, Store, canonical_key, now, split_result


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
        progress: bool = True, retry_failed: bool = False) -> pd.DataFrame:
    """Run the study's trials not yet stored in ``out_dir`` and return all its trials as a table.

    Trials run on ``workers`` local processes (default: one per CPU), or on the Dask cluster
    at ``scheduler`` ("tcp://host:port"). Each finished trial is committed as it arrives; a
    trial that raises (or kills its worker) is stored as failed and the rest go on. Stored
    failures are skipped like successes unless ``retry_failed``. On Ctrl-C the workers are
    stopped and KeyboardInterrupt propagates; every trial finished before it stays stored.
    Columns as in :meth:`Store.load`, rows in grid order.
    """
    if not isinstance(study, Study):
        raise TypeError(f"study must be a Study, got {type(study).__name__}")
    if scheduler is not None:
        if not isinstance(scheduler, str) or not scheduler:
            raise TypeError(f"scheduler must be a Dask scheduler address like 'tcp://host:8786', got {scheduler!r}")
        if workers is not None:
            raise ValueError("workers applies to local processes; a Dask cluster (scheduler=) brings its own")
    workers = (os.cpu_count() or 1) if workers is None else integer(workers, "workers", 1)
    with Store(out_dir) as store:
        stored = store.keys(study.name)
        if retry_failed:
            stored -= store.keys(study.name, status="failed")
        pending = [p for p in study.trials if canonical_key(p) not in stored]
        if scheduler is None:
            finished = _run_local(study.fn, pending, max(1, min(workers, len(pending))))
        else:
            finished = _run_dask(study.fn, pending, scheduler)
        failed = 0
        with tqdm(total=len(study.trials), initial=len(study.trials) - len(pending), desc=study.name,
                  unit="trial", disable=not progress, dynamic_ncols=True) as bar:
            try:
                for params, outcome in finished:
                    store.write(study.name, params, **outcome)
                    if outcome["status"] == "failed":
                        failed += 1
                        bar.set_postfix(failed=failed, refresh=False)
                    bar.update()
            finally:
                finished.close()
        return store.load(study.name, trials=study.trials)


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


def _execute(fn, params: dict) -> dict:
    """Run one trial (in a worker); its outcome as keyword arguments of :meth:`Store.write`."""
    started, t0 = now(), time.perf_counter()
    try:
        metrics, arrays = split_result(params, fn(**params))
        outcome = {"result": {**metrics, **arrays}, "status": "ok"}
    except Exception as exc:
        outcome = {"status": "failed", "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
    return {**outcome, "wall_time": time.perf_counter() - t0, "started": started, "finished": now()}


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


def _run_local(fn, pending: list[dict], workers: int):
    """Yield (params, outcome) as trials finish on a pool of spawn-started processes.

    At most ``workers`` trials are in flight, so when a worker dies the culprit is among them:
    alone, it is stored as failed; otherwise they all become suspects and rerun one at a time.
    """
    with _thread_budget(max(1, (os.cpu_count() or 1) // workers)):
        yield from _run_pool(fn, pending, workers)


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


def _run_pool(fn, pending: list[dict], workers: int):
    queue, suspects = deque(pending), deque()
    context = multiprocessing.get_context("spawn")  # fork is unsafe with Taichi/CUDA threads
    while queue or suspects:
        pool = ProcessPoolExecutor(workers, mp_context=context, initializer=_worker_init, initargs=(os.getpid(),))
        running = {}
        try:
            broken = False
            while not broken and (queue or suspects or running):
                if suspects:
                    if not running:
                        params = suspects.popleft()
                        running[pool.submit(_execute, fn, params)] = params
                else:
                    while queue and len(running) < workers:
                        params = queue.popleft()
                        running[pool.submit(_execute, fn, params)] = params
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                if any(isinstance(f.exception(), BrokenProcessPool) for f in done):
                    broken, done = True, wait(running).done
                crashed = []
                for future in done:
                    params, exc = running.pop(future), future.exception()
                    if exc is None:
                        yield params, future.result()
                    elif isinstance(exc, BrokenProcessPool):
                        crashed.append(params)
                    else:  # the trial or its outcome could not be pickled, say
                        yield params, _failure(f"{type(exc).__name__}: {exc}")
                if len(crashed) == 1:
                    yield crashed[0], _failure("the worker process died while running this trial "
                                               "(killed by a signal, os._exit, a segfault or out of memory)")
                else:
                    suspects.extend(crashed)
        except BaseException:
            # Python 3.11 has no public way to stop busy workers; terminate them so Ctrl-C is prompt.
            for process in list((pool._processes or {}).values()):
                process.terminate()
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)


def _run_dask(fn, pending: list[dict], scheduler: str):
    """(params, outcome) pairs as trials finish on the Dask cluster at ``scheduler``: a generator,
    but whether distributed is installed is checked now."""
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise ImportError('running a study on a Dask cluster needs distributed: pip install "ocpkit[dask]"') from None
    return _dask_outcomes(Client, as_completed, fn, pending, scheduler)


def _dask_outcomes(Client, as_completed, fn, pending: list[dict], scheduler: str):
    if not pending:
        return
    with Client(scheduler) as client:
        futures = {client.submit(_execute, fn, params, pure=False): params for params in pending}
        for future in as_completed(futures):
            params = futures.pop(future)
            try:
                outcome = future.result()
            except Exception as exc:  # e.g. KilledWorker: the trial took down its workers repeatedly
                outcome = _failure(f"{type(exc).__name__}: {exc}")
            future.release()
            yield params, outcome
