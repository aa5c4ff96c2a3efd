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
