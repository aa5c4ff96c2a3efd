"""The grafting library's builder (plad.tools.graft_library): the library of the programs search finds for
evenly spaced training shapes, from the batch's programs only."""
from __future__ import annotations

import pytest

from plad.data.files import write_prepared
from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.rewrite import search_config
from plad.rewrite.graft import Library
from plad.tools import graft_library


def _execute(domain, programs):
    return domain.execute(pad_programs(programs))


def test_the_library_command_writes_what_a_refinement_loads(tmp_path, capsys):
    domain = get_domain("csg2d")
    shapes = _execute(domain, [domain.parse("s(24,24,8)c(40,40,12)+$"), domain.parse("s(32,32,16)c(32,32,8)-$")])
    write_prepared("csg2d", domain.shape, {"train": shapes.numpy()}, tmp_path / "csg2d.npz", tmp_path / "csg2d.json")
    out = tmp_path / "lib.npz"
    graft_library.main(["csg2d", "--prepared", str(tmp_path), "--spaced", "2", "--out", str(out)])
    assert f"{out}: 6 sub-expressions" in capsys.readouterr().out
    library = Library.load(out, domain)
    # search finds both shapes exactly: the library executes to their 6 sub-expressions, all distinct
    expected = _execute(domain, [domain.parse(t) for t in (
        "s(24,24,8)$", "c(40,40,12)$", "s(24,24,8)c(40,40,12)+$", "s(32,32,16)$", "c(32,32,8)$",
        "s(32,32,16)c(32,32,8)-$")])
    def keys(x):
        return sorted(row.numpy().tobytes() for row in x.reshape(len(x), -1))

    assert keys(library.executions) == keys(expected)
    assert search_config(domain, **{"refine.graft_library": str(out)}).refine.graft_library == str(out)
    with pytest.raises(SystemExit, match="shapeassembly: the domain has no expression tree"):
        graft_library.main(["shapeassembly", "--prepared", str(tmp_path)])
    with pytest.raises(SystemExit, match="no such prepared dataset"):
        graft_library.main(["csg3d", "--prepared", str(tmp_path)])


def test_the_builder_searches_with_the_batch_only(tmp_path, monkeypatch):
    """The builder's search must not read the file it is about to replace (the 2D search levels graft from the
    shipped library)."""
    from plad.rewrite import driver

    domain = get_domain("csg2d")
    seen = []
    real = driver.search

    def spy(domain, targets, config, **kw):
        seen.append(config.refine.graft_library)
        return real(domain, targets, config, **kw)

    monkeypatch.setattr(driver, "search", spy)
    shapes = _execute(domain, [domain.parse("s(24,24,8)c(40,40,12)+$")])
    write_prepared("csg2d", domain.shape, {"train": shapes.numpy()}, tmp_path / "csg2d.npz", tmp_path / "csg2d.json")
    graft_library.main(["csg2d", "--prepared", str(tmp_path), "--spaced", "1", "--out", str(tmp_path / "lib.npz")])
    assert seen == [None]
