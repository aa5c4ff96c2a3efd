"""Nothing is lost (issue 30): `plad infer` gives every shape its own output names inside its run folder, and
`-o` never writes over an input and is checked before any work."""
from __future__ import annotations

import csv

import numpy as np
import pytest
from PIL import Image

from plad.serve.cli import main


@pytest.fixture(scope="module")
def model(tmp_path_factory, tiny_checkpoint):
    return tiny_checkpoint(tmp_path_factory.mktemp("model") / "csg2d.pt", "csg2d")


def square(offset: int = 0) -> np.ndarray:
    grid = np.zeros((64, 64), bool)
    grid[16 + offset:40 + offset, 20:44] = True
    return grid


def snapshot(root) -> dict:
    return {str(p): p.read_bytes() if p.is_file() else None for p in sorted(root.rglob("*"))}


def test_every_shape_gets_its_own_names_inside_the_run_folder(model, tmp_path, capsys):
    folder = tmp_path / "in"
    folder.mkdir()
    np.save(folder / "x.npy", np.stack([square(0), square(2)]))                  # shapes x_0 and x_1
    Image.fromarray(square(4).astype(np.uint8) * 255).save(folder / "x_0.png")    # its stem is x_0 too
    Image.fromarray(square(6).astype(np.uint8) * 255).save(folder / "part.left.png")
    Image.fromarray(square(8).astype(np.uint8) * 255).save(folder / "part.right.png")
    Image.fromarray(square(10).astype(np.uint8) * 255).save(folder / "..png", format="PNG")   # stem "."
    inputs = snapshot(folder)
    out = tmp_path / "out"
    assert main(["infer", "csg2d", str(folder), "--model", str(model), "--beam", "1", "--no-refine",
                 "--out", str(out)]) == 0
    assert snapshot(folder) == inputs                                             # inputs untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in", "out"]           # nothing beside the run
    (run,) = list(out.iterdir())
    with open(run / "results.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    names = [r["name"] for r in rows]
    assert len(set(names)) == len(rows) == 6
    assert sorted(names) == sorted(["shape", "part.left", "part.right", "x_0", "x_1", "x_0-2"])
    for r in rows:   # each row's input file holds its own shape
        assert (run / f"{r['name']}.txt").read_text().strip() == r["program"]
        assert (run / f"{r['name']}.svg").is_file()
    inputs_seen = [np.load(run / f"{n}.input.npy") for n in names]
    assert len({a.tobytes() for a in inputs_seen}) == 6
    assert "x_0.png (as x_0-2)" in capsys.readouterr().out


def test_search_never_writes_over_its_input_and_checks_o_first(tmp_path, capsys):
    victim = tmp_path / "victim.npy"
    np.save(victim, square())
    before = victim.read_bytes()
    (tmp_path / "folder").mkdir()
    search = ["search", "csg2d", str(victim)]
    refine = ["refine", "csg2d", "c(32,32,16)$", "--target", str(victim)]
    execute = ["execute", "csg2d", "c(32,32,16)$"]
    cases = [(str(victim), "cannot write (it is an input of this command, which is never written over)",
              [search, refine]),
             (str(tmp_path / "folder"), "cannot write (it is a folder; name a file)", [search, refine, execute]),
             ("/proc/self/x.txt", "/proc/self/x.txt: cannot write (", [search, refine, execute]),
             (str(tmp_path / "no" / "x.txt"), "cannot write (No such file or directory: no folder",
              [search, refine, execute])]
    for target, phrase, commands in cases:
        for command in commands:
            assert main([*command, "-o", target]) == 2, (command, target)
            captured = capsys.readouterr()
            assert captured.err.count("\n") == 1 and phrase in captured.err, captured.err
            assert captured.out == ""                                   # refused before any work
    assert victim.read_bytes() == before


def test_an_unwritable_out_is_refused_before_the_model_is_loaded(tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    np.save(tmp_path / "a.npy", square())
    assert main(["infer", "csg2d", str(tmp_path / "a.npy"), "--model", str(tmp_path / "missing.pt"),
                 "--out", str(tmp_path / "file" / "runs")]) == 2
    assert "is a file, not a folder" in capsys.readouterr().err


def test_a_run_without_one_usable_shape_leaves_no_run_folder(model, tmp_path, capsys):
    """As the README's Quick start run from an empty folder: the inputs are not there."""
    out = tmp_path / "out"
    assert main(["infer", "csg2d", str(tmp_path / "examples" / "csg2d"), "--model", str(model), "--out",
                 str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0].endswith("csg2d: no such file or folder") and "nothing was written" in err[-1]
    assert not out.exists()


def test_a_file_name_cannot_forge_a_line(model, tmp_path, capsys):
    folder = tmp_path / "in"
    folder.mkdir()
    np.save(folder / "a\nplad: error: forged.npy", square())
    assert main(["infer", "csg2d", str(folder), "--model", str(model), "--beam", "1", "--no-refine",
                 "--out", str(tmp_path / "out")]) == 0
    captured = capsys.readouterr()
    assert not any(line.startswith("plad: error: forged") for line in (captured.out + captured.err).splitlines())
    assert repr(str(folder / "a\nplad: error: forged.npy")) in captured.out
