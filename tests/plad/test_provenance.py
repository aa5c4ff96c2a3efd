"""plad.provenance: the one home of the git state and the params hash that metrics files, shipped models'
sidecars and MLflow run folders record."""
from __future__ import annotations

import dataclasses
import shutil
import subprocess

import pytest

from plad.provenance import code_state, params_hash


def _git(cwd, *args):
    subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=cwd, check=True,
                   capture_output=True)


@pytest.mark.skipif(shutil.which("git") is None, reason="no git")
def test_code_state_is_dirty_for_code_and_params_not_for_results(tmp_path):
    def state(name):
        # code_state is cached per root (a process's code does not change under it): one copy per question
        root = tmp_path / name
        shutil.copytree(tmp_path / "repo", root, symlinks=True)
        return root

    repo = tmp_path / "repo"
    (repo / "plad").mkdir(parents=True)
    (repo / "results").mkdir()
    (repo / "plad" / "x.py").write_text("a = 1\n")
    (repo / "params.yaml").write_text("base: {}\n")
    (repo / "results" / "m.json").write_text("{}\n")
    _git(repo, "init", "-q")
    _git(repo, "add", "-A")
    _git(repo, "commit", "-q", "-m", "c")
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True).stdout.strip()

    assert code_state(str(state("clean"))) == {"commit": head, "dirty": False}
    results = state("results")
    (results / "results" / "m.json").write_text('{"a": 1}\n')      # a run's outputs: not the code
    assert code_state(str(results)) == {"commit": head, "dirty": False}
    params = state("params")
    (params / "params.yaml").write_text("base: {seed: 1}\n")
    assert code_state(str(params)) == {"commit": head, "dirty": True}
    untracked = state("untracked")
    (untracked / "plad" / "new.py").write_text("b = 2\n")        # a new module counts, untracked as it is
    assert code_state(str(untracked)) == {"commit": head, "dirty": True}

    outside = tmp_path / "outside"
    outside.mkdir()
    assert code_state(str(outside)) == {"commit": None, "dirty": None}


@dataclasses.dataclass
class _Cfg:
    domain: str = "csg2d"
    lr: float = 1e-3
    sizes: tuple = (1, 2)


def test_params_hash_is_of_the_values_whatever_holds_them():
    cfg = _Cfg()
    assert params_hash(cfg) == params_hash(dataclasses.asdict(cfg)) == params_hash({"sizes": (1, 2), "lr": 1e-3,
                                                                                     "domain": "csg2d"})
    assert params_hash(cfg) != params_hash(_Cfg(lr=2e-3))
    assert params_hash({"a": 1}) != params_hash({"a": "1"})     # typed: a string is not the number
    # the number committed metrics files carry for these params (canonical JSON: sorted keys, no spaces)
    assert params_hash({"a": 1}) == "015abd7f5cc57a2d"
