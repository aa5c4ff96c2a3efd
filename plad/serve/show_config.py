"""``plad config SECTION [--profile P] [--set KEY=VALUE]``: a stage's configuration as the stage builds it.

The section of the params file (``pretrain.<domain>``: the ``base`` block merged with the domain's block), the
profile's override file on top (its base block, then its domain block; ``--profile`` in place of the file's
``profile`` key, as ``dvc exp run -S profile=...`` would), then the ``--set`` overrides, built into the
stage's config class (:data:`plad.config.SECTION_CLASSES`: every key typed and checked, the defaults filled
in) and printed as YAML: what ``python -m plad.stages.<stage> --section SECTION`` runs with, the same
functions doing each step (:func:`plad.stages.stage_main`).
"""
from __future__ import annotations

import argparse
import dataclasses
from typing import Any

from plad.errors import BadInput


class SectionError(BadInput):
    """A section or profile named on the command line that the params file does not have (exit status 2)."""


def _plain(value: Any) -> Any:
    """A built config as YAML's plain types (tuples as lists)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _names() -> str:
    from plad.config import PER_DOMAIN, STAGE_SECTIONS

    return ", ".join(f"{n}.<domain>" if n in PER_DOMAIN else n for n in STAGE_SECTIONS)


def resolved_config(name: str, params_path: str = "params.yaml", profile: str | None = None,
                    overrides: list[str] | tuple[str, ...] = ()) -> tuple[dict[str, Any], str]:
    """(the built config of section ``name`` as plain data, what it was built from: the params file, the
    profile's file where that changes the section)."""
    from pathlib import Path

    from plad.config import (
        PER_DOMAIN,
        STAGE_SECTIONS,
        apply_overrides,
        build,
        load_params,
        profile_path,
        section_class,
    )

    parts = name.split(".")
    top = parts[0]
    if top not in STAGE_SECTIONS or len(parts) > (2 if top in PER_DOMAIN else 1):
        raise SectionError(f"unknown section {name!r}; one of: {_names()}")
    if profile is not None and not profile_path(params_path, profile).is_file():
        folder = profile_path(params_path, "x").parent
        known = sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []
        raise SectionError(f"--profile {profile}: no such profile ({folder / (profile + '.yaml')}); "
                           f"known: {', '.join(known) or 'none'}")
    params = load_params(Path(params_path), profile)
    if top in PER_DOMAIN:
        domains = [d for d in params.get(top) or {}]
        if len(parts) == 1 or parts[1] not in domains:
            what = f"{top} has one block per domain" if len(parts) == 1 else f"{top} has no domain {parts[1]!r}"
            raise SectionError(f"{what}: name one, e.g. {top}.{domains[0] if domains else '<domain>'} "
                               f"({', '.join(domains) or 'none in the file'})")
    elif top not in params:
        raise SectionError(f"{params_path}: has no section {top!r}")
    source = params.source(name)
    raw = apply_overrides(params[top][parts[1]] if len(parts) == 2 else params[top], list(overrides), name)
    cfg = build(section_class(top), raw, name, source=source)
    return _plain(dataclasses.asdict(cfg)), source


def _dumper() -> type:
    """YAML in block style, but a list of plain values on one line (``enc_channels: [4, 8, 16, 32]``), as
    params.yaml writes them."""
    import yaml

    class Dumper(yaml.SafeDumper):
        pass

    def represent_list(dumper: yaml.SafeDumper, data: list) -> yaml.Node:
        flat = all(not isinstance(v, (dict, list)) for v in data)
        return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flat)

    Dumper.add_representer(list, represent_list)
    return Dumper


def render(name: str, params_path: str = "params.yaml", profile: str | None = None,
           overrides: list[str] | tuple[str, ...] = ()) -> str:
    """The YAML ``plad config`` prints: a comment line saying what was merged, then the config."""
    import yaml

    config, source = resolved_config(name, params_path, profile, overrides)
    head = f"# {name} as its stage builds it: {source}" + (f", --set {' '.join(overrides)}" if overrides else "")
    return head + "\n" + yaml.dump(config, Dumper=_dumper(), sort_keys=False, default_flow_style=False)


def cmd_config(args: argparse.Namespace) -> int:
    print(render(args.section, args.params, args.profile, args.set), end="")
    return 0


def add_parser(sub: Any) -> None:
    """The ``config`` command of ``plad`` (:mod:`plad.serve.cli`)."""
    p = sub.add_parser("config", help="print a stage's config, params and profile merged",
                       description="Print a stage's configuration as the stage builds it: the params section "
                                   "(base merged with the domain's block), the profile's overrides, then --set, "
                                   "typed and with the defaults filled in, as YAML.")
    p.add_argument("section", help="a section of the params file: prepare, report, flows, or a per-domain one "
                                   "with its domain, e.g. finetune.<domain>")
    p.add_argument("--profile", default=None,
                   help="apply this profile (profiles/PROFILE.yaml) instead of the params file's `profile`")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a key of the section, as a stage's --set does (dotted, YAML value; repeatable)")
    p.add_argument("--params", default="params.yaml", help="params file (default params.yaml)")
    p.set_defaults(func=cmd_config)
