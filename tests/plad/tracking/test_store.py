"""plad.tracking.store: opening a store. A new SQLite store is created once, under the lock beside it, as
one rename of a complete database; a store that cannot be opened is a one-line StoreError naming its URI
and what to do, raised before anything is written (and within seconds, not MLflow's minutes of retries).

Six processes racing on a new store, and a read-only folder: test_store_concurrency.py (integration).
"""
from __future__ import annotations

import shutil
import sqlite3
import threading
import time
from pathlib import Path

import pytest

from plad.errors import RunFailure
from plad.fsutil import file_lock
from plad.tracking import StageRun, StoreError, open_store
from tests.procs import free_port

ADVICE = "or set MLFLOW_TRACKING_URI to another store (sqlite:////absolute/path/mlflow.db, or a tracking server " \
         "http://host:port)"


@pytest.fixture(scope="module")
def made_store(tmp_path_factory) -> Path:
    """A store created by open_store (the database file), to copy."""
    db = tmp_path_factory.mktemp("made") / "mlflow.db"
    open_store(f"sqlite:///{db}")
    return db


def refused(uri: str, run_dir: Path, monkeypatch) -> str:
    """The message of the StoreError a StageRun on ``uri`` raises (one line, naming the store); no run file."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    with pytest.raises(StoreError) as err:
        with StageRun("pretrain", "csg2d", {"a": 1}, run_dir):
            pytest.fail("the run started")
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"MLflow store {uri}: ") and message.endswith(ADVICE)
    assert isinstance(err.value, RunFailure) and err.value.exit_code == 1
    assert not run_dir.exists()
    return message


def test_a_file_that_is_not_a_database_is_refused_and_kept(tmp_path, monkeypatch):
    db = tmp_path / "mlflow.db"
    db.write_bytes(b"my notes, not a database\n" * 100)
    uri = f"sqlite:///{db}"
    assert refused(uri, tmp_path / "run", monkeypatch) == (
        f"MLflow store {uri}: {db} cannot be read as an SQLite database (file is not a database); move the file "
        f"away (a new store is then created there), {ADVICE}")
    assert db.read_bytes() == b"my notes, not a database\n" * 100
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mlflow.db"]   # no lock file, no store beside it


def test_a_sqlite_database_that_is_not_a_store_is_refused_and_kept(tmp_path, monkeypatch):
    db = tmp_path / "mlflow.db"
    with sqlite3.connect(db) as con:
        con.execute("CREATE TABLE notes (text TEXT)")
        con.execute("INSERT INTO notes VALUES ('keep me')")
    before = db.read_bytes()
    uri = f"sqlite:///{db}"
    assert refused(uri, tmp_path / "run", monkeypatch) == (
        f"MLflow store {uri}: {db} is an SQLite database but not an MLflow store (no experiments or alembic_version "
        f"table); move the file away, {ADVICE}")
    assert db.read_bytes() == before


def test_a_store_of_another_mlflow_version_is_refused_and_kept(made_store, tmp_path, monkeypatch):
    import mlflow

    db = tmp_path / "mlflow.db"
    shutil.copy(made_store, db)
    with sqlite3.connect(db) as con:
        (head,), = con.execute("SELECT version_num FROM alembic_version").fetchall()
        con.execute("UPDATE alembic_version SET version_num = '0a8213491aaa'")   # MLflow 1.x's revision
    before = db.read_bytes()
    uri = f"sqlite:///{db}"
    assert refused(uri, tmp_path / "run", monkeypatch) == (
        f"MLflow store {uri}: its schema is version 0a8213491aaa, not the {head} of MLflow {mlflow.__version__} "
        f"(written by another MLflow version); if older, back up the database, then run `mlflow db upgrade {uri}`; "
        f"if newer, use that MLflow; {ADVICE}")
    assert db.read_bytes() == before


def test_a_server_that_does_not_answer_is_refused_at_once(tmp_path, monkeypatch):
    uri = f"http://127.0.0.1:{free_port()}"   # nothing listens there
    start = time.monotonic()
    message = refused(uri, tmp_path / "run", monkeypatch)
    # MLflow's own client retried for 4 min 9 s here before it gave up (a traceback)
    assert time.monotonic() - start < 30
    assert message.startswith(f"MLflow store {uri}: no tracking server answers at {uri}/health within 5 s (")
    assert "Connection refused" in message and "start it (mlflow server --host HOST --port PORT)" in message
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_new_store_is_created_once_under_the_lock_and_in_one_piece(tmp_path):
    db = tmp_path / "mlflow.db"
    db.touch()   # an empty database file (e.g. touched) is made a store too
    stale = tmp_path / ".mlflow.db.999999.0badcafe.creating"   # what a creation killed half-way left
    stale.write_bytes(b"half")
    uri = f"sqlite:///{db}"
    opened = []
    with file_lock(tmp_path / "mlflow.db.lock") as held:   # another process creating the store
        assert held
        thread = threading.Thread(target=lambda: opened.append(open_store(uri, write=True)))
        thread.start()
        thread.join(1.0)
        assert thread.is_alive() and db.stat().st_size == 0   # it waits, and writes nothing meanwhile
    thread.join(120)
    assert opened == [uri]
    with sqlite3.connect(db) as con:
        tables = {row[0] for row in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        experiments = con.execute("SELECT experiment_id, name FROM experiments").fetchall()
    assert {"experiments", "runs", "metrics", "registered_models", "alembic_version"} <= tables
    assert experiments == [(0, "Default")]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mlflow.db", "mlflow.db.lock"]
