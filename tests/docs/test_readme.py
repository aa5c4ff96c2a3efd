"""The README is what the project says it is: a short guide whose set-up commands are the ones CI runs,
whose sections (and the docs pages' sections) exist wherever the code cites them, whose fine-tuning
examples use real params keys, whose real-data table names every data file the datasets read, and
whose docs index lists every page of docs/."""
from __future__ import annotations

import re

from tests.conftest import REPO_ROOT as REPO

README = (REPO / "README.md").read_text()
DOCS = sorted((REPO / "docs").glob("*.md"))
MAX_LINES = 450


def headings(text: str) -> set[str]:
    """The Markdown headings of ``text`` (outside fenced code blocks)."""
    return {m.group(1).strip() for m in re.finditer(r"^#+ (.+)$", strip_code_blocks(text), re.M)}


def strip_code_blocks(text: str) -> str:
    return re.sub(r"^```.*?^```", "", text, flags=re.M | re.S)


def section(text: str, heading: str) -> str:
    """The body of the ``## heading`` section of ``text``, up to the next heading of that level."""
    start = text.index(f"\n## {heading}\n")
    end = text.find("\n## ", start + 1)
    return text[start:end if end >= 0 else len(text)]


def cites(cited: str, heads: set[str]) -> bool:
    """A cited section exists: a heading is the citation, or starts with it before a ':' or ' ('."""
    return any(h == cited or h.startswith(cited + ":") or h.startswith(cited + " (") for h in heads)


def test_the_readme_is_a_guide_of_at_most_450_lines():
    lines = README.count("\n") + (not README.endswith("\n"))
    assert lines <= MAX_LINES, f"README.md has {lines} lines; move detail into docs/ (at most {MAX_LINES})"


def test_the_set_up_commands_are_the_two_commands_ci_runs():
    blocks = re.findall(r"^```bash\n(.*?)^```", section(README, "Set up and test"), re.M | re.S)
    assert len(blocks) >= 2, "the set-up section lost its two commands"
    install, test = (b.strip() for b in blocks[:2])
    ci = (REPO / ".ci" / "run").read_text().splitlines()
    ran = [ci[i + 1].strip() for i, line in enumerate(ci) if re.match(r"# [12]\. ", line)]
    assert ran == [install, test]


def cited_sections(text: str) -> list[tuple[str, str]]:
    """(page, section) for every citation of a README or docs/ section: ``README, "Section"``,
    ``README: "Section"``, ``(docs/page.md, "Section")``, ```docs/page.md`` ("Section")``."""
    out = [("README.md", m.group(1))
           for m in re.finditer(r'(?<![\w/."])README(?:\.md)?`?\W{0,3}"([^"\n]+)"', text)]
    out += [(f"docs/{m.group(1)}", m.group(2))
            for m in re.finditer(r'(?<![\w/])docs/([\w-]+\.md)`?\W{0,3}"([^"\n]+)"', text)]
    return out


def test_cited_sections_exist():
    # pyproject.toml and .ci/run tie their comments to the README's set-up section
    for path in (REPO / "pyproject.toml", REPO / ".ci" / "run"):
        assert ("README.md", "Set up and test") in cited_sections(path.read_text()), path.name
    files = [REPO / "pyproject.toml", REPO / ".ci" / "run", REPO / "params.yaml", REPO / "dvc.yaml",
             REPO / ".gitignore", *(REPO / "profiles").glob("*.yaml"), *REPO.glob("*/README.md"), *DOCS,
             *(p for folder in ("plad", "flows", "bench", "tests") for p in (REPO / folder).rglob("*.py")
               if "tests/docs" not in p.as_posix())]
    missing, seen = [], 0
    for path in files:
        for page, cited in cited_sections(path.read_text()):
            seen += 1
            target = REPO / page
            if not target.is_file() or not cites(cited, headings(target.read_text())):
                missing.append(f"{path.relative_to(REPO)} cites {page}, \"{cited}\"")
    assert seen >= 10, "the citation pattern no longer finds the project's citations"
    assert not missing, "\n".join(missing)


def test_the_citation_check_sees_both_forms_and_tells_sections_apart():
    text = ('x (README, "Quick start") y README: "Set up and test" `docs/domains.md` ("Rendering") '
            '(docs/domains.md, "Metric") (EXAMPLES / "README.md").read_text()')
    assert cited_sections(text) == [("README.md", "Quick start"), ("README.md", "Set up and test"),
                                    ("docs/domains.md", "Rendering"), ("docs/domains.md", "Metric")]
    heads = {"Metric: Chamfer distance", "The warm runner (opt-in)", "Rendering"}
    assert cites("Metric", heads) and cites("The warm runner", heads) and cites("Rendering", heads)
    assert not cites("Metri", heads) and not cites("Render", heads)


def test_fine_tuning_overrides_in_the_readme_and_docs_are_keys_of_their_section():
    from plad.config import load_params, lookup

    params = load_params(REPO / "params.yaml")
    # the fine-tuning commands (their --set keys are all in params.yaml; other stages may also set
    # model fields that params.yaml leaves at their defaults)
    pattern = r"--section (finetune\.\S+)((?: --set \S+=\S+)+)"
    assert re.findall(pattern, README), "the README shows no fine-tuning command"
    found = [f for text in (README, *(p.read_text() for p in DOCS)) for f in re.findall(pattern, text)]
    for section_name, sets in found:
        block = lookup(params, section_name)
        for key in re.findall(r"--set (\S+?)=", sets):
            node = block
            for part in key.split("."):
                if part == "key" and node is block:
                    break   # the stage's own selector of a finetune.base.methods entry
                assert isinstance(node, dict) and part in node, f"--set {key}: not a key of {section_name}"
                node = node[part]


def test_the_real_data_table_names_every_source_file():
    from plad.data.datasets.cad import CAD
    from plad.data.datasets.partnet.source import FOLDER, SOURCE_NAME

    data = section(README, "The real data")
    assert f"{FOLDER}/{SOURCE_NAME}" in data
    assert all(c in data for c in CAD.candidates[:2])
    assert "plad data check" in data


def test_the_docs_index_lists_every_docs_page():
    index = section(README, "Documentation")
    listed = set(re.findall(r"\]\((docs/[\w-]+\.md)\)", index))
    pages = {f"docs/{p.name}" for p in DOCS}
    assert pages - listed == set(), f"pages missing from the README's docs index: {sorted(pages - listed)}"
