"""Links and code references in the README and docs/ point at things that exist: every relative link at a
file (and its #anchor at a heading of that file), every repository path at a file or folder, every
``plad.x.y`` name at a module or attribute of the package."""
from __future__ import annotations

import importlib
import re
from pathlib import Path

from tests.conftest import REPO_ROOT as REPO

PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md")), *sorted(REPO.glob("*/README.md"))]
ROOTS = ("plad", "tests", "bench", "flows", "docs", "profiles", "examples")


def strip_code_blocks(text: str) -> str:
    return re.sub(r"^```.*?^```", "", text, flags=re.M | re.S)


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation other than '-' and '_' dropped, spaces to '-'."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(text: str) -> set[str]:
    out, seen = set(), {}
    for m in re.finditer(r"^#+ (.+)$", strip_code_blocks(text), re.M):
        s = slug(m.group(1))
        out.add(s if s not in seen else f"{s}-{seen[s]}")   # GitHub numbers repeated headings
        seen[s] = seen.get(s, 0) + 1
    return out


def links(text: str) -> list[str]:
    """Targets of Markdown links and images outside code (fenced blocks and inline code)."""
    prose = re.sub(r"`[^`\n]*`", "", strip_code_blocks(text))
    return re.findall(r"!?\[[^\]]*\]\(([^)\s]+)\)", prose)


def broken_links(page: Path, root: Path = REPO) -> list[str]:
    out = []
    for target in links(page.read_text()):
        if re.match(r"[a-z]+:", target):   # https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            out.append(f"{page.relative_to(root)}: {target}: no such file")
        elif anchor and file.suffix == ".md" and anchor not in anchors(file.read_text()):
            out.append(f"{page.relative_to(root)}: {target}: no heading #{anchor} in {file.name}")
    return out


def test_every_relative_link_points_at_an_existing_file_and_heading():
    assert len(PAGES) > 5 and sum(len(links(p.read_text())) for p in PAGES) > 20
    broken = [b for page in PAGES for b in broken_links(page)]
    assert not broken, "\n".join(broken)


def test_the_link_check_finds_broken_links_and_anchors(tmp_path):
    (tmp_path / "a.md").write_text("# Title\n\n## The warm runner (opt-in)\n\n## Same\n\n## Same\n")
    page = tmp_path / "b.md"
    page.write_text("[ok](a.md#the-warm-runner-opt-in) [ok](a.md#same-1) [web](https://x.org/y) `[no](c.md)`\n"
                    "[gone](c.md) [bad](a.md#nothing) ![img](pic.png)\n```\n[code](d.md)\n```\n")
    assert broken_links(page, tmp_path) == ["b.md: c.md: no such file",
                                            "b.md: a.md#nothing: no heading #nothing in a.md",
                                            "b.md: pic.png: no such file"]


def repository_paths(text: str) -> set[str]:
    """Paths under the repository's folders (``plad/model/network.py``, ``tests/docs/``), templates
    such as ``plad/domains/<name>/`` and globs left out."""
    out = set()
    for m in re.finditer(rf"(?<![\w./-])(?:{'|'.join(ROOTS)})/[^\s`'\"()\[\],;:|]*", text):
        path = m.group(0).partition("#")[0].rstrip(".")   # a link's anchor is checked with the links
        if not re.search(r"[<>{}*$]", path):
            out.add(path)
    return out


def resolves(name: str) -> bool:
    """``plad.a.b.c`` is a module, or an attribute reached from the longest importable module prefix."""
    parts = name.split(".")
    for i in range(len(parts), 1, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def package_names(text: str) -> set[str]:
    """``plad.x...`` names whose first part is a module of the package (MLflow tags such as
    ``plad.method`` and params keys such as ``plad.max_rounds`` are not)."""
    names = set()
    for m in re.finditer(r"(?<![\w./-])plad(?:\.\w+)+", text):
        first = m.group(0).split(".")[1]
        if (REPO / "plad" / f"{first}.py").is_file() or (REPO / "plad" / first / "__init__.py").is_file():
            names.add(m.group(0))
    return names


def test_every_path_and_package_name_in_the_readme_and_docs_exists():
    missing = []
    for page in PAGES:
        text = page.read_text()
        missing += [f"{page.relative_to(REPO)}: {p}" for p in sorted(repository_paths(text))
                    if not (REPO / p).exists()]
        missing += [f"{page.relative_to(REPO)}: {n}" for n in sorted(package_names(text)) if not resolves(n)]
    assert not missing, "\n".join(missing)


def test_the_reference_check_tells_real_names_from_stale_ones():
    text = ("`plad/model/network.py` `plad/domains/<name>/` `plad/model/gone.py` `tests/docs/`. (docs/x.md#y) "
            "plad.model.checkpoint.load_model plad.model.nothing plad.method plad.max_rounds finetune.x.plad.y")
    assert repository_paths(text) == {"plad/model/network.py", "plad/model/gone.py", "tests/docs/", "docs/x.md"}
    assert package_names(text) == {"plad.model.checkpoint.load_model", "plad.model.nothing"}
    assert resolves("plad.model.checkpoint.load_model") and not resolves("plad.model.nothing")
