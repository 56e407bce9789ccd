"""Durable study results: one SQLite row per finished trial, keyed by the trial's parameters.

The database (``results.sqlite`` in the results folder) runs in WAL mode and commits every
trial on its own, so killing the writing process (even with SIGKILL) loses no finished trial.
"""
from __future__ import annotations

import io
import json
import math
import sqlite3
from collections.abc import Mapping
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd

from ._checks import choice

FILENAME = "results.sqlite"
STATUSES = ("ok", "failed")
# Columns of the results table besides the parameters and metrics; neither may use these names.
RESERVED = ("study", "status", "error", "traceback", "wall_time", "started", "finished")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS trials (
    study     TEXT NOT NULL,
    key       TEXT NOT NULL,   -- canonical JSON of the parameters (see canonical_key)
    status    TEXT NOT NULL CHECK (status IN ('ok', 'failed')),
    metrics   TEXT NOT NULL,   -- JSON object of scalars
    arrays    BLOB,            -- .npz archive, NULL when the trial returned no arrays
    error     TEXT,
    traceback TEXT,
    wall_time REAL,            -- seconds
    started   TEXT,            -- ISO 8601, UTC
    finished  TEXT,
    PRIMARY KEY (study, key)
)
"""


def canonical_key(params: Mapping) -> str:
    """The trial's identity: compact JSON with sorted keys and shortest round-trip floats.

    numpy scalars and arrays become plain numbers and lists, tuples become lists and -0.0
    becomes 0.0, so equal parameter sets always give the same key.
    """
    if not isinstance(params, Mapping):
        raise TypeError(f"params must be a mapping of parameter names to values, got {params!r}")
    return json.dumps(_plain(params, "params"), sort_keys=True, separators=(",", ":"), allow_nan=False)


def _plain(value, where: str):
    if isinstance(value, Mapping):
        for k in value:
            if not isinstance(k, str):
                raise TypeError(f"{where} keys must be strings, got {k!r}")
        return {k: _plain(v, f"{where}[{k!r}]") for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"{where} must be finite, got {value!r}")
        return value + 0.0  # turns -0.0 into 0.0
    raise TypeError(f"{where} must be None, a bool, number, string, list or dict, got {type(value).__name__}")


def split_result(params: Mapping, result) -> tuple[dict, dict]:
    """Split a trial's returned dict into JSON scalar metrics and numpy arrays, validating names and types."""
    if not isinstance(result, Mapping):
        raise TypeError(f"a trial must return a dict of metrics, got {type(result).__name__}")
    metrics, arrays = {}, {}
    for name, value in result.items():
        if not isinstance(name, str) or not name:
            raise TypeError(f"metric names must be non-empty strings, got {name!r}")
        if name in RESERVED or name in params:
            raise ValueError(f"metric {name!r} clashes with a {'reserved column' if name in RESERVED else 'parameter'}")
        if isinstance(value, (list, tuple)) or (isinstance(value, np.ndarray) and value.ndim > 0):
            a = np.asarray(value)
            if a.dtype.hasobject:
                raise TypeError(f"array metric {name!r} must hold numbers or strings, got dtype object")
            arrays[name] = a
            continue
        if isinstance(value, (np.generic, np.ndarray)):
            value = value.item()
        if value is not None and not isinstance(value, (bool, int, float, str)):
            raise TypeError(f"metric {name!r} must be a number, bool, string, None or array, "
                            f"got {type(value).__name__}")
        metrics[name] = value
    return metrics, arrays


def now() -> str:
    """The current UTC time as ISO 8601, the store's timestamp format."""
    return datetime.now(timezone.utc).isoformat()


class Store:
    """The results database of one output folder; a context manager that closes it."""

    def __init__(self, out_dir):
        if not isinstance(out_dir, (str, Path)):
            raise TypeError(f"out_dir must be a path, got {out_dir!r}")
        folder = Path(out_dir)
        if folder.exists() and not folder.is_dir():
            raise ValueError(f"out_dir must be a folder, got the file {str(folder)!r}")
        folder.mkdir(parents=True, exist_ok=True)
        self.path = folder / FILENAME
        self._con = sqlite3.connect(self.path, timeout=60)
        self._con.execute("PRAGMA journal_mode=WAL")
        # NORMAL in WAL mode: a commit survives the process being killed (not a power cut) at low cost.
        self._con.execute("PRAGMA synchronous=NORMAL")
        with self._con:
            self._con.execute(_SCHEMA)

    def close(self) -> None:
        self._con.close()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def studies(self) -> list[str]:
        """Names of the studies with stored trials."""
        return [r[0] for r in self._con.execute("SELECT DISTINCT study FROM trials ORDER BY study")]

    def keys(self, study: str, *, status: str | None = None) -> set[str]:
        """Canonical keys of the stored trials of ``study`` (only those with ``status`` if given)."""
        if status is None:
            rows = self._con.execute("SELECT key FROM trials WHERE study = ?", (study,))
        else:
            _check_status(status)
            rows = self._con.execute("SELECT key FROM trials WHERE study = ? AND status = ?", (study, status))
        return {r[0] for r in rows}

    def write(self, study: str, params: Mapping, result: Mapping | None = None, *, status: str = "ok",
              error: str | None = None, traceback: str | None = None, wall_time: float | None = None,
              started: str | None = None, finished: str | None = None) -> None:
        """Store one finished trial (replacing an earlier one with the same parameters) and commit."""
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
        with self._con:
            self._con.execute(
                "INSERT OR REPLACE INTO trials VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (study, key, status, json.dumps(metrics), blob, error, traceback,
                 None if wall_time is None else float(wall_time), started or stamp, finished or stamp))

    def arrays(self, study: str, params: Mapping) -> dict[str, np.ndarray]:
        """The arrays a stored trial returned ({} if none); KeyError if the trial is not stored."""
        row = self._con.execute("SELECT arrays FROM trials WHERE study = ? AND key = ?",
                                (study, canonical_key(params))).fetchone()
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
        query = "SELECT study, key, status, metrics, error, traceback, wall_time, started, finished FROM trials"
        args = ()
        if study is not None:
            query, args = query + " WHERE study = ?", (study,)
        rows = self._con.execute(query + " ORDER BY finished, rowid", args).fetchall()
        if trials is not None:
            by_key = {(r[0], r[1]): r for r in rows}
            wanted = [canonical_key(p) for p in trials]
            names = [study] if study is not None else sorted({r[0] for r in rows})
            rows = [by_key[(s, k)] for s in names for k in wanted if (s, k) in by_key]
        params, metrics, records = {}, {}, []
        for name, key, status, metrics_json, error, tb, wall, started, finished in rows:
            p, m = json.loads(key), json.loads(metrics_json)
            params.update(dict.fromkeys(p))
            metrics.update(dict.fromkeys(m))
            records.append({"study": name, **p, **m, "status": status, "error": error, "traceback": tb,
                            "wall_time": wall, "started": started, "finished": finished})
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
