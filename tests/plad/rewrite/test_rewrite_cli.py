"""``plad refine`` and ``plad search``: output format and one-line errors."""
import os
import shutil
import subprocess
import sys

import numpy as np

from plad.serve.cli import main
from tests.reference.csg2d_render import render

PLAD = shutil.which("plad")


def run(*args):
    cmd = [PLAD, *args] if PLAD else [sys.executable, "-m", "plad.serve.cli", *args]
    return subprocess.run(cmd, capture_output=True, text=True,
                          env={**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"})


def test_refine_prints_the_program_first_and_the_metric_change_last(tmp_path):
    target = tmp_path / "target.npy"
    np.save(target, render("s(24,24,16)c(40,40,12)+$"))
    out = tmp_path / "refined.txt"
    res = run("refine", "csg2d", "s(24,24,12)$", "--target", str(target), "-o", str(out),
              "--set", "refine.rounds=2")
    assert res.returncode == 0, res.stderr
    lines = res.stdout.strip().splitlines()
    name, before, arrow, after = lines[-1].split()
    assert name == "chamfer" and arrow == "->" and float(after) < float(before)
    assert float(after) == 0.0                       # the two-primitive target is rebuilt exactly
    assert np.array_equal(render(lines[0]), np.load(target))
    assert out.read_text().strip() == lines[0]


def test_refine_takes_an_effort_level(tmp_path, capsys):
    import torch

    from plad.domains import get_domain
    from plad.rewrite.evaluate import Scorer

    target = tmp_path / "target.npy"
    np.save(target, render("s(24,24,16)c(40,40,12)+$"))
    out = tmp_path / "refined.txt"
    assert main(["refine", "csg2d", "s(24,24,12)$", "--target", str(target), "-o", str(out), "--effort", "fast"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    name, before, arrow, after = lines[-1].split()
    assert name == "chamfer" and arrow == "->" and float(after) < float(before)
    # the reported value is the written program's, executed again
    domain = get_domain("csg2d")
    program = domain.parse(out.read_text().strip())
    assert out.read_text().strip() == lines[0]
    assert f"{float(Scorer(domain, torch.from_numpy(np.load(target)[None])).values([program])[0]):.6f}" == after


def test_search_from_scratch_prints_program_and_metric(tmp_path, capsys):
    target = tmp_path / "two.npy"
    np.save(target, np.stack([render("s(24,24,16)c(40,40,12)+$"), render("c(32,32,16)$")]))
    assert main(["search", "csg2d", str(target), "--set", "refine.rounds=0", "--set", "insertions=2"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[1] == "chamfer 0.000000" and lines[3] == "chamfer 0.000000" and lines[4] == "mean 0.000000"
    assert np.array_equal(render(lines[2]), render("c(32,32,16)$"))


def test_search_takes_an_effort_level(tmp_path, capsys):
    target = tmp_path / "two.npy"
    np.save(target, np.stack([render("s(24,24,16)c(40,40,12)+$"), render("c(32,32,16)$")]))
    for effort in ("fast", "best"):
        assert main(["search", "csg2d", str(target), "--effort", effort, "--set", "insertions=2"]) == 0
        lines = capsys.readouterr().out.strip().splitlines()
        assert lines[-1] == "mean 0.000000"


def test_bad_input_is_one_line(tmp_path, capsys):
    targets = tmp_path / "two.npy"
    np.save(targets, np.stack([render("c(32,32,16)$")] * 2))
    cases = [
        (("refine", "csg2d", "c(32,32,16)$", "--target", str(targets)), "refine takes one target shape"),
        (("refine", "csg2d", "c(3,32,16)$", "--target", str(targets)), "not in the vocabulary"),
        (("search", "csg2d", str(tmp_path / "missing.npy")), "no such file"),
        (("search", "csg2d", str(targets), "--set", "sweeps=3"), "unknown key(s) sweeps"),
        (("search", "csg2d", str(targets), "--set", "insertions"), "expected KEY=VALUE"),
        (("search", "csg2d", str(targets), "--set", "refine=3"), "refine = 3: expected a mapping of refine settings"),
        (("search", "csg2d", str(targets), "--effort", "quick"), "'quick': expected one of fast, default, best"),
        (("search", "csg2d", str(targets), "--effort", "fast", "--set", "effort=best"), "give the effort once"),
        (("refine", "csg2d", "c(32,32,16)$", "--target", str(targets), "--effort", "quick"),
         "'quick': expected one of fast, default, best"),
        (("refine", "csg2d", "c(32,32,16)$", "--target", str(targets), "--effort", "fast", "--set", "effort=best"),
         "give the effort once"),
    ]
    for args, message in cases:
        assert main(list(args)) == 2, args
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err
