"""Where the MLflow store is, and the one place that imports ``mlflow``.

The store is ``$MLFLOW_TRACKING_URI`` or ``./mlflow.db`` (SQLite, absolute
path), never the plain ``./mlruns`` file store. For a SQLite store the
experiment's artifacts go beside the database (``<db dir>/mlartifacts/``)
rather than MLflow's default ``<cwd>/mlruns/<id>``, which depends on the
directory the experiment happened to be created from.

``mlflow`` is imported lazily by :func:`mlflow_module` (it costs about 3 s),
so importing :mod:`plad.tracking` stays cheap.

Opening a store (:func:`open_store`, once per process and store, before anything
reads or writes it) is what makes concurrent first runs safe and a broken store a
one-line :class:`StoreError`:

* SQLite: MLflow creates and migrates the schema on the first connection, and
  first connections that run together race (``table experiments already
  exists``, ``duplicate column name: step``). Here a new store is created once,
  under an exclusive ``flock`` on ``<database>.lock`` beside the database, in a
  temporary file beside it that is renamed into place only once complete (a
  killed creation leaves no half-made store); every other process waits on the
  lock, then finds the store complete. MLflow's own open, which completes a schema
  that lacks tables (an older store: it upgrades it), runs under the lock too; a store
  of another schema version with every table is refused (``mlflow db upgrade`` is the
  user's call). A file that is not an SQLite database, a SQLite database that is not an
  MLflow store, an unwritable folder or database are refused before MLflow sees them
  (MLflow raises a traceback; in a folder it cannot write, after retrying for 1 min
  44 s, measured); nothing is written to them.
* HTTP(S): the server is probed (``/health``, :data:`PROBE_TIMEOUT_S`); no answer is
  a :class:`StoreError` at once (MLflow's client retried for 4 min 9 s against a
  refused port here, then raised a traceback).
* Other stores (``postgresql://``, ``databricks``, ...) are opened by MLflow; what it raises is
  a :class:`StoreError` too (a database server that does not answer takes MLflow's retries first).
"""
from __future__ import annotations

import contextlib
import os
import re
import sqlite3
import ssl
import threading
import urllib.error
import urllib.request
import uuid
from collections.abc import Iterator
from glob import escape as glob_escape
from pathlib import Path
from typing import Any

from plad.errors import RunFailure, one_line
from plad.fsutil import file_lock

#: the experiment of the pipeline runs (one per profile: the report, its tables and pictures, the models it
#: registers); older stores also hold every stage run here, from before the experiments per domain
PIPELINE_EXPERIMENT = "plad"
#: the experiment of a domain's runs (:func:`domain_experiment`): ``plad-<domain>``
DOMAIN_EXPERIMENT_PREFIX = "plad-"
# MLflow's limits (mlflow.utils.validation), repeated here to avoid importing mlflow.
MAX_PARAM_VAL_LENGTH = 6000
MAX_KEY_LENGTH = 250
MAX_TAG_VAL_LENGTH = 8000
#: how long a tracking server may take to answer the probe of :func:`open_store`, in seconds
PROBE_TIMEOUT_S = 5.0
#: what every store error suggests besides its own fix
ELSEWHERE = ("or set MLFLOW_TRACKING_URI to another store (sqlite:////absolute/path/mlflow.db, "
             "or a tracking server http://host:port)")


class StoreError(RunFailure):
    """The MLflow store cannot be opened or written; one line naming its URI and what to do (exit status 1)."""

    def __init__(self, uri: str, problem: str, advice: str) -> None:
        self.uri, self.problem, self.advice = uri, problem, advice
        super().__init__(one_line(f"MLflow store {uri}: {problem}; {advice}"))

    def __reduce__(self) -> tuple[type[StoreError], tuple[str, str, str]]:
        # picklable across worker processes (Prefect, Dask), like plad.data.DataError
        return (type(self), (self.uri, self.problem, self.advice))


def tracking_uri() -> str:
    """``$MLFLOW_TRACKING_URI`` if set, else ``sqlite:///<cwd>/mlflow.db`` (absolute)."""
    env = os.environ.get("MLFLOW_TRACKING_URI")
    if env:
        return env
    return "sqlite:///" + str((Path.cwd() / "mlflow.db").resolve())


def mlflow_module() -> Any:
    """``mlflow`` (imported on first use) pointed at :func:`tracking_uri`."""
    import mlflow

    uri = tracking_uri()
    if mlflow.get_tracking_uri() != uri:
        mlflow.set_tracking_uri(uri)
    return mlflow


def client() -> Any:
    """An ``MlflowClient`` of the store at :func:`tracking_uri`, opened (:func:`open_store`)."""
    open_store()
    return mlflow_module().MlflowClient()


def sqlite_path(uri: str) -> Path | None:
    """The database file of a SQLite store URI (absolute), else ``None``."""
    if not uri.startswith("sqlite:///"):
        return None
    rest = uri[len("sqlite:///"):].split("?", 1)[0]
    if not rest or rest == ":memory:":
        return None
    path = Path(rest)  # sqlite:////abs/path -> "/abs/path"; sqlite:///rel -> relative to the cwd
    return path if path.is_absolute() else path.resolve()


def _artifact_location(uri: str, experiment: str) -> str | None:
    """Artifacts of a SQLite store live beside the database, not under the cwd."""
    db = sqlite_path(uri)
    if db is None:
        return None  # a server or another store decides
    safe = re.sub(r"[^\w.-]+", "_", experiment).strip("._") or "experiment"
    return (db.parent / "mlartifacts" / safe).as_uri()


def ensure_experiment(mlflow_client: Any, uri: str, name: str) -> str:
    """The id of experiment ``name``, created (or restored from deleted) when needed."""
    from mlflow.exceptions import MlflowException

    exp = mlflow_client.get_experiment_by_name(name)
    if exp is None:
        try:
            return mlflow_client.create_experiment(name, artifact_location=_artifact_location(uri, name))
        except MlflowException:  # created concurrently by another stage
            exp = mlflow_client.get_experiment_by_name(name)
            if exp is None:
                raise
    if exp.lifecycle_stage == "deleted":
        mlflow_client.restore_experiment(exp.experiment_id)
    return exp.experiment_id


def domain_experiment(domain: str) -> str:
    """The experiment of one domain's runs, ``plad-<domain>``: one experiment per domain, so that a metric
    column and a chart of an experiment compare one metric (Chamfer distance in 2D, IoU in 3D), never two."""
    if not isinstance(domain, str) or not re.fullmatch(r"[A-Za-z0-9][\w.-]*", domain):
        raise ValueError(f"MLflow experiment of domain {domain!r}: expected one domain name (letters, digits, "
                         "'_', '-', '.')")
    return DOMAIN_EXPERIMENT_PREFIX + domain


def find_experiment(name: str) -> str:
    """The id of an existing experiment; ``LookupError`` naming the store when there is none."""
    return find_experiments([name])[0]


def find_experiments(names: list[str]) -> list[str]:
    """The ids of those of the experiments ``names`` that exist, in that order; ``LookupError`` naming the
    first and the store when none does."""
    mlflow_client = client()
    found = [exp.experiment_id for exp in map(mlflow_client.get_experiment_by_name, names) if exp is not None]
    if not found:
        others = "".join(f" (or {n!r})" for n in names[1:])
        raise LookupError(f"no MLflow experiment {names[0]!r}{others} at {tracking_uri()}")
    return found


# -- opening a store ------------------------------------------------------------------------------
_OPENED: set[tuple[str, bool]] = set()      # (uri, write) opened by this process
_OPENING = threading.Lock()                 # threads of one process (Prefect's thread runner) open one at a time


def open_store(uri: str | None = None, *, write: bool = False) -> str:
    """Make the store at ``uri`` (default :func:`tracking_uri`) ready for this process; returns the URI.

    Once per process (and per ``write``): a SQLite store is created if it does not exist, under
    the inter-process lock beside it, and checked (readable, an MLflow store, its schema that of
    this MLflow; with ``write``, writable); a tracking server must answer. Anything else is left
    to MLflow. A store that cannot be used is a :class:`StoreError`, and nothing is written to it.
    """
    uri = uri or tracking_uri()
    if (uri, write) in _OPENED:
        return uri
    with _OPENING:
        if (uri, write) not in _OPENED:
            db = sqlite_path(uri)
            if db is not None:
                _open_sqlite(uri, db, write)
            elif uri.startswith(("http://", "https://")):
                _probe_server(uri)
            else:
                with store_errors(uri, "cannot be opened"):
                    mlflow_module().MlflowClient(tracking_uri=uri).search_experiments(max_results=1)
            _OPENED.update({(uri, write), (uri, False)})
    return uri


@contextlib.contextmanager
def store_errors(uri: str, doing: str) -> Iterator[None]:
    """Turn what MLflow, SQLAlchemy or the network raise about the store into a one-line :class:`StoreError`."""
    from mlflow.exceptions import MlflowException

    try:
        yield
    except StoreError:
        raise
    except MlflowException as err:
        old = re.search(r"out-of-date database schema \(found version (\w+), but expected (\w+)\)", str(err.message))
        if old:   # written by another MLflow: upgrading the schema is the user's call (MLflow: back up first)
            import mlflow

            raise StoreError(uri, f"its schema is version {old[1]}, not the {old[2]} of MLflow {mlflow.__version__} "
                                  "(written by another MLflow version)",
                             f"if older, back up the database, then run `mlflow db upgrade {uri}`; if newer, use "
                             f"that MLflow; {ELSEWHERE}") from err
        raise StoreError(uri, f"{doing}: {_short(err.message)}", f"check the store, {ELSEWHERE}") from err
    except Exception as err:
        import requests
        import sqlalchemy.exc

        if isinstance(err, (sqlalchemy.exc.SQLAlchemyError, requests.RequestException)):
            raise StoreError(uri, f"{doing}: {_short(err)}", f"check the store, {ELSEWHERE}") from err
        raise


def _short(message: object) -> str:
    """The gist of an MLflow/SQLAlchemy message: one line, without the SQL statement and the links."""
    text = one_line(message)
    for cut in (" [SQL:", " (Background on this error"):
        text = text.split(cut, 1)[0]
    return text if len(text) <= 300 else text[:297] + "..."


def _open_sqlite(uri: str, db: Path, write: bool) -> None:
    try:
        db.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise StoreError(uri, f"cannot create the folder {db.parent} ({err.strerror or err})",
                         f"create it or make it writable, {ELSEWHERE}") from None
    if db.exists():
        _sqlite_tables(uri, db)         # not a database / not MLflow's: refused before anything else
    # what MLflow's open imports (0.7 s), imported before the lock so that processes hold it for 0.1 s each
    import alembic.runtime.migration  # noqa: F401
    import alembic.script  # noqa: F401
    import mlflow.store.tracking.sqlalchemy_store  # noqa: F401

    with _lock_beside(uri, db):
        tables = _sqlite_tables(uri, db) if db.exists() else set()
        if not tables:                  # a new store (or an empty database file): create it, once
            _create_sqlite(uri, db)
        # MLflow's own open (engine, schema version, default experiment) under the lock too, so
        # that a store whose schema is incomplete is never completed by two processes at once
        with store_errors(uri, "cannot be opened"):
            mlflow_module().MlflowClient(tracking_uri=uri).search_experiments(max_results=1)
    if write:
        for path in (db, db.parent):    # the folder too: SQLite writes its journal beside the database
            if not os.access(path, os.W_OK):
                raise StoreError(uri, f"{path} is read-only, so runs cannot be recorded",
                                 f"make it writable, {ELSEWHERE}")


def _sqlite_tables(uri: str, db: Path) -> set[str]:
    """The table names of the database ``db`` (read, not written); :class:`StoreError` when it is no MLflow store."""
    if not db.is_file():
        raise StoreError(uri, f"{db} is not a file", f"remove it, {ELSEWHERE}")
    con = None
    try:
        # never creates the file; read-only where it cannot be written (mode=rw only so that SQLite may
        # roll back the journal a killed writer left, as MLflow's own connection would)
        mode = "rw" if os.access(db, os.W_OK) else "ro"
        con = sqlite3.connect(f"{db.as_uri()}?mode={mode}", uri=True, timeout=30)
        tables = {row[0] for row in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    except sqlite3.Error as err:
        raise StoreError(uri, f"{db} cannot be read as an SQLite database ({err})",
                         f"move the file away (a new store is then created there), {ELSEWHERE}") from None
    finally:
        if con is not None:
            con.close()
    if tables and not {"experiments", "alembic_version"} <= tables:
        raise StoreError(uri, f"{db} is an SQLite database but not an MLflow store (no experiments or "
                              "alembic_version table)", f"move the file away, {ELSEWHERE}")
    return tables


@contextlib.contextmanager
def _lock_beside(uri: str, db: Path) -> Iterator[None]:
    """The exclusive lock ``<db>.lock`` (:func:`plad.fsutil.file_lock`) for as long as the block runs.

    In a folder where the lock file cannot be created (read-only), an existing store is opened
    without it (nothing can create or change a schema there), and a new one is refused.
    """
    lock = db.with_name(db.name + ".lock")
    with file_lock(lock) as held:   # waits while another process creates or opens the store
        if not held and not db.exists():
            raise StoreError(uri, f"cannot create the lock file {lock}, so no store can be created in {db.parent}",
                             f"make the folder writable, {ELSEWHERE}")
        yield


def _create_sqlite(uri: str, db: Path) -> None:
    """Create an MLflow store at ``db`` (absent, or an empty database) as one rename of a complete one."""
    from mlflow.store.tracking.sqlalchemy_store import SqlAlchemyStore

    if not os.access(db.parent, os.W_OK):   # else MLflow retries for 1 min 44 s before it gives up
        raise StoreError(uri, f"{db.parent} is read-only, so no store can be created there",
                         f"make it writable, {ELSEWHERE}")
    # what a creation killed half-way left (creations run only under the lock, so none is running now)
    for stale in db.parent.glob(f".{glob_escape(db.name)}.*.creating*"):
        stale.unlink(missing_ok=True)
    # not mkstemp: SQLite creates the file itself, with the permissions the user's umask gives
    tmp = db.with_name(f".{db.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.creating")
    tmp_uri = "sqlite:///" + str(tmp)
    try:
        with store_errors(uri, f"cannot be created (in {tmp.name})"):
            mlflow_module().MlflowClient(tracking_uri=tmp_uri).search_experiments(max_results=1)
        engine = getattr(SqlAlchemyStore, "_engine_map", {}).pop(tmp_uri, None)   # close MLflow's connections
        if engine is not None:
            engine.dispose()
        try:
            if db.exists():
                os.replace(tmp, db)     # an empty database: nothing in it to keep
            else:
                os.link(tmp, db)        # never over a store another (lock-less) program made meanwhile
        except FileExistsError:
            pass
        except OSError as err:
            raise StoreError(uri, f"cannot create {db} ({err.strerror or err})",
                             f"make {db.parent} writable, {ELSEWHERE}") from None
    finally:
        for leftover in (tmp, tmp.with_name(tmp.name + "-journal")):
            leftover.unlink(missing_ok=True)


def _probe_server(uri: str) -> None:
    """A tracking server must answer (any HTTP status) within :data:`PROBE_TIMEOUT_S`."""
    url = uri.rstrip("/") + "/health"
    try:
        with urllib.request.urlopen(urllib.request.Request(url, method="GET"), timeout=PROBE_TIMEOUT_S):
            pass
    except urllib.error.HTTPError:
        pass                    # it answers: what it answers to MLflow's requests is MLflow's to report
    except (urllib.error.URLError, OSError, ValueError) as err:
        reason = err.reason if isinstance(err, urllib.error.URLError) else err
        if isinstance(reason, ssl.SSLError):
            return              # it answers over TLS; MLflow has its own certificate settings (MLFLOW_TRACKING_*)
        raise StoreError(uri, f"no tracking server answers at {url} within {PROBE_TIMEOUT_S:g} s ({reason})",
                         f"start it (mlflow server --host HOST --port PORT), {ELSEWHERE}") from None
    except Exception as err:    # http.client.HTTPException: something answers, but not HTTP
        raise StoreError(uri, f"{url} does not answer as an HTTP server ({type(err).__name__}: {err})",
                         f"check the address, {ELSEWHERE}") from None
