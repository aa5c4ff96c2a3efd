"""The ``plad`` command line: execute and score, through the installed console script."""
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
from PIL import Image

from plad.domains import get_domain
from tests.reference.csg2d_render import render

PLAD = shutil.which("plad")


def run(*args, cwd=None):
    cmd = [PLAD, *args] if PLAD else [sys.executable, "-m", "plad.serve.cli", *args]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=cwd, env={**os.environ})


def test_execute_writes_png_and_npy(tmp_path):
    program = "c(32,24,16)s(40,40,12)+$"
    res = run("execute", "csg2d", program, "-o", str(tmp_path / "shape.png"))
    assert res.returncode == 0, res.stderr
    image = np.asarray(Image.open(tmp_path / "shape.png"))
    assert image.dtype == np.uint8 and image.shape == (64, 64)
    assert set(np.unique(image)) == {0, 255}
    assert np.array_equal(image == 255, render(program))  # rows and columns as in docs/domains.md

    res = run("execute", "csg2d", program, "-o", str(tmp_path / "shape.npy"))
    assert res.returncode == 0, res.stderr
    array = np.load(tmp_path / "shape.npy")
    assert array.dtype == bool and np.array_equal(array, render(program))


def test_execute_without_output_prints_the_shape_then_the_program():
    program = "c(32,24,16)s(40,40,12)+$"
    res = run("execute", "csg2d", program)
    assert res.returncode == 0, res.stderr
    *rows, text = res.stdout.splitlines()
    assert text == get_domain("csg2d").format(get_domain("csg2d").parse(program))
    assert np.array_equal(np.array([[c == "#" for c in row] for row in rows]), render(program))


@pytest.mark.parametrize("program, token", [
    ("c(32,24,16)s(40,40,12)x$", "x$"),
    ("c(32,24,16)+$", "'+'"),
    ("c(9,24,16)$", "c(9,24,16)"),
])
def test_execute_rejects_invalid_programs_with_status_2(tmp_path, program, token):
    res = run("execute", "csg2d", program, "-o", str(tmp_path / "x.png"))
    assert res.returncode == 2
    assert token in res.stderr and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x.png").exists()


def test_execute_rejects_an_unknown_output_type(tmp_path):
    res = run("execute", "csg2d", "c(32,32,16)$", "-o", str(tmp_path / "x.gif2"))
    assert res.returncode == 2 and "unsupported output type" in res.stderr


def test_score_single_png_pair(tmp_path):
    a, b = "c(32,32,16)$", "c(32,32,20)$"
    run("execute", "csg2d", a, "-o", str(tmp_path / "a.png"))
    run("execute", "csg2d", b, "-o", str(tmp_path / "b.png"))
    res = run("score", "csg2d", "--pred", str(tmp_path / "a.png"), "--target", str(tmp_path / "b.png"))
    assert res.returncode == 0, res.stderr
    lines = res.stdout.strip().splitlines()
    assert len(lines) == 2 and lines[1] == f"mean {lines[0]}"
    metric = get_domain("csg2d").metric
    want = metric(torch.from_numpy(render(a)[None]), torch.from_numpy(render(b)[None]))[0].item()
    assert float(lines[0]) == pytest.approx(want, abs=1e-6)
    assert want > 0


def test_score_npy_batch_prints_values_then_mean(tmp_path):
    domain = get_domain("csg2d")
    programs = domain.sample(5, np.random.default_rng(0))
    shapes = np.stack([render(domain.format(p)) for p in programs])
    pred = np.roll(shapes, 2, axis=2)
    np.save(tmp_path / "p.npy", pred)
    np.save(tmp_path / "t.npy", shapes.astype(np.uint8) * 255)  # numeric arrays: nonzero is inside
    res = run("score", "csg2d", "--pred", str(tmp_path / "p.npy"), "--target", str(tmp_path / "t.npy"))
    assert res.returncode == 0, res.stderr
    lines = res.stdout.strip().splitlines()
    assert len(lines) == 6 and lines[-1].startswith("mean ")
    values = np.array([float(v) for v in lines[:5]])
    want = domain.metric(torch.from_numpy(pred), torch.from_numpy(shapes)).numpy()
    assert np.allclose(values, want, atol=1e-6)
    assert float(lines[-1].split()[1]) == pytest.approx(want.mean(), abs=1e-6)


def test_score_reports_bad_files_in_one_line(tmp_path):
    np.save(tmp_path / "wrong.npy", np.zeros((3, 32, 32), bool))
    ok = np.zeros((3, 64, 64), bool)
    ok[:, 20:40, 20:40] = True   # an empty target is refused (plad.data.inputs): these targets are not empty
    np.save(tmp_path / "ok.npy", ok)
    (tmp_path / "junk.png").write_bytes(b"not a png")
    cases = [
        (tmp_path / "wrong.npy", "expected an array of shape"),
        (tmp_path / "missing.npy", "no such file"),
        (tmp_path / "junk.png", "not a readable image"),
    ]
    for path, phrase in cases:
        res = run("score", "csg2d", "--pred", str(path), "--target", str(tmp_path / "ok.npy"))
        assert res.returncode == 2 and phrase in res.stderr and str(path) in res.stderr
        assert "Traceback" not in res.stderr
    np.save(tmp_path / "two.npy", np.zeros((2, 64, 64), bool))
    res = run("score", "csg2d", "--pred", str(tmp_path / "two.npy"), "--target", str(tmp_path / "ok.npy"))
    assert res.returncode == 2 and "holds 2 shapes" in res.stderr


def test_data_check_reports_a_missing_dataset_in_one_line(tmp_path):
    res = run("data", "check", "--data-dir", str(tmp_path))
    assert res.returncode == 1
    assert str(tmp_path) in res.stderr and "Traceback" not in res.stderr
    # one line for each missing source: the CAD file and the PartNet programs
    assert len(res.stderr.strip().splitlines()) == 2


def test_help_lists_the_domains_and_one_line_per_command(monkeypatch, capsys):
    """`plad --help` (an 80-column terminal) names every domain and gives each command one line, as
    plad/serve/cli.py's docstring says; every command that docstring shows is listed."""
    import re

    from plad.domains import domain_names
    from plad.serve import cli

    monkeypatch.setenv("COLUMNS", "80")
    with pytest.raises(SystemExit) as exit_:
        cli.main(["--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    assert all(line == line.rstrip() and len(line) <= 80 for line in text.splitlines())
    assert f"DOMAIN is one of: {', '.join(domain_names())}." in " ".join(text.split())
    section = text.split("\ncommands:\n", 1)[1].split("\n\n", 1)[0].splitlines()
    assert section[0].strip() == "COMMAND"
    lines = section[1:]
    found = [re.match(r"^    (\S+)  +\S", line) for line in lines]
    assert all(found), lines   # a line that is not a command's: a help wrapped onto a second line
    commands = [m.group(1) for m in found]
    shown = set(re.findall(r"^    plad (\S+)", cli.__doc__, re.M))
    assert commands == ["execute", "export", "score", "data", "infer", "refine", "search", "models", "config"]
    assert shown <= set(commands) and len(lines) == len(commands)
