"""DVC stage entry points: each is a thin ``main()`` around a pure function.

Prefect flows (``flows/``) call the same functions, so each step has one
implementation. :func:`stage_main` is the shared command-line shell: read
the stage's params section, run, print the JSON result, and turn the errors
a user can fix into one line and exit status 1.
"""
from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from plad.layout import Layout

T = TypeVar("T")


@dataclass(frozen=True)
class StageContext:
    """What a stage run gets besides its config: where its files are, and the params file it was configured by."""

    layout: Layout = field(default_factory=Layout)
    #: recorded with the run (the MLflow tags of :func:`plad.tracking.pipeline_tags`)
    params: Path = Path("params.yaml")


def stage_main(stage: str, cls: type[T], run: Callable[[T, StageContext], Any], argv: list[str] | None = None,
               description: str | None = None) -> int:
    from plad.checkpoint import CheckpointError
    from plad.config import ConfigError, apply_overrides, build, load_params, lookup
    from plad.data import DataError

    parser = argparse.ArgumentParser(prog=f"python -m plad.stages.{stage}", description=description)
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--section", default=stage,
                        help="params section to read (default: the stage name; a domain's: e.g. pretrain.<domain>)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a key of the section (dotted for nested keys; value parsed as YAML)")
    parser.add_argument("--root", default=".",
                        help="root folder of the artifacts (plad.layout; default: the working directory)")
    args = parser.parse_args(argv)
    try:
        params = load_params(args.params)
        raw = apply_overrides(lookup(params, args.section), args.set, args.section)
        cfg = build(cls, raw, args.section, source=params.source(args.section))
        print(json.dumps(run(cfg, StageContext(Layout(args.root), Path(args.params)))))
    except (ConfigError, DataError, CheckpointError) as err:
        print(f"{stage}: error: {err}", file=sys.stderr)
        return 1
    return 0
