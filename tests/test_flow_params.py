"""Which params file a flow run reads: a named profile or a path."""
import pytest

from flows.finetune import params_file
from plad.config import ConfigError
from tests.procs import REPO_ROOT


def test_a_profile_names_its_file_in_the_repository(monkeypatch):
    monkeypatch.chdir(REPO_ROOT)   # where a deployment's pull step puts a run
    assert params_file("params.yaml", None) == "params.yaml"
    assert params_file("other.yaml", "paper") == "profiles/paper.yaml"
    with pytest.raises(ConfigError, match=r"^profile 'gpu': no such file profiles/gpu.yaml "
                                          r"\(profiles: cpu, paper, smoke\)$"):
        params_file("params.yaml", "gpu")
