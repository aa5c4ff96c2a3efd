"""One exit-code convention (plad.errors) and one-line errors for the tracebacks of issue 18; params ranges
and relations; the PartNet tarball's sha256."""
from __future__ import annotations

import gzip
import shutil
from pathlib import Path

import pytest

from plad.serve.cli import main
from tests.conftest import shared_dir

TARBALL = shared_dir() / "datasets" / "shapeassembly_partnet" / "partnet_programs.tar.gz"


def one_error_line(err: str, prefix: str) -> str:
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(prefix) and "Traceback" not in err, err
    return lines[0]


def test_execute_into_a_missing_folder_is_bad_input(capsys):
    assert main(["execute", "csg2d", "c(32,32,16)$", "-o", "/no/such/dir/x.png"]) == 2
    line = one_error_line(capsys.readouterr().err, "plad: error: /no/such/dir/x.png: cannot write")
    assert "No such file or directory" in line


def test_a_program_file_that_does_not_exist_is_file_not_found(tmp_path, capsys):
    for domain in ("shapeassembly", "csg3d", "csg2d"):
        missing = str(tmp_path / "programs" / "chair.txt")
        assert main(["execute", domain, missing]) == 2
        assert one_error_line(capsys.readouterr().err, "plad: error:") == f"plad: error: {missing}: file not found"


def test_exit_codes_follow_one_convention(tmp_path, capsys):
    from plad import errors

    assert (errors.OK, errors.FAILURE, errors.USAGE) == (0, 1, 2)
    assert main(["execute", "csg2d", "c(32,32,16)$"]) == errors.OK
    assert main(["execute", "csg2d", "c(32,32"]) == errors.USAGE                     # a bad program
    assert main(["data", "check", "--data-dir", str(tmp_path)]) == errors.FAILURE     # missing data
    with pytest.raises(SystemExit) as exit_:                                          # argparse: usage
        main(["execute", "csg4d", "x"])
    assert exit_.value.code == errors.USAGE
    capsys.readouterr()


def _params(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "params.yaml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("module, section, text, key", [
    ("synthesize", "synthesize.csg2d", "synthesize:\n  base: {train_programs: -5}\n  csg2d: {}\n",
     "synthesize.csg2d.train_programs = -5 must be positive"),
    ("synthesize", "synthesize.csg4d", "synthesize:\n  base: {}\n  csg4d: {}\n",
     "synthesize.csg4d.domain: unknown domain 'csg4d'"),
    ("prepare", "prepare", "domains: [csg2d, csg4d]\nprepare: {}\n", "prepare.domains: unknown domain 'csg4d'"),
    ("pretrain", "pretrain.csg2d", "pretrain:\n  base: {model: {d_model: 32, n_heads: 3}}\n  csg2d: {}\n",
     "pretrain.csg2d.model: d_model 32 must be divisible by n_heads 3"),
    ("pretrain", "pretrain.csg2d", "pretrain:\n  base: {train: {batch_size: 0}}\n  csg2d: {}\n",
     "pretrain.csg2d.train.batch_size = 0 must be positive"),
    ("finetune", "finetune.csg2d", "finetune:\n  base: {plad: {ws: {latent: 0}}}\n  csg2d: {}\n",
     "finetune.csg2d.plad.ws.latent = 0 must be positive"),
    ("evaluate", "evaluate.csg2d", "evaluate:\n  base: {beam: -1}\n  csg2d: {}\n",
     "evaluate.csg2d.beam = -1 must be a beam width from 1 to 100 (MAX_BEAM)"),
    ("evaluate", "evaluate.csg2d", "evaluate:\n  base: {beam: 1000000000}\n  csg2d: {}\n",
     "evaluate.csg2d.beam = 1000000000 must be a beam width from 1 to 100 (MAX_BEAM)"),
    ("evaluate", "evaluate.csg2d", "evaluate:\n  base: {device: tpu}\n  csg2d: {}\n",
     "evaluate.csg2d.device = 'tpu': use auto (CUDA when present), cpu, cuda or cuda:N"),
])
def test_params_ranges_and_relations_are_one_line_naming_the_key(tmp_path, capsys, module, section, text, key):
    import importlib

    stage = importlib.import_module(f"plad.stages.{module}")
    p = _params(tmp_path, text)
    assert stage.main(["--params", str(p), "--section", section, "--root", str(tmp_path / "out")]) == 1
    line = one_error_line(capsys.readouterr().err, f"{module}: error: {p}: ")
    assert key in line
    assert not (tmp_path / "out").exists()   # refused before anything was written


def test_the_partnet_tarball_is_checked_against_its_sha256(tmp_path):
    from plad.data.datasets.partnet.dataset import SOURCE_SHA256, find_source, load_split, read_source
    from plad.data.files import DataError

    folder = tmp_path / "shapeassembly_partnet"
    folder.mkdir()
    bad = folder / "partnet_programs.tar.gz"
    bad.write_bytes(gzip.compress(b"a swapped file"))
    with pytest.raises(DataError, match=r"sha256 mismatch: expected 957ace4785ff\.\.\., got .* \(not PartNet's "
                                        r"published file, or damaged\)"):
        find_source(tmp_path)
    with pytest.raises(DataError, match="sha256 mismatch"):
        load_split("val", tmp_path)
    bad.write_bytes(b"<html>")
    with pytest.raises(DataError, match="not gzip data"):
        find_source(tmp_path)
    if TARBALL.is_file():
        shutil.copy(TARBALL, bad)
        assert find_source(tmp_path) == bad
        import hashlib
        assert hashlib.sha256(bad.read_bytes()).hexdigest() == SOURCE_SHA256
    # a tarball without its split lists: a DataError naming the file, not a bare ValueError
    import io
    import tarfile
    other = tmp_path / "other.tar.gz"
    with tarfile.open(other, "w:gz") as tar:
        info = tarfile.TarInfo("programs/chair/1.txt")
        info.size = 1
        tar.addfile(info, io.BytesIO(b"x"))
    with pytest.raises(DataError, match="missing split lists"):
        read_source(other)
