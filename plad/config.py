"""Typed configuration from ``params.yaml``.

Each component has a dataclass; its section of ``params.yaml`` is named after
the DVC stage that uses it. Unknown keys are errors (a typo must not silently
fall back to a default), and so are values of the wrong type.
"""
from __future__ import annotations

import dataclasses
import os
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

T = TypeVar("T")


class ConfigError(ValueError):
    """A params file problem; the message is one line naming the file and key."""


#: Top-level keys a params file may have: ``profile`` and one section per stage.
SECTIONS = {"profile", "domains", "methods", "prepare", "synthesize", "pretrain", "evaluate", "finetune", "report",
            "flows"}


def load_params(path: str | os.PathLike = "params.yaml") -> dict[str, Any]:
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"{path}: no such params file")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML ({' '.join(str(err).split())})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of sections at the top level")
    unknown = sorted(set(data) - SECTIONS)
    if unknown:
        raise ConfigError(f"{path}: unknown section(s) {', '.join(unknown)}; allowed: {', '.join(sorted(SECTIONS))}")
    return data


def _check_type(value: Any, annotation: Any) -> bool:
    origin = typing.get_origin(annotation)
    if annotation is Any:
        return True
    if origin in (typing.Union, types.UnionType):
        return any(_check_type(value, a) for a in typing.get_args(annotation))
    if annotation is type(None):
        return value is None
    if origin in (list, tuple):
        (inner, *_) = typing.get_args(annotation) or (Any,)
        return isinstance(value, (list, tuple)) and all(_check_type(v, inner) for v in value)
    if origin is dict:
        return isinstance(value, dict)
    if annotation is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if annotation is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, annotation)


def build(cls: type[T], raw: Any, where: str, source: str = "params.yaml") -> T:
    """Build dataclass ``cls`` from a mapping; nested dataclass fields are built recursively.

    Unknown keys and wrongly typed values raise :class:`ConfigError` naming ``source`` and the key.
    """
    raw = {} if raw is None else raw
    if not isinstance(raw, dict):
        raise ConfigError(f"{source}: {where} must be a mapping, got {raw!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(raw) - fields)
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {', '.join(unknown)} in {where!r}; "
                          f"allowed: {', '.join(sorted(fields))}")
    values = {}
    for key, value in raw.items():
        hint = hints[key]
        if dataclasses.is_dataclass(hint):
            values[key] = build(hint, value, f"{where}.{key}", source)
            continue
        if typing.get_origin(hint) is dict and dataclasses.is_dataclass(typing.get_args(hint)[-1]):
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: {where}.{key} must be a mapping, got {value!r}")
            inner = typing.get_args(hint)[-1]
            values[key] = {str(k): build(inner, v, f"{where}.{key}.{k}", source) for k, v in value.items()}
            continue
        if not _check_type(value, hint):
            raise ConfigError(f"{source}: {where}.{key} = {value!r} should be of type "
                              f"{getattr(hint, '__name__', hint)}")
        values[key] = value
    # keys without a default (e.g. a stage's domain) must be given; checked after the given keys,
    # since a typo in those is the likelier mistake
    missing = [f.name for f in dataclasses.fields(cls)  # type: ignore[arg-type]
               if f.name not in raw and f.default is dataclasses.MISSING
               and f.default_factory is dataclasses.MISSING]
    if missing:
        raise ConfigError(f"{source}: missing key(s) {', '.join(missing)} in {where!r}")
    return cls(**values)


def lookup(params: dict[str, Any], name: str, source: str = "params.yaml") -> Any:
    """``params["pretrain"]["<domain>"]`` for ``name = "pretrain.<domain>"``; a missing part is an error."""
    node: Any = params
    for i, part in enumerate(name.split(".")):
        if not isinstance(node, dict) or part not in node:
            where = ".".join(name.split(".")[:i + 1])
            raise ConfigError(f"{source}: section {where!r} is missing")
        node = node[part]
    return node


def section(params: dict[str, Any], name: str, cls: type[T], source: str = "params.yaml") -> T:
    """Build ``cls`` from the section ``name`` (dotted for a domain's subsection, e.g. ``pretrain.<domain>``)."""
    return build(cls, lookup(params, name, source), name, source)


def apply_overrides(raw: dict[str, Any], overrides: list[str], where: str) -> dict[str, Any]:
    """``["a.b=3", "c=x"]`` applied to a copy of section ``raw``; values are parsed as YAML.

    Keys are checked later by :func:`build`, so a typo is still an error.
    """
    import copy

    out = copy.deepcopy(raw) if raw is not None else {}
    for item in overrides:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
        parts = key.strip().split(".")
        node = out
        for p in parts[:-1]:
            if not isinstance(node.get(p), dict):
                node[p] = {}
            node = node[p]
        try:
            node[parts[-1]] = yaml.safe_load(text) if text.strip() else None
        except yaml.YAMLError:
            raise ConfigError(f"--set {item!r}: value is not valid YAML") from None
    return out
