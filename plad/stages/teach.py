"""Stage ``teach``: a network taught by search labels of the real shapes (beyond the paper, issue 58).

A thin shell around :func:`plad.learn.teach.teach` as one MLflow run (method ``taught``, a metric row per
epoch): reads ``teach.<domain>``, trains on ``data/labels/<domain>.npz`` and writes
``runs/finetune/<domain>/taught/`` (:mod:`plad.layout`).
"""
from __future__ import annotations

import sys
from dataclasses import asdict
from pathlib import Path

from plad.learn.teach import TAUGHT, TeachConfig
from plad.stages import StageContext, stage_main


def init_checkpoint(cfg: TeachConfig) -> Path:
    """The checkpoint teaching starts from (``init``): the shipped SP network ("pretrained"), a kept network
    (:data:`plad.shipped.KEPT_STARTS`: "search_seeded", or "taught", a taught network kept as it was shipped, which
    a longer run continues; each a file of its own so that shipping the taught network leaves the start as it
    was) or a path."""
    from plad.config import ConfigError
    from plad.shipped import KEPT_STARTS, kept_checkpoint, pretrained_checkpoint

    if cfg.init == "pretrained":
        return pretrained_checkpoint(cfg.domain)
    if cfg.init in KEPT_STARTS:
        return kept_checkpoint(cfg.domain, cfg.init)
    if cfg.init == "shipped":
        raise ConfigError(f"teach.{cfg.domain}.init = shipped: the shipped model may be this stage's own network "
                          "(`plad models ship`), so its start would change with its result; name "
                          "'taught', 'search_seeded', 'pretrained' or a checkpoint's path")
    return Path(cfg.init)


def _numbers(row: dict) -> dict[str, float]:
    """The finite numbers of a history row but its epoch."""
    import math

    numbers = {}
    for k, v in row.items():
        try:
            x = float(v)
        except (TypeError, ValueError):
            continue
        if math.isfinite(x) and k != "unit":
            numbers[k] = x
    return numbers


def tracked_teach(cfg: TeachConfig, ctx: StageContext = StageContext()) -> dict:
    import csv

    from plad.domains import get_domain
    from plad.layout import BEST, SUMMARY
    from plad.learn.teach import FIRST, HISTORY_FILE, teach
    from plad.tracking import StageRun

    out = ctx.layout.finetune_dir(cfg.domain, TAUGHT)
    out.mkdir(parents=True, exist_ok=True)
    with StageRun("teach", cfg.domain, asdict(cfg), out, method=TAUGHT, params_path=ctx.params) as run:
        def log(line: str) -> None:
            print(line, file=sys.stderr, flush=True)

        summary = teach(cfg, init_checkpoint(cfg), ctx.layout, log=log)
        # one curve: a first segment's epochs, then the second's after them (its epoch 0, the first's best, left out)
        first = summary.get("first")
        curves = [(out / FIRST / HISTORY_FILE, 0), (out / HISTORY_FILE, first["units"])] if first else \
            [(out / HISTORY_FILE, 0)]
        for path, offset in curves:
            with open(path, newline="") as fh:
                rows = list(csv.DictReader(fh))
            for row in rows:
                unit = int(float(row["unit"]))
                if not (offset and unit == 0):
                    run.log_metrics(_numbers(row), step=offset + unit)
        metric = get_domain(cfg.domain).metric
        run.log_result(metric=metric.name, higher_is_better=metric.higher_is_better, val=summary.get("val"),
                       train_seconds=summary.get("train_seconds"), stopped=summary["stopped"])
        for name in (SUMMARY, BEST, HISTORY_FILE):
            run.log_artifact(out / name)
    return summary


def main(argv: list[str] | None = None) -> int:
    return stage_main("teach", TeachConfig, tracked_teach, argv, __doc__.splitlines()[0])


if __name__ == "__main__":
    sys.exit(main())
