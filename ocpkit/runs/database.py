"""The results store's SQLite file (:mod:`ocpkit.runs.store`): its tables, opening it for writing (WAL, the tables
created or brought up to date) or for reading only, and its failures in one line naming the file and what to do."""

from __future__ import annotations

import sqlite3
import time
from pathlib import Path

TRIALS = """
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
# Columns added after the first release: older stores gain them (NULL for their trials) when opened for writing.
ADDED_COLUMNS = {
    "ocpkit_version": "TEXT",  # the package version that computed the trial
    "code_hash": "TEXT",  # hash of the code the trial ran (ocpkit.runs.provenance; see code)
}
CLAIMS = """
CREATE TABLE IF NOT EXISTS claims (
    study   TEXT NOT NULL,
    key     TEXT NOT NULL,
    owner   TEXT NOT NULL,     -- host:pid:token of the claiming process
    expires REAL NOT NULL,     -- Unix time; the heartbeat pushes it forward
    PRIMARY KEY (study, key)
)
"""
CODE = """
CREATE TABLE IF NOT EXISTS code (
    hash     TEXT PRIMARY KEY, -- a trials.code_hash
    manifest TEXT NOT NULL     -- JSON: the files and dependency versions it hashes (see ocpkit.runs.provenance)
)
"""
RUNS = """
CREATE TABLE IF NOT EXISTS runs (
    study    TEXT NOT NULL,
    owner    TEXT NOT NULL,
    started  TEXT NOT NULL,
    finished TEXT NOT NULL,
    wall     REAL NOT NULL,    -- seconds this run took
    trials   INTEGER NOT NULL  -- trials it ran
)
"""


def create_tables(con: sqlite3.Connection) -> None:
    """Switch ``con``'s database to WAL and create its tables, or add the columns an older store lacks."""
    con.execute("PRAGMA journal_mode=WAL")
    # NORMAL in WAL mode: a commit survives the process being killed (not a power cut) at low cost.
    con.execute("PRAGMA synchronous=NORMAL")
    # One write transaction for the schema: DDL autocommits statement by statement otherwise, and two
    # processes opening a new store both saw a column missing and both added it.
    con.execute("BEGIN IMMEDIATE")
    try:
        con.execute(TRIALS)
        con.execute(CLAIMS)
        con.execute(RUNS)
        con.execute(CODE)
        have = {r[1] for r in con.execute("PRAGMA table_info(trials)")}
        for name, kind in ADDED_COLUMNS.items():
            if name not in have:
                con.execute(f"ALTER TABLE trials ADD COLUMN {name} {kind}")
        con.execute("COMMIT")
    except BaseException:
        con.execute("ROLLBACK")
        raise


def retry_locked(action, seconds: float = 60.0):
    """``action()``, retried while SQLite answers "database is locked" (up to ``seconds``). Switching a new
    database to WAL takes a lock for which SQLite does not wait on its busy timeout: two processes opening one
    new store at once saw the second fail at once (a study pair sharing a folder)."""
    deadline = time.monotonic() + seconds
    while True:
        try:
            return action()
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) or time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def open_readonly(path: Path) -> sqlite3.Connection:
    """The database at ``path``, for reading only."""
    con = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True, timeout=60)
    try:
        con.execute("SELECT count(*) FROM sqlite_master").fetchone()
    except sqlite3.OperationalError:
        # WAL with a -wal file but no way to create the -shm beside it: read the main file as it is.
        con.close()
        con = sqlite3.connect(f"{path.resolve().as_uri()}?immutable=1", uri=True)
    return con


def explain(path: Path, doing: str, exc: BaseException) -> str:
    """One line: the file, what went wrong, what to do."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    lower = text.lower()
    if isinstance(exc, OSError) and exc.strerror:
        text = exc.strerror
        lower = text.lower()
    if "not a database" in lower or "malformed" in lower or "corrupt" in lower:
        advice = (
            "the file is damaged: move it (and any -wal/-shm beside it) aside and rerun to recompute, "
            "or restore it from a copy"
        )
    elif "disk is full" in lower or "no space" in lower or "quota" in lower:
        advice = "the disk is full: free space and rerun (finished trials are kept)"
    elif "readonly" in lower or "read-only" in lower or "permission" in lower or "unable to open" in lower:
        advice = "the file or its folder cannot be written: fix its permissions or choose another --out"
    elif "locked" in lower or "busy" in lower:
        advice = "another process holds the database locked: wait for it or stop it, then rerun"
    else:
        advice = "check the file, or move it aside and rerun"
    return f"results store {path}: could not {doing} it ({text}); {advice}"
