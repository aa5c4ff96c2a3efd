"""Runs started together: six processes open a StageRun and log metrics at the same moment, on a new
SQLite store and then on the existing one (tests/plad/tracking/stage_run_worker.py); a store in a
read-only folder is one line in a real process.

Before plad.tracking.store took a lock beside the database, five of six first runs died on MLflow's
schema migrations (``table experiments already exists``, ``duplicate column name: step``).
"""
from __future__ import annotations

import hashlib
import os
import re
import shutil
import sqlite3
import sys
import time
from pathlib import Path

import pytest

from tests.procs import child_env, children, left_behind, start, stop, tail

pytestmark = pytest.mark.integration

WORKER = "tests.plad.tracking.stage_run_worker"
STEPS = 30


def workers(folder: Path, uri: str, indices: range, prefix: tuple[str, ...] = ()) -> list[tuple[int, int, list[str]]]:
    """Start one worker per index (run folder ``folder/run<i>``), wait until each has imported mlflow,
    then let them all open the store at once; returns (index, exit status, output lines) per worker."""
    folder.mkdir(parents=True, exist_ok=True)
    env = child_env(MLFLOW_TRACKING_URI=uri, PLAD_PIPELINE_ID="concurrency")
    procs = [(i, start([*prefix, sys.executable, "-m", WORKER, str(folder / f"run{i}"), str(i), str(STEPS)],
                       env, folder / f"log{i}", cwd=folder)) for i in indices]
    try:
        deadline = time.monotonic() + 180
        while not all((folder / f"ready{i}").exists() for i in indices):
            for i, proc in procs:
                assert proc.poll() is None or (folder / f"ready{i}").exists(), tail(folder / f"log{i}")
            assert time.monotonic() < deadline, "the workers did not start within 180 s"
            time.sleep(0.05)
        (folder / "go").touch()
        return [(i, proc.wait(timeout=240), (folder / f"log{i}").read_text(errors="replace").splitlines())
                for i, proc in procs]
    finally:
        for _, proc in procs:
            stop(proc)


def run_ids(results: list[tuple[int, int, list[str]]]) -> dict[int, str]:
    """{worker: run id}: each worker exited 0 and printed its run id (32 hex digits), once."""
    ids = {}
    for i, status, lines in results:
        assert status == 0, f"worker {i} exited {status}:\n" + "\n".join(lines[-30:])
        printed = [line for line in lines if re.fullmatch(r"[0-9a-f]{32}", line)]
        assert len(printed) == 1, lines[-10:]
        ids[i] = printed[0]
    return ids


def stored_runs(db: Path) -> dict[str, tuple[str, str, str, list[tuple[int, float]]]]:
    """{run id: (experiment, name of its row run, run name, status, [(step, loss)...])} of the stage runs of
    the workers' experiments (``plad-worker<i>``: one per domain; the row runs they nest under,
    plad.tracking.rows, left out), read with sqlite3."""
    with sqlite3.connect(db) as con:
        runs = con.execute("SELECT r.run_uuid, r.name, r.status, e.name FROM runs r JOIN experiments e "
                           "ON r.experiment_id = e.experiment_id WHERE e.name LIKE 'plad-worker%'").fetchall()
        names = {run_id: name for run_id, name, *_ in runs}
        tags = dict(con.execute("SELECT run_uuid || '/' || key, value FROM tags").fetchall())
        out = {}
        for run_id, name, status, experiment in runs:
            if f"{run_id}/plad.row" in tags:
                continue
            history = con.execute("SELECT step, value FROM metrics WHERE run_uuid = ? AND key = 'loss' "
                                  "ORDER BY step", (run_id,)).fetchall()
            out[run_id] = (experiment, names.get(tags.get(f"{run_id}/mlflow.parentRunId")), name, status, history)
    return out


def expected_history(i: int) -> list[tuple[int, float]]:
    return [(step, i + step / 100) for step in range(STEPS)]


def test_six_first_runs_on_a_new_store_all_succeed_and_so_do_six_on_the_existing_one(tmp_path):
    before = children()
    db = tmp_path / "store" / "mlflow.db"        # the folder does not exist yet either
    uri = f"sqlite:///{db}"

    first = run_ids(workers(tmp_path / "first", uri, range(6)))
    assert len(set(first.values())) == 6
    runs = stored_runs(db)
    assert set(runs) == set(first.values())
    for i, run_id in first.items():
        assert runs[run_id] == (f"plad-worker{i}", "sp", "pretrain", "FINISHED", expected_history(i))
    # the store was made once, in place: the lock file beside it, nothing half-made left
    assert sorted(p.name for p in db.parent.iterdir() if not p.is_dir()) == ["mlflow.db", "mlflow.db.lock"]

    again = run_ids(workers(tmp_path / "again", uri, range(6, 12)))
    runs = stored_runs(db)
    assert set(runs) == set(first.values()) | set(again.values()) and len(runs) == 12
    for i, run_id in again.items():
        assert runs[run_id] == (f"plad-worker{i}", "sp", "pretrain", "FINISHED", expected_history(i))
    assert not left_behind(before)


def without_root_override() -> tuple[str, ...]:
    """A command prefix under which file permissions bind this user: none for a normal user; for root,
    ``setpriv`` without the capabilities that let root write anywhere (skip when there is none)."""
    if os.geteuid() != 0:
        return ()
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("running as root, and no setpriv to drop the capability that writes through permissions")
    return (setpriv, "--bounding-set=-dac_override,-dac_read_search")


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_store_in_a_read_only_folder_is_one_line_and_is_left_as_it_was(tmp_path):
    before = children()
    prefix = without_root_override()
    # a new store where none can be created
    new = tmp_path / "new"
    new.mkdir()
    # an existing store in a folder that became read-only (made here by a first run)
    old = tmp_path / "old"
    run_ids(workers(tmp_path / "make", f"sqlite:///{old / 'mlflow.db'}", range(1)))
    kept = digest(old / "mlflow.db")
    for folder in (new, old):
        folder.chmod(0o555)
    try:
        for folder, problem in (
                (new, f"cannot create the lock file {new / 'mlflow.db.lock'}, so no store can be created in {new}"),
                (old, f"{old} is read-only, so runs cannot be recorded")):
            uri = f"sqlite:///{folder / 'mlflow.db'}"
            (_, status, lines), = workers(tmp_path / f"try-{folder.name}", uri, range(1), prefix)
            advice = "make the folder writable" if folder is new else "make it writable"
            # the whole output: one line, naming the store, the problem and what to do
            assert status == 1 and lines == [
                f"stage_run_worker: error: MLflow store {uri}: {problem}; {advice}, or set MLFLOW_TRACKING_URI to "
                "another store (sqlite:////absolute/path/mlflow.db, or a tracking server http://host:port)"], lines
            assert not (tmp_path / f"try-{folder.name}" / "run0").exists()   # no run file either
    finally:
        for folder in (new, old):
            folder.chmod(0o755)
    assert sorted(p.name for p in new.iterdir()) == []
    assert digest(old / "mlflow.db") == kept
    assert not left_behind(before)
