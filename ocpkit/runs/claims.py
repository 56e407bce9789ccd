"""A study's trials as this process claims them from the store (a lease per trial, renewed by a heartbeat), and what
this process computes them with: shared by the local runner (:mod:`ocpkit.runs.study`) and the Dask one
(:mod:`ocpkit.runs.cluster`)."""

from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import dataclass

from ocpkit.runs.store import Store


@dataclass(frozen=True)
class OwnProvenance:
    """What this process computes trials with: its ocpkit version, each trial's code hash (by canonical key) and
    each code hash's manifest."""

    version: str
    codes: dict
    manifests: dict


class Claims:
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


class Heartbeat:
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
