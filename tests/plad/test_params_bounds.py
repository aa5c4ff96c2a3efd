"""Bad params and profiles (issue 53, reproductions 7 and 9): every size a user can set has a bound
(plad.config.LIMITS), refused in one line before any work (a beam of 100,000,000, 10^20 synthetic programs,
1,000 threads); a key given twice in params.yaml or a profile is refused instead of the last one silently
winning (fuzzed over every key line of the real params.yaml); an empty ``--set`` value is no value."""
from __future__ import annotations

import re

import numpy as np
import pytest

from plad.config import LIMITS, ConfigError, _check_value, apply_overrides, load_params, safe_yaml
from tests.conftest import REPO_ROOT


@pytest.mark.parametrize("key", sorted(LIMITS))
def test_every_bounded_size_is_refused_past_its_limit_in_one_line(key):
    limit = LIMITS[key]
    _check_value(key, min(limit, 1), "section", "params.yaml")            # within: accepted
    for value in (int(limit) + 1, 99999999999999999999):
        with pytest.raises(ConfigError) as err:
            _check_value(key, value, "section", "params.yaml")
        assert str(err.value) == f"params.yaml: section.{key} = {value!r} is more than the limit of {limit:,} " \
                                 "(plad.config.LIMITS)"
    with pytest.raises(ConfigError):                                     # inside a list too (enc_channels)
        _check_value(key, [1, int(limit) + 1], "section", "params.yaml")


def test_the_commands_refuse_a_huge_size_before_any_work(tmp_path, capsys):
    from plad.serve.cli import main
    from plad.stages.synthesize import main as synthesize

    assert main(["search", "csg2d", str(REPO_ROOT / "examples/csg2d/house.png"), "--set", "beam_width=100000000"]) == 2
    assert capsys.readouterr().err == "plad: error: search configuration: search.beam_width = 100000000 is more " \
                                      "than the limit of 100 (plad.config.LIMITS)\n"
    params = tmp_path / "params.yaml"
    params.write_text("synthesize:\n  base: {train_programs: 10, val_programs: 5}\n  csg2d: {}\n")
    assert synthesize(["--params", str(params), "--section", "synthesize.csg2d", "--root", str(tmp_path / "r"),
                       "--set", "train_programs=99999999999999999999"]) == 1
    assert "train_programs = 99999999999999999999 is more than the limit" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


def _key_lines(text: str) -> list[int]:
    """Indices of the lines of a YAML file that start a mapping key (block style)."""
    return [i for i, line in enumerate(text.splitlines())
            if re.match(r"^\s*[A-Za-z_][\w.-]*\s*:(\s|$)", line) and not line.lstrip().startswith("#")]


def test_a_key_given_twice_anywhere_in_params_is_refused(tmp_path):
    text = (REPO_ROOT / "params.yaml").read_text()
    (tmp_path / "profiles").mkdir()
    for profile in (REPO_ROOT / "profiles").glob("*.yaml"):
        (tmp_path / "profiles" / profile.name).write_text(profile.read_text())
    lines = text.splitlines()
    rng = np.random.default_rng(9)
    picks = rng.choice(_key_lines(text), 12, replace=False)
    for i in [*picks.tolist(), next(i for i in _key_lines(text) if lines[i].startswith("profile:"))]:
        line = lines[i]
        if line.rstrip().endswith(":"):              # a block: give the key again as an empty mapping after it
            dup = lines[:i] + [line.split(":")[0] + ": {}"] + lines[i:]
        else:                                        # a value: the same line again
            dup = lines[:i + 1] + [line] + lines[i + 1:]
        path = tmp_path / "params.yaml"
        path.write_text("\n".join(dup) + "\n")
        key = line.split(":")[0].strip()
        with pytest.raises(ConfigError) as err:
            load_params(path)
        assert f"refused: the key '{key}' is given twice in one mapping" in str(err.value), (i, line)
        assert "\n" not in str(err.value)


def test_a_key_given_twice_in_a_profile_is_refused_and_anchors_still_merge(tmp_path):
    (tmp_path / "profiles").mkdir()
    (tmp_path / "profiles" / "dup.yaml").write_text("synthesize:\n  base: {seed: 1}\nsynthesize:\n  base: {seed: 2}\n")
    (tmp_path / "params.yaml").write_text("profile: dup\nsynthesize:\n  base: {seed: 0}\n  csg2d: {}\n")
    with pytest.raises(ConfigError, match=r"dup.yaml: refused: the key 'synthesize' is given twice .*lines 1 and 3"):
        load_params(tmp_path / "params.yaml")
    assert safe_yaml("a: &A {x: 1}\nb:\n  <<: *A\n  y: 2\n") == {"a": {"x": 1}, "b": {"x": 1, "y": 2}}
    assert safe_yaml("1: a\n'1': b\n") == {1: "a", "1": "b"}             # two keys: an int and a string


def test_an_empty_set_value_is_no_value():
    with pytest.raises(ConfigError, match=r"--set 'init=': no value; write init=null for none"):
        apply_overrides({}, ["init="], "pretrain.csg2d")
    assert apply_overrides({}, ["init=null"], "pretrain.csg2d") == {"init": None}
