"""A flow that fails on an error a user can fix prints one line (issue 30): a bad params file before Prefect
starts, and no Prefect traceback for a PladError raised inside a flow or task."""
from __future__ import annotations

import logging
import subprocess
import sys

import pytest

from tests.conftest import REPO_ROOT


@pytest.mark.parametrize("module", ["flows.prepare_data", "flows.finetune"])
def test_a_bad_params_file_is_one_line_before_prefect_starts(module, tmp_path):
    (tmp_path / "bin.yaml").write_bytes(bytes(range(256)) * 8)
    res = subprocess.run([sys.executable, "-m", module, "--params", str(tmp_path / "bin.yaml")], cwd=REPO_ROOT,
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 1
    assert res.stderr == f"{module}: error: {tmp_path / 'bin.yaml'}: not a text file (YAML is UTF-8 text)\n"


def test_prefect_logs_a_plad_error_without_its_traceback():
    from flows import one_line_errors
    from plad.config import ConfigError

    one_line_errors()
    one_line_errors()   # idempotent: one filter
    logger = logging.getLogger("prefect.flow_runs")
    assert sum("drop_traceback" in getattr(f, "__qualname__", "") for f in logger.filters) == 1
    records = []
    for err in (ConfigError("params.yaml: bad key"), RuntimeError("a bug")):
        try:
            raise err
        except Exception:
            record = logger.makeRecord(logger.name, logging.ERROR, __file__, 1, "Encountered exception", (),
                                       sys.exc_info())
        assert logger.filter(record)
        records.append(record)
    assert records[0].exc_info is None                                   # a user's error: its message line only
    assert records[1].exc_info is not None and records[1].exc_info[0] is RuntimeError   # a bug keeps it
