"""Stage ``prepare``: the real target shapes S* of every domain, verified and written compactly.

Each domain names where its real shapes come from (its target source,
:attr:`plad.domains.base.Domain.targets`). Every source of the configured
domains is prepared once from the data directory (a published file is
checked against its sha256; PartNet's programs are executed and voxelized,
with a report and a failures log, see :mod:`plad.data.datasets.partnet.dataset`),
and its splits are written as ``data/prepared/<domain>.npz`` (bit-packed) plus
``data/prepared/<domain>.json`` (counts and occupancy) for every domain on it
(:mod:`plad.layout`), atomically (:func:`plad.data.files.write_prepared`).
"""
from __future__ import annotations

import sys
from dataclasses import dataclass, field, replace

from plad.layout import Layout
from plad.stages import stage_main


@dataclass
class PrepareConfig:
    #: domains whose real shapes are prepared
    domains: list[str] = field(kw_only=True)
    #: directory holding the datasets; null means $PLAD_DATA_DIR, else ./data/datasets
    data_dir: str | None = None
    #: target source name -> keep only the first N shapes of each split (smoke runs); a source not named: all
    limit: dict[str, int] = field(default_factory=dict)


def target_groups(domains: list[str]) -> dict[str, list[str]]:
    """Target source name -> the given domains on it, in the order given."""
    from plad.domains import get_domain

    groups: dict[str, list[str]] = {}
    for name in domains:
        groups.setdefault(get_domain(name).targets.name, []).append(name)
    return groups


def prepare(cfg: PrepareConfig, layout: Layout = Layout()) -> dict[str, dict]:
    """Prepare each target source of ``cfg.domains`` once and write its splits for every domain on it.

    Returns ``{"domains": {domain: summary}, "sources": {source: report}}``.
    """
    from plad.config import ConfigError
    from plad.data.files import DataError, write_prepared
    from plad.domains import get_domain

    groups = target_groups(cfg.domains)
    for source, n in cfg.limit.items():
        if source not in groups:
            raise ConfigError(f"prepare.limit: {source!r} is not the target source of a configured domain "
                              f"(sources: {', '.join(groups)})")
        if not isinstance(n, int) or isinstance(n, bool) or n < 0:
            raise ConfigError(f"prepare.limit.{source} = {n!r} should be a non-negative integer")
    out: dict[str, dict] = {"domains": {}, "sources": {}}
    for source_name, names in groups.items():
        domains = [get_domain(name) for name in names]
        prepared = domains[0].targets.prepare(cfg.data_dir, layout.prepared_dir, cfg.limit.get(source_name))
        for domain in domains:
            got = prepared.splits["train"].shape[1:]
            if tuple(domain.shape) != got:
                raise DataError(layout.prepared_dir, f"domain {domain.name} works on {domain.shape}, its target "
                                                     f"source {source_name} gives {got}")
            out["domains"][domain.name] = write_prepared(
                domain.name, tuple(domain.shape), prepared.splits, layout.prepared(domain.name),
                layout.prepared_summary(domain.name), prepared.provenance)
        out["sources"][source_name] = prepared.report
    return out


def prepare_sources(cfg: PrepareConfig) -> list[PrepareConfig]:
    """``cfg`` split by target source: each part prepares one source (e.g. a parallel task each)."""
    return [replace(cfg, domains=names, limit={k: v for k, v in cfg.limit.items() if k == source})
            for source, names in target_groups(cfg.domains).items()]


def main(argv: list[str] | None = None) -> int:
    return stage_main("prepare", PrepareConfig, lambda cfg, ctx: prepare(cfg, ctx.layout), argv,
                      __doc__.splitlines()[0])

if __name__ == "__main__":
    sys.exit(main())
