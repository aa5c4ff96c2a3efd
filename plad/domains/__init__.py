"""Registry of domain plugins.

Domains are imported lazily by name so that ``import plad`` and the CLI stay
fast and a broken optional domain cannot break the others. This module itself
imports neither torch nor a plugin: ``domain_names()`` (what ``plad --help``
and the CLI's argument checks need) costs nothing; :class:`Domain` (whose
module imports torch) is loaded on first access.
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from plad.domains.base import Domain

# name -> "module:attribute" of a Domain subclass
_REGISTRY: dict[str, str] = {
    "csg2d": "plad.domains.csg2d:CSG2D",
    "csg3d": "plad.domains.csg3d:CSG3D",
    "shapeassembly": "plad.domains.shapeassembly:ShapeAssembly",
}
_INSTANCES: dict[str, Domain] = {}


def register(name: str, target: str) -> None:
    """Register a domain plugin given as ``"package.module:ClassName"``."""
    _REGISTRY[name] = target
    _INSTANCES.pop(name, None)


def domain_names() -> list[str]:
    return sorted(_REGISTRY)


def plugin_module(name: str) -> str:
    """The module :func:`get_domain` imports for ``name`` (e.g. ``plad.domains.csg2d``)."""
    if name not in _REGISTRY:
        raise KeyError(f"unknown domain {name!r}; known domains: {', '.join(domain_names())}")
    return _REGISTRY[name].split(":")[0]


def get_domain(name: str) -> Domain:
    """The (cached) domain instance registered under ``name``."""
    if name not in _REGISTRY:
        raise KeyError(f"unknown domain {name!r}; known domains: {', '.join(domain_names())}")
    if name not in _INSTANCES:
        module, attr = _REGISTRY[name].split(":")
        _INSTANCES[name] = getattr(importlib.import_module(module), attr)()
    return _INSTANCES[name]


def __getattr__(name: str) -> Any:
    if name == "Domain":   # plad.domains.base imports torch: only when asked for
        from plad.domains.base import Domain

        return Domain
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["Domain", "domain_names", "get_domain", "plugin_module", "register"]
