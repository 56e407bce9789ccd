"""Durable study results: one SQLite row per finished trial, keyed by the trial's parameters.

The database (``results.sqlite`` in the results folder) runs in WAL mode and commits every
trial on its own, so killing the writing process (even with SIGKILL) loses no finished trial.
Processes sharing one folder coordinate through **claims**: a trial is leased to one process
in a transaction, the lease is renewed by a heartbeat, and a lease whose owner died (or
stopped renewing it) may be taken by another process. Each run of a study is recorded, so the
compute time summed over runs is known. Every failure of the database itself is a
:class:`StoreError` whose one-line message names the file and what to do.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import socket
import sqlite3
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from ocpkit._checks import choice
from ocpkit.runs.database import ADDED_COLUMNS, create_tables, explain, open_readonly, retry_locked
from ocpkit.runs.rows import RESERVED, canonical_key, now, split_result

FILENAME = "results.sqlite"
STATUSES = ("ok", "failed")


class StoreError(RuntimeError):
    """The results database could not be used; the message is one line naming the file and what to do."""


class Store:
    """The results database of one output folder; a context manager that closes it.

    ``readonly`` (default: when the folder or file cannot be written) opens the database for reading
    only: :meth:`load`, :meth:`arrays` and :meth:`keys` work, writing raises :class:`StoreError`.
    """

    def __init__(self, out_dir, *, readonly: bool | None = None):
        if not isinstance(out_dir, (str, Path)):
            raise TypeError(f"out_dir must be a path, got {out_dir!r}")
        folder = Path(out_dir)
        if folder.exists() and not folder.is_dir():
            raise ValueError(f"out_dir must be a folder, got the file {str(folder)!r}")
        self.path = folder / FILENAME
        if readonly is None:
            readonly = folder.is_dir() and not (
                os.access(folder, os.W_OK) and (not self.path.exists() or os.access(self.path, os.W_OK))
            )
        self.readonly = bool(readonly)
        if self.readonly:
            if not self.path.is_file():
                raise StoreError(
                    f"{self.path}: no results store to read (the folder is read-only or "
                    f"readonly=True was asked); run the study in a writable folder first"
                )
            self._con = self._guard("open", lambda: open_readonly(self.path))
            self._guard("read", lambda: self._con.execute("SELECT count(*) FROM trials").fetchone())
            return
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StoreError(
                f"{folder}: cannot create the results folder ({exc.strerror or exc}); choose another --out"
            ) from None
        self._con = self._guard("open", lambda: sqlite3.connect(self.path, timeout=60))
        self._guard("open", lambda: retry_locked(lambda: create_tables(self._con)))

    def _guard(self, doing: str, action):
        """Run ``action``; turn database and OS errors into one-line StoreErrors naming the file."""
        try:
            return action()
        except StoreError:
            raise
        except sqlite3.DatabaseError as exc:
            raise StoreError(explain(self.path, doing, exc)) from None
        except OSError as exc:
            raise StoreError(explain(self.path, doing, exc)) from None

    def _writable(self) -> None:
        if self.readonly:
            raise StoreError(
                f"{self.path}: opened read-only (the folder or file cannot be written); "
                f"copy the folder somewhere writable to run more trials"
            )

    def close(self) -> None:
        self._con.close()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def checkpoint(self) -> None:
        """Move everything in the ``-wal`` file into ``results.sqlite`` (so a plain copy of it is complete);
        a no-op for a read-only store. Another process reading at the same time may keep part of it back."""
        if not self.readonly:
            self._guard("checkpoint", lambda: self._con.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchall())

    def export(self, path) -> Path:
        """Write a single self-contained copy of the database (no ``-wal``/``-shm`` beside it) to ``path``."""
        path = Path(path)
        if path.is_dir():
            raise ValueError(f"export path must be a file, got the folder {str(path)!r}")
        partial = path.with_name(f".{path.name}.partial")

        def copy():
            with contextlib.suppress(FileNotFoundError):
                partial.unlink()
            target = sqlite3.connect(partial)
            try:
                self._con.backup(target)
                target.execute("PRAGMA journal_mode=DELETE")
            finally:
                target.close()
            os.replace(partial, path)

        try:
            self._guard("export", copy)
        finally:
            with contextlib.suppress(FileNotFoundError):
                partial.unlink()
        return path

    def studies(self) -> list[str]:
        """Names of the studies with stored trials."""
        return [r[0] for r in self._con.execute("SELECT DISTINCT study FROM trials ORDER BY study")]

    def keys(self, study: str, *, status: str | None = None) -> set[str]:
        """Canonical keys of the stored trials of ``study`` (only those with ``status`` if given)."""
        if status is None:
            query, args = "SELECT key FROM trials WHERE study = ?", (study,)
        else:
            _check_status(status)
            query, args = "SELECT key FROM trials WHERE study = ? AND status = ?", (study, status)
        return {r[0] for r in self._guard("read", lambda: self._con.execute(query, args).fetchall())}

    def provenance(self, study: str) -> dict[str, tuple]:
        """{key: (status, finished, ocpkit_version, code_hash)} of the stored trials of ``study``."""
        rows = self._guard(
            "read",
            lambda: self._con.execute(
                "SELECT key, status, finished, ocpkit_version, code_hash FROM trials WHERE study = ?", (study,)
            ).fetchall(),
        )
        return {r[0]: tuple(r[1:]) for r in rows}

    def record_code(self, manifests: Mapping[str, Mapping]) -> None:
        """Keep the manifest of each code hash ({hash: manifest}), so a later run can say what changed."""
        self._writable()
        rows = [(h, json.dumps(m, sort_keys=True)) for h, m in manifests.items()]

        def insert():
            with self._con:
                self._con.executemany("INSERT OR IGNORE INTO code VALUES (?, ?)", rows)

        self._guard("write", insert)

    def code(self, hashes) -> dict[str, dict]:
        """{hash: manifest} of those of ``hashes`` whose manifest was recorded."""
        hashes = [h for h in set(hashes) if h]

        def read():
            try:
                return [
                    r
                    for i in range(0, len(hashes), 500)
                    for r in self._con.execute(
                        f"SELECT hash, manifest FROM code WHERE hash IN ({', '.join('?' * len(hashes[i : i + 500]))})",
                        hashes[i : i + 500],
                    )
                ]
            except sqlite3.OperationalError as exc:
                if "no such table" in str(exc):  # a read-only store from before manifests were recorded
                    return []
                raise

        return {h: json.loads(m) for h, m in self._guard("read", read)}

    def write(
        self,
        study: str,
        params: Mapping,
        result: Mapping | None = None,
        *,
        status: str = "ok",
        error: str | None = None,
        traceback: str | None = None,
        wall_time: float | None = None,
        started: str | None = None,
        finished: str | None = None,
        version: str | None = None,
        code: str | None = None,
        owner: str | None = None,
    ) -> None:
        """Store one finished trial (replacing an earlier one with the same parameters) and commit.

        ``version`` and ``code`` record the package version and the study code's hash that computed it;
        ``owner`` releases that owner's claim on the trial in the same transaction."""
        self._writable()
        if not isinstance(study, str) or not study:
            raise TypeError(f"study must be a non-empty string, got {study!r}")
        key = canonical_key(params)
        _check_status(status)
        metrics, arrays = split_result(params, {} if result is None else result)
        blob = None
        if arrays:
            buffer = io.BytesIO()
            np.savez_compressed(buffer, **arrays)
            blob = buffer.getvalue()
        stamp = now()

        def insert():
            with self._con:
                self._con.execute(
                    "INSERT OR REPLACE INTO trials (study, key, status, metrics, arrays, error, traceback, wall_time, "
                    "started, finished, ocpkit_version, code_hash) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (
                        study,
                        key,
                        status,
                        json.dumps(metrics),
                        blob,
                        error,
                        traceback,
                        None if wall_time is None else float(wall_time),
                        started or stamp,
                        finished or stamp,
                        version,
                        code,
                    ),
                )
                if owner is not None:
                    self._con.execute(
                        "DELETE FROM claims WHERE study = ? AND key = ? AND owner = ?", (study, key, owner)
                    )

        self._guard("write", insert)

    # Claims: which process runs which trial.

    def claim(self, study: str, candidates, owner: str, lease: float, *, done) -> tuple[str | None, int]:
        """Lease the first of ``candidates`` (canonical keys, in order) that is neither ``done(key, row)`` nor
        leased to another live process; returns (its key or None, how many candidates other processes hold).

        ``row`` is the stored (status, finished, ocpkit_version, code_hash) or None. Taken in one write
        transaction, so two processes never lease the same trial. A lease is live while unexpired and, when
        its owner runs on this host, while that process exists."""
        self._writable()

        def take():
            with self._con:
                self._con.execute("BEGIN IMMEDIATE")
                stored = {
                    r[0]: tuple(r[1:])
                    for r in self._con.execute(
                        "SELECT key, status, finished, ocpkit_version, code_hash FROM trials WHERE study = ?", (study,)
                    )
                }
                clock = time.time()
                held = {
                    r[0]
                    for r in self._con.execute(
                        "SELECT key, owner, expires FROM claims WHERE study = ? AND owner != ?", (study, owner)
                    )
                    if r[2] > clock and _alive(r[1])
                }
                others = 0
                for key in candidates:
                    if done(key, stored.get(key)):
                        continue
                    if key in held:
                        others += 1
                        continue
                    self._con.execute(
                        "INSERT OR REPLACE INTO claims VALUES (?, ?, ?, ?)", (study, key, owner, clock + lease)
                    )
                    return key, others
                return None, others

        return self._guard("claim trials in", take)

    def renew(self, owner: str, lease: float) -> None:
        """Push every claim of ``owner`` ``lease`` seconds into the future (the heartbeat)."""

        def update():
            with self._con:
                self._con.execute("UPDATE claims SET expires = ? WHERE owner = ?", (time.time() + lease, owner))

        self._guard("renew claims in", update)

    def release(self, owner: str, study: str | None = None) -> None:
        """Drop every claim of ``owner`` (of ``study`` if given)."""
        if self.readonly:
            return
        query, args = "DELETE FROM claims WHERE owner = ?", (owner,)
        if study is not None:
            query, args = query + " AND study = ?", (owner, study)

        def drop():
            with self._con:
                self._con.execute(query, args)

        self._guard("release claims in", drop)

    def claims(self, study: str | None = None) -> pd.DataFrame:
        """The current claims: study, key, owner, expires (Unix time)."""
        query, args = "SELECT study, key, owner, expires FROM claims", ()
        if study is not None:
            query, args = query + " WHERE study = ?", (study,)
        rows = self._guard("read", lambda: self._con.execute(query, args).fetchall())
        return pd.DataFrame(rows, columns=["study", "key", "owner", "expires"])

    def record_run(self, study: str, owner: str, started: str, wall: float, trials: int) -> None:
        """Record one run of ``study`` (its wall time and how many trials it ran)."""
        self._writable()

        def insert():
            with self._con:
                self._con.execute(
                    "INSERT INTO runs VALUES (?, ?, ?, ?, ?, ?)",
                    (study, owner, started, now(), float(wall), int(trials)),
                )

        self._guard("write", insert)

    def runs(self, study: str | None = None) -> pd.DataFrame:
        """Every recorded run: study, owner, started, finished, wall (s), trials; oldest first."""
        query, args = "SELECT study, owner, started, finished, wall, trials FROM runs", ()
        if study is not None:
            query, args = query + " WHERE study = ?", (study,)

        def read():
            try:
                return self._con.execute(query + " ORDER BY rowid", args).fetchall()
            except sqlite3.OperationalError as exc:
                if "no such table" in str(exc):  # a read-only store from before runs were recorded
                    return []
                raise

        return pd.DataFrame(
            self._guard("read", read), columns=["study", "owner", "started", "finished", "wall", "trials"]
        )

    def arrays(self, study: str, params: Mapping) -> dict[str, np.ndarray]:
        """The arrays a stored trial returned ({} if none); KeyError if the trial is not stored."""
        row = self._guard(
            "read",
            lambda: self._con.execute(
                "SELECT arrays FROM trials WHERE study = ? AND key = ?", (study, canonical_key(params))
            ).fetchone(),
        )
        if row is None:
            raise KeyError(f"no stored trial of study {study!r} with params {canonical_key(params)}")
        if row[0] is None:
            return {}
        with np.load(io.BytesIO(row[0]), allow_pickle=False) as npz:
            return {name: npz[name] for name in npz.files}

    def load(self, study: str | None = None, *, trials=None) -> pd.DataFrame:
        """Stored trials as a table: study, one column per parameter, one per scalar metric, then
        status, error, traceback, wall_time, started, finished.

        ``study`` selects one study (all when None). ``trials`` (a list of parameter dicts) keeps
        only those trials, in that order; otherwise rows are in the order they finished.
        ``df.attrs["params"]`` and ``df.attrs["metrics"]`` name the parameter and metric columns.
        """
        query = "SELECT study, key, status, metrics, error, traceback, wall_time, started, finished, {} FROM trials"
        args = ()
        if study is not None:
            query, args = query + " WHERE study = ?", (study,)

        def read():
            have = {r[1] for r in self._con.execute("PRAGMA table_info(trials)")}
            added = ", ".join(name if name in have else "NULL" for name in ADDED_COLUMNS)
            return self._con.execute(query.format(added) + " ORDER BY finished, rowid", args).fetchall()

        rows = self._guard("read", read)
        if trials is not None:
            by_key = {(r[0], r[1]): r for r in rows}
            wanted = [canonical_key(p) for p in trials]
            names = [study] if study is not None else sorted({r[0] for r in rows})
            rows = [by_key[(s, k)] for s in names for k in wanted if (s, k) in by_key]
        params, metrics, records = {}, {}, []
        for name, key, status, metrics_json, error, tb, wall, started, finished, version, code in rows:
            p, m = json.loads(key), json.loads(metrics_json)
            params.update(dict.fromkeys(p))
            metrics.update(dict.fromkeys(m))
            records.append(
                {
                    "study": name,
                    **p,
                    **m,
                    "status": status,
                    "error": error,
                    "traceback": tb,
                    "wall_time": wall,
                    "started": started,
                    "finished": finished,
                    "ocpkit_version": version,
                    "code_hash": code,
                }
            )
        columns = ["study", *params, *metrics, *RESERVED[1:]]
        df = pd.DataFrame.from_records(records, columns=columns)
        for column in ("started", "finished"):
            df[column] = pd.to_datetime(df[column], utc=True, format="ISO8601")
        df.attrs["params"], df.attrs["metrics"] = list(params), list(metrics)
        return df

    def to_csv(self, path, study: str | None = None) -> Path:
        """Write :meth:`load`'s table as CSV; returns the path."""
        path = Path(path)
        self.load(study).to_csv(path, index=False)
        return path

    def to_parquet(self, path, study: str | None = None) -> Path:
        """Write :meth:`load`'s table as Parquet (needs pyarrow); returns the path."""
        try:
            import pyarrow  # noqa: F401
        except ImportError:
            raise ImportError("Parquet export needs pyarrow, which is not installed: pip install pyarrow") from None
        path = Path(path)
        self.load(study).to_parquet(path, index=False)
        return path


def _check_status(status) -> None:
    choice(status, STATUSES, "status")


def owner_id() -> str:
    """A claim owner name for this process: host:pid:random (unique even after the pid is reused)."""
    return f"{socket.gethostname()}:{os.getpid()}:{os.urandom(4).hex()}"


def _alive(owner: str) -> bool:
    """Whether a claim's owner may still run: False only when it ran on this host and its process is gone."""
    host, _, rest = owner.partition(":")
    pid = rest.partition(":")[0]
    if host != socket.gethostname() or not pid.isdigit():
        return True
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:  # a zombie (killed, not yet reaped by its parent) runs nothing
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True
