"""The plugin boundary: a domain is a package plad/domains/<name>/ that no other code names or imports.

Everything specific to a domain sits behind plad.domains.base.Domain; the
registry (plad/domains/__init__.py) is the one place that lists the domains.
"""
import re
from pathlib import Path

from plad.domains import _REGISTRY, domain_names
from tests.conftest import REPO_ROOT
from tests.imports import imported_modules

PLAD = REPO_ROOT / "plad"
DOMAINS_DIR = PLAD / "domains"


def package_of(path: Path) -> str:
    return ".".join(path.relative_to(PLAD.parent).parts[:-1])


def test_every_registered_domain_is_a_plugin_package():
    for name in domain_names():
        module = _REGISTRY[name].split(":")[0]
        assert module == f"plad.domains.{name}", module
        assert (DOMAINS_DIR / name / "__init__.py").is_file()


def test_no_plugin_imports_another():
    names = domain_names()
    for name in names:
        for path in sorted((DOMAINS_DIR / name).rglob("*.py")):
            others = {m for m in imported_modules(path.read_text(), package_of(path)) for other in names
                      if other != name and (m == f"plad.domains.{other}" or m.startswith(f"plad.domains.{other}."))}
            assert not others, f"{path.relative_to(PLAD.parent)} imports {sorted(others)}"


def test_the_import_check_sees_absolute_relative_and_nested_imports():
    source = ("import plad.domains.b.tokens\nfrom ..c import executor\nfrom . import sampler\n"
              "def f():\n    from plad.domains import d\n")
    got = imported_modules(source, "plad.domains.a")
    assert {"plad.domains.b.tokens", "plad.domains.c", "plad.domains.c.executor", "plad.domains.a.sampler",
            "plad.domains.d"} <= got


def test_no_module_outside_the_plugins_names_a_domain():
    # a domain's name as a word, e.g. in a string, an identifier or a docstring; the registry is the
    # exception. Citations of spec and docs pages (``specs/<name>.md``, ``docs/<name>.md``) are document names.
    word = re.compile(r"\b(" + "|".join(map(re.escape, domain_names())) + r")\b")
    spec = re.compile(r"(specs|docs)/[\w-]+\.md")
    plugins = [DOMAINS_DIR / name for name in domain_names()]
    found = []
    for path in sorted(PLAD.rglob("*.py")):
        if path == DOMAINS_DIR / "__init__.py" or any(p in path.parents for p in plugins):
            continue
        for i, line in enumerate(path.read_text().splitlines(), 1):
            if word.search(spec.sub("", line)):
                found.append(f"{path.relative_to(PLAD.parent)}:{i}: {line.strip()}")
    assert not found, "\n".join(found)
