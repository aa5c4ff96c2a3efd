"""Prefect flows. They call the same functions as the DVC stages (``plad.stages``).

Importing this package sets the project's Prefect defaults, before any flow module imports
Prefect, so that an offline run is quiet and works on a busy machine. Each is a default
(``os.environ.setdefault``): to change one, set the environment variable (Prefect ranks
environment variables above a profile's ``prefect config set``, so a profile cannot).

* ``PREFECT_SERVER_ANALYTICS_ENABLED=false``: the temporary server that a plain flow run starts
  sends no telemetry; its telemetry heartbeat is what printed "Failed to send telemetry" offline
  and "database is locked" tracebacks (it writes to the server's SQLite database while the flow
  run does);
* ``DO_NOT_TRACK=1``: the client sends no analytics either;
* ``PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS=90``: the temporary server gets 90 s to start
  instead of 20 (it took 25 s on our busy 2-core machine, and the run failed at 20).
"""
from __future__ import annotations

import os

PREFECT_DEFAULTS = {
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "DO_NOT_TRACK": "1",
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "90",
}
for _key, _value in PREFECT_DEFAULTS.items():
    os.environ.setdefault(_key, _value)


def one_line_errors() -> None:
    """Prefect logs a failing flow's or task's exception with its traceback; for an error a user can fix
    (:class:`plad.errors.PladError`: a params, data or checkpoint problem) the command prints it as one line
    anyway (:func:`plad.errors.run_guarded`), so Prefect keeps only its message line for those."""
    import logging

    from plad.errors import PladError

    def drop_traceback(record: logging.LogRecord) -> bool:
        if record.exc_info and isinstance(record.exc_info[1], PladError):
            record.exc_info, record.exc_text = None, None
        return True

    for name in ("prefect.flow_runs", "prefect.task_runs"):
        logger = logging.getLogger(name)
        if drop_traceback.__qualname__ not in {getattr(f, "__qualname__", "") for f in logger.filters}:
            logger.addFilter(drop_traceback)
