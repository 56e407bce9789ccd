"""The results store under what users do to it: copies, damage, full disks, read-only folders, old stores."""

import os
import shutil
import sqlite3

import pytest

from ocpkit.runs.store import FILENAME, Store, StoreError
from ocpkit.runs.study import Study, grid, run


def trial(x):
    return {"y": x * x}


def finished_study(folder, n=20):
    return run(Study("q", trial, grid(x=range(n))), folder, workers=1, progress=False)


def one_line(exc) -> str:
    text = str(exc)
    assert "\n" not in text
    return text


def test_a_copy_of_results_sqlite_alone_holds_every_trial_after_a_run(tmp_path):
    finished_study(tmp_path / "a")
    wal = tmp_path / "a" / (FILENAME + "-wal")
    assert not wal.exists() or wal.stat().st_size == 0  # checkpointed at the end of the run
    (tmp_path / "copy").mkdir()
    shutil.copy(tmp_path / "a" / FILENAME, tmp_path / "copy" / FILENAME)
    with Store(tmp_path / "copy") as store:
        assert len(store.load("q")) == 20


def test_export_writes_one_self_contained_file(tmp_path):
    with Store(tmp_path / "a") as store:
        for x in range(5):
            store.write("q", {"x": x}, {"y": x})  # uncheckpointed: these sit in the -wal file
        path = store.export(tmp_path / "exported.sqlite")
        with pytest.raises(ValueError, match="must be a file"):
            store.export(tmp_path)
    assert sorted(os.listdir(tmp_path)) == ["a", "exported.sqlite"]
    with sqlite3.connect(path) as con:
        assert con.execute("SELECT count(*) FROM trials").fetchone() == (5,)
        assert con.execute("PRAGMA journal_mode").fetchone() == ("delete",)


@pytest.mark.parametrize("damage", ["garbage", "truncated"])
def test_a_damaged_store_is_one_line_naming_the_file(tmp_path, damage):
    path = tmp_path / FILENAME
    if damage == "garbage":
        path.write_bytes(b"this is not a database" * 100)
    else:
        finished_study(tmp_path, n=200)
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 3])
    with pytest.raises(StoreError) as info:
        with Store(tmp_path) as store:
            store.load("q")
            run(Study("q", trial, grid(x=range(200))), tmp_path, workers=1, progress=False)
    message = one_line(info.value)
    assert str(path) in message and "damaged" in message and "move it" in message


def test_a_full_disk_is_one_line_and_keeps_what_was_written(tmp_path):
    with Store(tmp_path) as store:
        store.write("q", {"x": 0}, {"y": 0})
        pages = store._con.execute("PRAGMA page_count").fetchone()[0]
        store._con.execute(f"PRAGMA max_page_count = {pages}")  # as if the disk had no room left
        with pytest.raises(StoreError) as info:
            for x in range(1, 200):
                store.write("q", {"x": x}, {"y": x, "pad": "x" * 5000})
        message = one_line(info.value)
        assert str(store.path) in message and "disk is full" in message
    with Store(tmp_path) as store:
        assert 0 in store.load("q").x.tolist()


def test_a_finished_study_in_a_read_only_folder_reads_back(tmp_path, monkeypatch):
    expected = finished_study(tmp_path)
    real_access = os.access
    # Tests may run as root, whom file modes do not stop: make the folder read-only as the store sees it.
    monkeypatch.setattr(os, "access", lambda path, mode, **kw: False if mode & os.W_OK else real_access(path, mode))
    with Store(tmp_path) as store:
        assert store.readonly
        assert sorted(store.load("q").y) == sorted(expected.y)
        with pytest.raises(StoreError, match="read-only"):
            store.write("q", {"x": 99}, {"y": 1})
    df = run(Study("q", trial, grid(x=range(20))), tmp_path, workers=1, progress=False)  # nothing to run
    assert df.y.tolist() == expected.y.tolist()
    with pytest.raises(StoreError, match=r"read-only.*copy the folder"):
        run(Study("q", trial, grid(x=range(21))), tmp_path, workers=1, progress=False)
    (tmp_path / "empty").mkdir()
    with pytest.raises(StoreError, match="no results store"):
        Store(tmp_path / "empty")


def test_a_store_from_before_provenance_gains_its_columns(tmp_path):
    with sqlite3.connect(tmp_path / FILENAME) as con:  # the schema of the first release, one trial in it
        con.execute(
            "CREATE TABLE trials (study TEXT NOT NULL, key TEXT NOT NULL, status TEXT NOT NULL, "
            "metrics TEXT NOT NULL, arrays BLOB, error TEXT, traceback TEXT, wall_time REAL, started TEXT, "
            "finished TEXT, PRIMARY KEY (study, key))"
        )
        con.execute(
            "INSERT INTO trials VALUES ('q', '{\"x\":0}', 'ok', '{\"y\":0}', NULL, NULL, NULL, 1.0, "
            "'2024-01-01T00:00:00+00:00', '2024-01-01T00:00:00+00:00')"
        )
    with Store(tmp_path) as store:
        df = store.load("q")
    assert df.ocpkit_version.isna().all() and df.code_hash.isna().all()
    with pytest.raises(ValueError, match="1 of the 1 stored trials.*other code"):  # unknown code is stale
        run(Study("q", trial, grid(x=range(2))), tmp_path, workers=1, progress=False)
    df = run(Study("q", trial, grid(x=range(2))), tmp_path, workers=1, progress=False, stale="reuse")
    assert df.y.tolist() == [0, 1]


def test_several_connections_opening_one_new_store_at_once(tmp_path):
    """Switching a new store to WAL does not wait on SQLite's busy timeout; opening must retry, not fail."""
    import threading

    errors = []
    for round_ in range(20):
        folder = tmp_path / f"r{round_}"
        gate = threading.Barrier(4)

        def open_store():
            gate.wait()
            try:
                with Store(folder):
                    pass
            except Exception as exc:  # collected: an assertion in a thread would be lost
                errors.append(exc)

        threads = [threading.Thread(target=open_store) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert not errors, errors[:3]
