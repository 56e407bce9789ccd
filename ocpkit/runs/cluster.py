"""Studies on a Dask cluster: trials submitted to the scheduler at ``--scheduler``, each worker and the scheduler
checked for this process's ocpkit version and code before they compute one, the outcomes written by the submitting
process as they return, a lost scheduler reported in one line (the finished trials kept)."""

from __future__ import annotations

import contextlib
import threading
import time
from collections import Counter
from concurrent.futures import CancelledError

import numpy as np

from ocpkit.runs import provenance
from ocpkit.runs.claims import Claims, OwnProvenance
from ocpkit.runs.provenance import package_version
from ocpkit.runs.rows import canonical_key
from ocpkit.runs.trial import execute, failure, grace, timeout_message


class ClusterMismatchError(ValueError):
    """A Dask scheduler or worker cannot import ocpkit or the trial, or runs another ocpkit version, other study code
    or other numerical libraries than the process running the study."""


class SchedulerLostError(ConnectionError):
    """The connection to the Dask scheduler was lost while a study ran on it."""


def run_dask(fn, source: Claims, scheduler: str, timeout: float | None, mine: OwnProvenance, placement: Counter):
    """(params, outcome) pairs as trials finish on the Dask cluster at ``scheduler``, counting in ``placement``
    the trials each worker ran: a generator (the caller checks the scheduler first: :func:`check_scheduler`)."""
    from distributed import Client

    return _dask_outcomes(Client, fn, source, scheduler, timeout, mine, placement)


HANDSHAKE_S = 10.0  # seconds a server has to answer Dask's handshake as a scheduler


def check_scheduler(scheduler: str, timeout: float = 5.0) -> None:
    """Raise ConnectionError (one line) unless a TCP connection to ``scheduler`` opens within ``timeout`` s and the
    server there answers Dask's handshake as a Dask scheduler within :data:`HANDSHAKE_S` s; ImportError without
    distributed. A web server or a listener that never answers would keep distributed's Client waiting forever,
    whatever its timeout."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        raise ImportError('running a study on a Dask cluster needs distributed: pip install "ocpkit[dask]"') from None
    _connect(scheduler, timeout)
    _handshake(scheduler, HANDSHAKE_S)


def _connect(scheduler: str, timeout: float) -> None:
    """Raise ConnectionError (one line) unless a TCP connection to ``scheduler`` opens within ``timeout`` s."""
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
        raise ConnectionError(
            f"cannot reach the Dask scheduler at {scheduler} ({reason}); start one "
            f"(`dask scheduler`) or check the address"
        ) from None


def _handshake(scheduler: str, timeout: float) -> None:
    """Raise ConnectionError (one line) unless the server at ``scheduler`` answers Dask's comm handshake and an
    identity request as a scheduler within ``timeout`` s. Run on a thread with its own event loop (the caller may
    be running one: a notebook), bounded by asyncio.wait_for: distributed's own connect timeout does not cover the
    handshake."""
    import asyncio
    from concurrent.futures import ThreadPoolExecutor

    from distributed.comm import connect
    from distributed.security import Security

    address = scheduler if "://" in scheduler else f"tcp://{scheduler}"

    async def identity():
        comm = await connect(address, timeout=timeout, **Security().get_connection_args("client"))
        try:
            await comm.write({"op": "identity"})
            return await comm.read()
        finally:
            comm.abort()

    async def bounded():
        return await asyncio.wait_for(identity(), timeout)

    with ThreadPoolExecutor(1, thread_name_prefix="ocpkit-handshake") as pool:
        try:
            reply = pool.submit(asyncio.run, bounded()).result()
        except asyncio.TimeoutError:
            reason = f"no answer to the Dask handshake within {timeout:g} s"
        except Exception as exc:
            reason = f"the Dask handshake failed: {type(exc).__name__} {(str(exc).splitlines() or [''])[0]}".strip()
        else:
            kind = reply.get("type") if isinstance(reply, dict) else None
            if kind == "Scheduler":
                return
            reason = f"it answers as a Dask {kind}" if isinstance(kind, str) else "an unknown answer to its identity"
    raise ConnectionError(
        f"the server at {scheduler} is not a Dask scheduler ({reason}): start one "
        f"(`dask scheduler`) or check the address"
    )


def _dask_outcomes(
    Client, fn, source: Claims, scheduler: str, timeout: float | None, mine: OwnProvenance, placement: Counter
):
    """The generator behind :func:`run_dask`. The scheduler, then each worker as it joins, is refused unless it
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
                    variables = mine.manifests[code].get("environment", {})
                    running[
                        client.submit(_execute_remote, fn, params, timeout, mine.version, code, variables, pure=False)
                    ] = (params, time.monotonic())
                if not running:
                    if not source.others:
                        return
                    source.pause()
                    continue
                wait_s = 1.0
                if timeout is not None:
                    first = min(t for _, t in running.values()) + timeout + grace(timeout)
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
                    for future in [f for f, (_, t) in running.items() if clock - t >= timeout + grace(timeout)]:
                        params, _ = running.pop(future)
                        future.cancel()
                        yield params, failure(timeout_message(timeout) + " (abandoned on the Dask cluster)")
        except (CancelledError, OSError) as exc:
            if "scheduler-connection-lost" not in str(exc) and not _scheduler_gone(client, scheduler):
                raise
            lost.set()
            raise SchedulerLostError(
                f"lost the connection to the Dask scheduler at {scheduler} mid-study ({len(running)} running trials "
                f"not stored; the {sum(placement.values())} finished in this run are): start a scheduler and rerun "
                "the same command to resume"
            ) from None


def _received(future, params: dict, scheduler: str, mine: OwnProvenance) -> tuple[str | None, dict]:
    """A finished Dask future's (worker address, outcome), releasing it; raises :class:`ClusterMismatchError` when
    the scheduler or the worker could not load the trial or the worker runs other code, CancelledError when the
    future was cancelled (the scheduler went away)."""
    try:
        address, outcome = future.result()
    except ImportError as exc:  # unpickling the trial failed on the worker (the trial's import errors are outcomes)
        raise ClusterMismatchError(
            f"a Dask worker cannot load the trial ({type(exc).__name__}: {exc}); {_SAME}"
        ) from None
    except CancelledError:
        raise
    except Exception as exc:  # e.g. KilledWorker: the trial took down its workers repeatedly
        if "deserialization of the task graph" in str(exc):  # Dask's words for it failing on the scheduler
            raise ClusterMismatchError(
                f"the Dask scheduler at {scheduler} cannot load the trial ({str(exc).splitlines()[0]}): {_SAME}"
            ) from None
        if _scheduler_gone(future.client, scheduler):  # not the trial's failure: it is rerun on a resume
            raise CancelledError(f"{type(exc).__name__}: {exc}") from None
        return None, failure(f"{type(exc).__name__}: {exc}")
    finally:
        future.release()
    if "mismatch" in outcome:
        theirs, manifest = outcome["mismatch"]
        raise ClusterMismatchError(
            _mismatch_message(
                f"worker {address}", theirs, mine.version, manifest, mine.manifests[mine.codes[canonical_key(params)]]
            )
        )
    return address, outcome


def _scheduler_gone(client, scheduler: str) -> bool:
    """Whether the client has lost its scheduler: its status says so, or the scheduler's port no longer answers (the
    status may still read "running" for a moment after the scheduler died)."""
    if client.status != "running":
        return True
    try:
        _connect(scheduler, timeout=2.0)
    except ConnectionError:
        return True
    return False


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
        found.update(
            (f"worker {address}", theirs)
            for address, theirs in client.run(package_version, workers=workers, on_error="return").items()
        )
    for where, theirs in found.items():
        if isinstance(theirs, BaseException):
            raise ClusterMismatchError(
                f"the Dask {where} cannot import ocpkit ({theirs}), this process runs ocpkit {version}: {_SAME}"
            )
        if theirs != version:
            raise ClusterMismatchError(_mismatch_message(where, theirs, version))


_VERIFIED: set = set()  # (version, code hash) pairs a Dask worker process found its own code to match


def _execute_remote(fn, params: dict, timeout: float | None, version: str, code: str, variables: dict):
    """:func:`execute` on a Dask worker: (the worker's address, the outcome). A worker first checks, once per code
    hash, that it runs the client's ocpkit version and code: if not, the outcome is ``{"mismatch": (its version,
    its manifest)}`` and the trial is not run. Its manifest takes the client's environment ``variables``: a worker's
    own are its cluster's (Dask's nanny sets the BLAS threads to 1), see :mod:`ocpkit.runs.provenance`."""
    from distributed import get_worker

    address = get_worker().address
    if (version, code) not in _VERIFIED:
        theirs = provenance.manifest(fn, params, variables)
        if package_version() != version or provenance.manifest_hash(theirs) != code:
            return address, {"mismatch": (package_version(), theirs)}
        _VERIFIED.add((version, code))
    return address, execute(fn, params, timeout)


_SAME = (
    "install the same ocpkit, study code and numerical libraries on the scheduler and every worker (or stop "
    "that worker) and rerun"
)


def _mismatch_message(where: str, their_version, version: str, their_manifest=None, manifest=None) -> str:
    """Why the Dask ``where`` ("worker tcp://…") is refused: its ocpkit version, or what differs between the
    manifest of the trial's code there and here (:mod:`ocpkit.runs.provenance`)."""
    if their_version != version:
        return f"the Dask {where} runs ocpkit {their_version}, this process ocpkit {version}: {_SAME}"
    differences = provenance.changes(manifest, their_manifest)
    text = "; ".join(differences[:6]) + (f"; and {len(differences) - 6} more" if len(differences) > 6 else "")
    return f"the Dask {where} runs other code than this process (here → there: {text or 'unknown'}): {_SAME}"


@contextlib.contextmanager
def _quiet_once_lost():
    """An Event to set when the study has lost its scheduler: from then on, the Dask client's own log records (its
    failed reconnection, the traceback of the attempt cancelled as it closes) stay off the terminal, since the study
    reports the loss itself in one line (:class:`SchedulerLostError`). Distributed's informational records (a closed
    connection's traceback among them) stay off it throughout: the study says what happened."""
    import logging

    lost = threading.Event()

    def keep(record) -> bool:
        return not lost.is_set()

    client, root = logging.getLogger("distributed.client"), logging.getLogger("distributed")
    level = root.level
    client.addFilter(keep)
    root.setLevel(max(logging.WARNING, level))
    try:
        yield lost
    finally:
        client.removeFilter(keep)
        root.setLevel(level)


def _dask_wait_or_none(futures, timeout: float):
    from distributed import wait

    try:
        return wait(futures, timeout=timeout, return_when="FIRST_COMPLETED").done
    except TimeoutError:
        return set()
