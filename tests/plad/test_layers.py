"""The package's import graph: layers that import only downwards, and no import circle.

Every ``import`` counts, those inside functions and under ``TYPE_CHECKING`` too: a lazy import that
would close a circle hides the circle, it does not remove it.
"""
from __future__ import annotations

import ast
from pathlib import Path

from tests.conftest import REPO_ROOT

#: bottom to top; a module may import its own layer and the layers below it
LAYERS = [
    ("plad", "plad.errors", "plad.fsutil", "plad.layout", "plad.provenance"),
    ("plad.metrics",),
    ("plad.domains.grammar",),   # the token table: data, which the datasets' languages use too
    ("plad.data",),
    ("plad.domains",),
    ("plad.config", "plad.device"),   # configs name domains (and are checked against the registry)
    ("plad.model",),
    ("plad.rewrite",),
    ("plad.learn",),
    ("plad.tracking",),
    ("plad.eval",),
    ("plad.shipped",),
    ("plad.serve", "plad.stages"),
    ("plad.tools",),   # maintainers' measuring, plotting and building: nothing of the package imports them
]


def module_name(path: Path) -> str:
    parts = path.relative_to(REPO_ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports() -> dict[str, set[str]]:
    """module -> the plad modules it imports (``from plad.x import y`` counts as ``plad.x.y`` when that is a
    module, else ``plad.x``)."""
    files = {module_name(p): p for p in (REPO_ROOT / "plad").rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for mod, path in files.items():
        out = set()
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in files else node.module
                         for a in node.names]
            out |= {n for n in names if n == "plad" or n.startswith("plad.")}
        graph[mod] = out - {mod}
    return graph


def layer(mod: str) -> int:
    best = None
    for i, names in enumerate(LAYERS):
        for name in names:
            if (mod == name or mod.startswith(name + ".")) and (best is None or len(name) > len(best[1])):
                best = (i, name)
    assert best is not None, f"{mod} is in no layer of LAYERS"
    return best[0]


def test_every_module_is_in_a_layer_and_imports_no_layer_above_it():
    up = sorted(f"{mod} -> {dep}" for mod, deps in imports().items() for dep in deps if layer(dep) > layer(mod))
    assert up == []


def test_no_import_circle():
    graph = imports()
    state: dict[str, int] = {}   # 1: on the path, 2: done
    circles = []

    def visit(mod: str, path: list[str]) -> None:
        state[mod] = 1
        for dep in sorted(graph.get(mod, ())):
            if dep == "plad" or dep not in graph:
                continue   # the package's __init__ holds only the version
            if state.get(dep) == 1:
                circles.append(" -> ".join(path[path.index(dep):] + [dep]))
            elif dep not in state:
                visit(dep, path + [dep])
        state[mod] = 2

    for mod in sorted(graph):
        if mod not in state:
            visit(mod, [mod])
    assert circles == []


def test_at_most_twelve_modules_directly_in_the_package():
    assert len(list((REPO_ROOT / "plad").glob("*.py"))) <= 12
