"""tests/README.md's rule for shared pieces: a test file never imports another test file (shared fixtures live
in a conftest.py, shared helpers in the modules at tests/), so running one file never runs another's imports
and a fixture is defined once."""
from __future__ import annotations

import ast

from tests.conftest import REPO_ROOT


def test_no_test_file_imports_another():
    offenders = []
    for path in sorted((REPO_ROOT / "tests").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            offenders += [f"{path.relative_to(REPO_ROOT)}: {n}" for n in names
                          if n.startswith("tests.") and n.rsplit(".", 1)[-1].startswith("test_")]
    assert offenders == []
