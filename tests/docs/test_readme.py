"""The README is what the project says it is: the README sections that pyproject.toml and .ci/run
cite exist, the fine-tuning examples use real params keys, and every data file the datasets read
is in the README's real-data table."""
from __future__ import annotations

import re

from tests.conftest import REPO_ROOT as REPO

README = (REPO / "README.md").read_text()
HEADINGS = {m.group(1).strip() for m in re.finditer(r"^#+ (.+)$", README, re.M)}


def test_cited_readme_sections_exist():
    for path in (REPO / "pyproject.toml", REPO / ".ci" / "run"):
        cited = re.findall(r'README[^"\n]*"([^"\n]+)"', path.read_text())
        assert cited, f"{path.name} cites no README section"
        missing = [c for c in cited if c not in HEADINGS]
        assert not missing, f"{path.name} cites README sections that do not exist: {missing}"


def test_fine_tuning_overrides_in_the_readme_are_keys_of_their_section():
    from plad.config import load_params, lookup

    params = load_params(REPO / "params.yaml")
    # the fine-tuning commands (their --set keys are all in params.yaml; other stages may also set
    # model fields that params.yaml leaves at their defaults)
    found = re.findall(r"--section (finetune\.\S+)((?: --set \S+=\S+)+)", README)
    assert found
    for section, sets in found:
        block = lookup(params, section)
        for key in re.findall(r"--set (\S+?)=", sets):
            node = block
            for part in key.split("."):
                if part == "key" and node is block:
                    break   # the stage's own selector of a finetune.base.methods entry
                assert isinstance(node, dict) and part in node, f"--set {key}: not a key of {section}"
                node = node[part]


def test_the_real_data_table_names_every_source_file():
    from plad.data.datasets.cad import CAD
    from plad.data.datasets.partnet.source import FOLDER, SOURCE_NAME

    section = README[README.index("## The real data"):README.index("## Pipeline")]
    assert f"{FOLDER}/{SOURCE_NAME}" in section
    assert all(c in section for c in CAD.candidates[:2])
    assert "plad data check" in section
