"""bench.sampler: both thread settings draw the same programs, and the report names every sampler."""
from __future__ import annotations


def test_the_sampler_benchmark_reports_each_sampler_and_identical_programs(capsys):
    from bench.sampler import main

    assert main(["--domains", "csg3d", "--programs", "20", "--repeats", "1", "--threads", "2"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [line.split(":")[0] for line in out[1:-1]] == ["csg3d paper", "csg3d parts"]
    assert all("identical True" in line for line in out[1:]) and out[-1].startswith("ratio ")
