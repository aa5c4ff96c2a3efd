"""Prefect flows run the same functions as the DVC stages."""
import json

import pytest


@pytest.fixture(scope="module")
def prefect_harness(tmp_path_factory):
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=120):
        yield


def test_prepare_flow_matches_the_stage(tmp_path, datasets_dir, prefect_harness):
    from flows.prepare_data import prepare_data
    from plad.stages.prepare import load_prepared

    params = tmp_path / "params.yaml"
    params.write_text(f"prepare:\n  data_dir: {datasets_dir}\n  out_dir: {tmp_path / 'out'}\n")
    result = prepare_data(str(params))
    assert result["csg2d"]["val_count"] == 3000
    assert json.loads((tmp_path / "out" / "csg2d.json").read_text()) == result["csg2d"]
    assert load_prepared(tmp_path / "out" / "csg2d.npz", "val").shape == (3000, 64, 64)
