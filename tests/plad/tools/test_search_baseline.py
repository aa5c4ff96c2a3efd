"""The search-only baseline's command line (plad.tools.search_baseline)."""
from __future__ import annotations

from plad.tools.search_baseline import main as baseline


def test_baseline_names_a_bad_setting_in_one_line(tmp_path, capsys):
    """``python -m plad.tools.search_baseline`` checks its ``--set`` before it looks for data or starts work."""
    assert baseline(["shapeassembly", "--prepared", str(tmp_path), "--set", "refine.remov=true"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "unknown key(s) remov in 'search.refine'" in err
    assert baseline(["shapeassembly", "--prepared", str(tmp_path)]) == 1      # good settings, no data
    assert "no such prepared dataset" in capsys.readouterr().err


def test_baseline_writes_its_summary_and_programs(tmp_path, capsys):
    import json

    import numpy as np

    from plad.data.files import write_prepared
    from plad.domains import get_domain
    from plad.domains.base import pad_programs

    domain = get_domain("csg2d")
    shapes = domain.execute(pad_programs(domain.sample(3, np.random.default_rng(0)))).numpy()
    write_prepared("csg2d", domain.shape, {"test": shapes}, tmp_path / "csg2d.npz", tmp_path / "csg2d.json")
    out = tmp_path / "base.json"
    assert baseline(["csg2d", "--prepared", str(tmp_path), "--limit", "2", "--set", "insertions=1",
                     "--set", "refine.rounds=0", "--out", str(out)]) == 0
    assert capsys.readouterr().out.startswith("csg2d test: 2 shapes, mean chamfer ")
    summary = json.loads(out.read_text())
    assert summary["n"] == 2 and "programs" not in summary and summary["config"]["insertions"] == 1
    lines = out.with_suffix(".programs.txt").read_text().splitlines()
    assert len(lines) == 2 and all("\t" in line for line in lines)
