"""`plad config SECTION`: a stage's configuration, params section, profile and --set merged, as the stage builds
it (plad/serve/show_config.py)."""
from __future__ import annotations

import dataclasses

import pytest
import yaml

from plad.config import load_params, section, section_class
from plad.serve import cli
from tests.conftest import REPO_ROOT as REPO


@pytest.fixture
def project(tmp_path):
    (tmp_path / "profiles").mkdir()
    (tmp_path / "profiles" / "cpu.yaml").write_text("{}\n")
    (tmp_path / "profiles" / "smoke.yaml").write_text(
        "search_only:\n  base: {workers: 1}\n  csg2d: {limit: 5, search: {effort: fast}}\n")
    params = tmp_path / "params.yaml"
    params.write_text("profile: cpu\n"
                      "search_only:\n"
                      "  base:\n    splits: [test]\n    limit: null\n    workers: 2\n    search: {effort: default}\n"
                      "  csg2d: {limit: 50}\n"
                      "  csg3d: {}\n")
    return params


def plad(capsys, *args):
    status = cli.main(list(args))
    out, err = capsys.readouterr()
    return status, out, err


def test_base_domain_profile_and_set_merged_typed_as_yaml(project, capsys):
    status, out, err = plad(capsys, "config", "search_only.csg2d", "--params", str(project), "--profile", "smoke",
                            "--set", "search.refine.rounds=0")
    assert (status, err) == (0, "")
    assert out == (f"# search_only.csg2d as its stage builds it: {project} with {project.parent}/profiles/smoke.yaml, "
                   f"--set search.refine.rounds=0\n"
                   "domain: csg2d\n"
                   "splits: [test]\n"
                   "limit: 5\n"
                   "workers: 1\n"
                   "search:\n"
                   "  effort: fast\n"
                   "  refine:\n"
                   "    rounds: 0\n"
                   "effort_levels: []\n"
                   "effort_overrides: {}\n")
    # without --profile: the params file's own (cpu, which changes nothing); a domain's block over base
    status, out, _ = plad(capsys, "config", "search_only.csg2d", "--params", str(project))
    assert status == 0 and out.splitlines()[0] == f"# search_only.csg2d as its stage builds it: {project}"
    assert yaml.safe_load(out) == {"domain": "csg2d", "splits": ["test"], "limit": 50, "workers": 2,
                                   "search": {"effort": "default"}, "effort_levels": [], "effort_overrides": {}}


@pytest.mark.parametrize("name", ["finetune.csg3d", "pretrain.csg2d", "report"])
def test_the_repository_section_is_what_its_stage_builds(capsys, monkeypatch, name):
    monkeypatch.chdir(REPO)
    status, out, err = plad(capsys, "config", name, "--profile", "cpu")
    assert (status, err) == (0, "")
    built = section(load_params(REPO / "params.yaml", "cpu"), name, section_class(name.split(".")[0]))
    assert yaml.safe_load(out) == yaml.safe_load(yaml.safe_dump(dataclasses.asdict(built)))


@pytest.mark.parametrize("args, message", [
    (["nope"], "unknown section 'nope'; one of: prepare, synthesize.<domain>, pretrain.<domain>, "),
    (["search_only"], "search_only has one block per domain: name one, e.g. search_only.csg2d (csg2d, csg3d)"),
    (["search_only.csg9"], "search_only has no domain 'csg9': name one, e.g. search_only.csg2d (csg2d, csg3d)"),
    (["search_only.csg2d", "--profile", "gpu"], "--profile gpu: no such profile ("),
    (["search_only.csg2d", "--set", "beam=3"], "unknown key(s) beam in 'search_only.csg2d'"),
])
def test_an_unknown_section_profile_or_key_is_one_line(project, capsys, args, message):
    status, out, err = plad(capsys, "config", *args, "--params", str(project))
    assert out == "" and err.count("\n") == 1 and err.startswith("plad: error: ") and message in err, err
    assert status == (1 if "--set" in args else 2)     # a bad key is the params' error, as for a stage
    if "--profile" in args:
        assert err.rstrip().endswith("known: cpu, smoke")
