"""`plad infer` loses nothing it computed (issue 53, reproductions 4 and 5): every result is printed as soon as
it is done, a shape whose files cannot be written keeps its program (printed, and in results.csv), a
results.csv that cannot be written is one line after every result, a run stopped midway keeps the rows of the
shapes done, and a file name that is not UTF-8 is escaped in results.csv (valid UTF-8) and quoted on the
terminal."""
from __future__ import annotations

import csv
import errno
import io
import os

import numpy as np
import pytest
from PIL import Image

from plad import fsutil
from plad.fsutil import WriteError
from plad.serve.cli import main


@pytest.fixture(scope="module")
def model(tmp_path_factory, tiny_checkpoint):
    return tiny_checkpoint(tmp_path_factory.mktemp("model") / "csg2d.pt", "csg2d")


def square(offset: int) -> np.ndarray:
    grid = np.zeros((64, 64), bool)
    grid[16 + offset:40 + offset, 20:44] = True
    return grid


@pytest.fixture
def inputs(tmp_path):
    folder = tmp_path / "in"
    folder.mkdir()
    for i, name in enumerate(["a", "b", "c"]):
        np.save(folder / f"{name}.npy", square(2 * i))
    return folder


def infer(model, folder, out, *extra):
    return main(["infer", "csg2d", str(folder), "--model", str(model), "--beam", "1", "--no-refine", "--out",
                 str(out), *extra])


def test_a_shape_whose_files_cannot_be_written_keeps_its_program(model, inputs, tmp_path, capsys, monkeypatch):
    import plad.serve.infer as infer_module

    real = infer_module.save_comparison

    def fails_for_b(panels, path, title=None):
        if path.name.startswith("b."):
            raise WriteError(path, OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)))
        return real(panels, path, title)
    monkeypatch.setattr(infer_module, "save_comparison", fails_for_b)
    assert infer(model, inputs, tmp_path / "out") == 2
    out, err = capsys.readouterr()
    assert [line.split(":")[0] for line in out.splitlines()] == [str(inputs / f"{n}.npy") for n in "abc"]
    (run,) = (tmp_path / "out").iterdir()
    assert f"plad: error: {inputs / 'b.npy'}: could not write its outputs (cannot write {run / 'b.png'}: No " \
           f"space left on device)" in err.splitlines()
    assert "3 of 3 shapes inferred in" in err and "(1 of them not all written)" in err
    assert (run / "b.txt").is_file() and not (run / "b.png").exists()        # what was written is kept
    with open(run / "results.csv", newline="") as fh:
        rows = {r["name"]: r for r in csv.DictReader(fh)}
    assert rows["b"]["status"] == "error" and rows["b"]["program"] and "could not write" in rows["b"]["notes"]
    assert rows["a"]["status"] == rows["c"]["status"] == "ok"


def test_a_full_disk_prints_every_program_then_one_line(model, inputs, tmp_path, capsys, monkeypatch):
    class Full(io.FileIO):
        def write(self, data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    monkeypatch.setattr(fsutil, "_open_temp", lambda fd: io.BufferedWriter(Full(fd, "wb")))
    out_dir = tmp_path / "out"
    assert infer(model, inputs, out_dir) == 2
    out, err = capsys.readouterr()
    assert len(out.splitlines()) == 3 and all("$" in line for line in out.splitlines())   # every program
    (run,) = out_dir.iterdir()
    assert list(run.iterdir()) == []                   # no 0-byte or truncated file, no temporary one
    last = err.strip().splitlines()[-1]
    assert last == f"plad: error: {run / 'results.csv'}: cannot write (No space left on device); the results " \
                   "are printed above"
    assert "Traceback" not in err


def test_a_run_stopped_midway_keeps_the_rows_of_the_shapes_done(model, inputs, tmp_path, monkeypatch):
    import plad.serve.infer as infer_module
    from plad.data.inputs import read_inputs
    from plad.domains import get_domain
    from plad.model.checkpoint import load_model

    real, calls = infer_module.infer_programs, []

    def interrupted(*args, **kw):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kw)
    monkeypatch.setattr(infer_module, "infer_programs", interrupted)
    net = load_model(model)[0]
    shown = []
    with pytest.raises(KeyboardInterrupt):
        infer_module.infer_items(net, get_domain("csg2d"), read_inputs([inputs], (64, 64)), 1, tmp_path / "run",
                                 batch_size=1, progress=False, on_result=shown.append)
    assert [r.item.name for r in shown] == ["a"]
    with open(tmp_path / "run" / "results.csv", newline="") as fh:
        assert [r["name"] for r in csv.DictReader(fh)] == ["a"]


def test_a_name_that_is_not_utf8_is_escaped_in_results_and_quoted_on_the_terminal(model, tmp_path, capsys):
    folder = tmp_path / "d"
    folder.mkdir()
    name = os.fsdecode(b"bad_\xff\xfe.png")
    Image.fromarray(square(0).astype(np.uint8) * 255).save(folder / name)
    assert infer(model, folder, tmp_path / "o") == 0
    out, err = capsys.readouterr()
    assert out.startswith(repr(str(folder / name)) + ": chamfer") and "Traceback" not in err
    (run,) = (tmp_path / "o").iterdir()
    text = (run / "results.csv").read_bytes().decode("utf-8")           # valid UTF-8
    assert "bad_\\xff\\xfe.png" in text and (run / "bad___.txt").is_file()
