"""Params files that are not params (issue 30): a folder, random bytes, a YAML alias bomb, a device torch does
not know, a beam of a billion: each a one-line error of the stage (exit status 1) before any work, never a
traceback or a MemoryError."""
from __future__ import annotations

import shutil

import pytest

from plad.config import MAX_YAML_NODES, ConfigError, load_params, safe_yaml
from tests.conftest import REPO_ROOT


def bomb(levels: int = 6, width: int = 10) -> str:
    """A YAML document whose aliases expand to width ** levels values (a few hundred bytes)."""
    lines = [f"a0: &a0 [{', '.join(['x'] * width)}]"]
    for i in range(1, levels + 1):
        lines.append(f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * width)}]")
    return "\n".join(lines) + "\n"


def test_safe_yaml_counts_what_aliases_expand_to():
    assert safe_yaml("a: &x [1, 2]\nb: *x\n") == {"a": [1, 2], "b": [1, 2]}
    with pytest.raises(ValueError, match=f"expand to more than {MAX_YAML_NODES:,} values"):
        safe_yaml(bomb())
    with pytest.raises(ValueError, match="recursive"):
        safe_yaml("a: &x [1, *x]\n")


@pytest.fixture
def work(tmp_path):
    shutil.copy(REPO_ROOT / "params.yaml", tmp_path / "params.yaml")
    shutil.copytree(REPO_ROOT / "profiles", tmp_path / "profiles")
    return tmp_path


def one_line(capsys, prefix: str) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(prefix) and "Traceback" not in err, err
    return err


def test_an_alias_bomb_in_any_section_stops_every_stage_at_once(work, capsys):
    from plad.stages import prepare

    text = (work / "params.yaml").read_text()
    body = "".join(f"    {line}\n" for line in bomb(levels=9).splitlines())    # 10^9 values through anchors
    (work / "params.yaml").write_text(text.replace("evaluate:\n  base:\n", "evaluate:\n  base:\n    bomb:\n" + body))
    # prepare never reads evaluate: the file is refused as a whole, before anything is built
    assert prepare.main(["--params", str(work / "params.yaml"), "--root", str(work / "out")]) == 1
    assert "anchors and aliases expand to more than" in one_line(capsys, "prepare: error: ")
    assert not (work / "out").exists()


@pytest.mark.parametrize("make, phrase", [
    (lambda w: w / "profiles", "not a file"),
    (lambda w: (w / "bin.yaml").write_bytes(bytes(range(256)) * 4) and w / "bin.yaml", "not a text file"),
])
def test_a_folder_or_random_bytes_as_params(work, capsys, make, phrase):
    from plad.stages import evaluate

    path = make(work)
    with pytest.raises(ConfigError, match=phrase):
        load_params(path)
    assert evaluate.main(["--params", str(path), "--section", "evaluate.csg2d", "--root", str(work / "o")]) == 1
    assert phrase in one_line(capsys, "evaluate: error: ")


@pytest.mark.parametrize("item, phrase", [
    ("device=tpu", "device = 'tpu': use auto (CUDA when present), cpu, cuda or cuda:N"),
    ("beam=1000000000", "beam = 1000000000 must be a beam width from 1 to 100 (MAX_BEAM)"),
    ("refine_config.bogus=1", "unknown key(s) bogus"),
    ("refine_config.rounds=-1", "refine_config.rounds = -1 must be non-negative"),
])
def test_stage_overrides_are_checked_whatever_the_switches(work, capsys, item, phrase):
    from plad.stages import evaluate

    assert evaluate.main(["--params", str(work / "params.yaml"), "--section", "evaluate.csg2d", "--set", item,
                          "--root", str(work / "out")]) == 1
    assert phrase in one_line(capsys, "evaluate: error: ")
    assert not (work / "out").exists()
