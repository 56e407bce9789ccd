"""One study trial run with a time limit, as a worker runs it (a local process or a Dask worker thread): its outcome
as the store records it, and :class:`TrialTimeout` raised inside it when it runs too long."""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
import traceback

from ocpkit.runs.rows import now, split_result

TIMEOUT_EXIT = 124  # exit status of a worker whose trial ignored its timeout


class TrialTimeout(Exception):
    """Raised inside a trial that ran longer than its timeout."""


def execute(fn, params: dict, timeout: float | None = None) -> dict:
    """Run one trial (in a worker); its outcome as keyword arguments of :meth:`Store.write`.

    With a ``timeout``, :class:`TrialTimeout` is raised inside the trial when it expires (see :func:`deadline`)."""
    started, t0 = now(), time.perf_counter()
    try:
        with deadline(timeout):
            metrics, arrays = split_result(params, fn(**params))
        outcome = {"result": {**metrics, **arrays}, "status": "ok"}
    except TrialTimeout:  # raised without its message on a worker thread (an asynchronous exception)
        outcome = {"status": "failed", "error": timeout_message(timeout), "traceback": traceback.format_exc()}
    except Exception as exc:
        outcome = {"status": "failed", "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
    return {**outcome, "wall_time": time.perf_counter() - t0, "started": started, "finished": now()}


def timeout_message(timeout: float) -> str:
    return f"TrialTimeout: the trial ran longer than the trial timeout of {timeout:g} s and was stopped"


@contextlib.contextmanager
def deadline(timeout: float | None):
    """Raise :class:`TrialTimeout` in the trial after ``timeout`` seconds: by SIGALRM on a worker process's main
    thread, where a trial stuck in C code also takes its worker down shortly after (the pool reports it as dead);
    on another thread (a Dask worker's) as an asynchronous exception, which Python raises between two bytecodes,
    so a trial stuck in C code runs on and the client abandons it (:mod:`ocpkit.runs.cluster`)."""
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
        raise TrialTimeout(timeout_message(timeout).partition(": ")[2])

    previous = signal.signal(signal.SIGALRM, expire)
    killer = threading.Timer(timeout + grace(timeout), os._exit, args=(TIMEOUT_EXIT,))
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


def grace(timeout: float) -> float:
    """How long past its timeout a trial that does not return to Python is waited for."""
    return max(2.0, 0.5 * timeout)


def failure(message: str) -> dict:
    """The outcome of a trial that ended outside the trial function (its worker died, say)."""
    return {"status": "failed", "error": message, "started": now(), "finished": now()}
