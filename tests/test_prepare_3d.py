"""Stage prepare_3d: PartNet programs -> the real 32^3 target shapes of the 3D domains."""
import json

import numpy as np
import pytest

from plad.data import DataError
from plad.stages.prepare import load_prepared
from plad.stages.prepare_3d import Prepare3DConfig, prepare_3d


def test_builds_shapes_of_every_split_and_the_domain_file(tmp_path, datasets_dir):
    result = prepare_3d(Prepare3DConfig(data_dir=str(datasets_dir), out_dir=str(tmp_path), limit=4))
    assert result["shapes"] == 12 and result["failures"] == 0
    report = json.loads((tmp_path / "partnet_voxels.json").read_text())
    assert report["listed"] == {"train": 4, "val": 4, "test": 4} and report["failures"] == []
    assert (tmp_path / "partnet_failures.log").read_text() == ""
    for split in ("train", "val", "test"):
        shapes = load_prepared(tmp_path / "shapeassembly.npz", split)
        assert shapes.shape == (4, 32, 32, 32) and shapes.reshape(4, -1).any(1).all()
    # val and test alternate over the official val ids: no shape is in both
    val, test = (load_prepared(tmp_path / "shapeassembly.npz", s) for s in ("val", "test"))
    assert not any(np.array_equal(a, b) for a in val for b in test)


def test_missing_or_broken_tarball_is_a_clear_error(tmp_path):
    with pytest.raises(DataError, match="partnet_programs.tar.gz"):
        prepare_3d(Prepare3DConfig(data_dir=str(tmp_path), out_dir=str(tmp_path / "out")))
    (tmp_path / "shapeassembly_partnet").mkdir()
    (tmp_path / "shapeassembly_partnet" / "partnet_programs.tar.gz").write_bytes(b"not a tarball")
    with pytest.raises(DataError, match="not a readable .tar.gz"):
        prepare_3d(Prepare3DConfig(data_dir=str(tmp_path), out_dir=str(tmp_path / "out")))
