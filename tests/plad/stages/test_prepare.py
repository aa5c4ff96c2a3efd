"""Stage prepare: every domain's real target shapes, prepared once per target source."""
import json

import numpy as np
import pytest

from plad.config import ConfigError
from plad.data.datasets.cad import load_cad
from plad.data.files import DataError, load_prepared
from plad.layout import Layout
from plad.stages.prepare import PrepareConfig, main, prepare, prepare_sources, target_groups


def test_domains_on_one_source_share_one_build(tmp_path, datasets_dir):
    cfg = PrepareConfig(domains=["csg3d", "shapeassembly"], data_dir=str(datasets_dir), limit={"partnet": 4})
    layout = Layout(tmp_path)
    result = prepare(cfg, layout)
    assert result["sources"]["partnet"]["shapes"] == 12 and result["sources"]["partnet"]["failures"] == 0
    out = tmp_path / "data" / "prepared"
    assert sorted(p.name for p in out.iterdir()) == ["csg3d.json", "csg3d.npz", "partnet_failures.log",
                                                     "partnet_voxels.json", "partnet_voxels.npz",
                                                     "shapeassembly.json", "shapeassembly.npz"]
    report = json.loads((out / "partnet_voxels.json").read_text())
    assert report["listed"] == {"train": 4, "val": 4, "test": 4} and report["failures"] == []
    assert (out / "partnet_failures.log").read_text() == ""
    for split in ("train", "val", "test"):
        shapes = load_prepared(layout.prepared("shapeassembly"), split)
        assert shapes.shape == (4, 32, 32, 32) and shapes.reshape(4, -1).any(1).all()
        assert np.array_equal(load_prepared(layout.prepared("csg3d"), split), shapes)
    for domain in ("csg3d", "shapeassembly"):
        summary = json.loads(layout.prepared_summary(domain).read_text())
        assert summary == result["domains"][domain] and summary["source"] == "partnet_voxels.npz"
    # val and test alternate over the official val ids: no shape is in both
    val, test = (load_prepared(layout.prepared("shapeassembly"), s) for s in ("val", "test"))
    assert not any(np.array_equal(a, b) for a in val for b in test)


def test_a_limit_keeps_the_first_shapes_of_each_split(tmp_layout, datasets_dir):
    result = prepare(PrepareConfig(domains=["csg2d"], data_dir=str(datasets_dir), limit={"cad": 5}), tmp_layout)
    assert result["domains"]["csg2d"]["test_count"] == 5
    assert np.array_equal(load_prepared(tmp_layout.prepared("csg2d"), "test"), load_cad(datasets_dir, "test")[:5])


def test_groups_by_source_and_one_config_per_source():
    assert target_groups(["csg3d", "csg2d", "shapeassembly"]) == {"partnet": ["csg3d", "shapeassembly"],
                                                                 "cad": ["csg2d"]}
    parts = prepare_sources(PrepareConfig(domains=["csg2d", "csg3d", "shapeassembly"], limit={"partnet": 3}))
    assert [(p.domains, p.limit) for p in parts] == [(["csg2d"], {}), (["csg3d", "shapeassembly"], {"partnet": 3})]


def test_a_limit_of_a_source_no_domain_uses_is_an_error(tmp_layout):
    with pytest.raises(ConfigError, match="'partnet' is not the target source of a configured domain"):
        prepare(PrepareConfig(domains=["csg2d"], limit={"partnet": 3}), tmp_layout)


def test_missing_or_broken_tarball_is_a_clear_error(tmp_path):
    cfg = PrepareConfig(domains=["shapeassembly"], data_dir=str(tmp_path))
    with pytest.raises(DataError, match="partnet_programs.tar.gz"):
        prepare(cfg, Layout(tmp_path / "out"))
    (tmp_path / "shapeassembly_partnet").mkdir()
    (tmp_path / "shapeassembly_partnet" / "partnet_programs.tar.gz").write_bytes(b"not a tarball")
    with pytest.raises(DataError, match="not a readable .tar.gz"):
        prepare(cfg, Layout(tmp_path / "out"))


def test_a_section_without_domains_is_a_one_line_error(tmp_path, capsys):
    p = tmp_path / "params.yaml"
    p.write_text("prepare:\n  limit: {}\n")
    assert main(["--params", str(p), "--root", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"prepare: error: {p}: missing key(s) domains in 'prepare'"
