"""DVC stage entry points: each is a thin ``main()`` around a pure function.

Prefect flows (``flows/``) call the same functions, so each step has one
implementation. :func:`stage_main` is the shared command-line shell: read
the stage's params section, run, print the JSON result, and turn the errors
a user can fix into one line and the exit status of :mod:`plad.errors` (1 for
a params, data or checkpoint problem).
"""
from __future__ import annotations

import argparse
import csv
import io
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from plad.fsutil import atomic_write_text
from plad.layout import Layout

T = TypeVar("T")


def write_programs_csv(path: str | Path, metric_name: str, index, values, texts) -> None:
    """``<split>_programs.csv`` of the evaluate and search_only stages, atomically: one row per shape with
    its index in the split, its metric value and its program text."""
    buf = io.StringIO()
    writer = csv.writer(buf)
    writer.writerow(["index", metric_name, "program"])
    for i, v, text in zip(list(index), values, texts):
        writer.writerow([int(i), f"{float(v):.6f}", text])
    atomic_write_text(path, buf.getvalue())


@dataclass(frozen=True)
class StageContext:
    """What a stage run gets besides its config: where its files are, and the params file it was configured by."""

    layout: Layout = field(default_factory=Layout)
    #: recorded with the run (the MLflow tags of :func:`plad.tracking.pipeline_tags`)
    params: Path = Path("params.yaml")


def stage_main(stage: str, cls: type[T], run: Callable[[T, StageContext], Any], argv: list[str] | None = None,
               description: str | None = None,
               options: Callable[[argparse.ArgumentParser], Callable[[T, argparse.Namespace], T]] | None = None
               ) -> int:
    """Run a stage from the command line. ``options`` may add a stage's own flags to the parser; it
    returns how the parsed flags change the built config."""
    from plad.config import apply_overrides, build, load_params, lookup
    from plad.errors import run_guarded

    parser = argparse.ArgumentParser(prog=f"python -m plad.stages.{stage}", description=description)
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--section", default=stage,
                        help="params section to read (default: the stage name; a domain's: e.g. pretrain.<domain>)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a key of the section (dotted for nested keys; value parsed as YAML)")
    parser.add_argument("--root", default=".",
                        help="root folder of the artifacts (plad.layout; default: the working directory)")
    configure = options(parser) if options is not None else None
    args = parser.parse_args(argv)

    def go() -> None:
        params = load_params(args.params)
        raw = apply_overrides(lookup(params, args.section), args.set, args.section)
        cfg = build(cls, raw, args.section, source=params.source(args.section))
        if configure is not None:
            cfg = configure(cfg, args)
        print(json.dumps(run(cfg, StageContext(Layout(args.root), Path(args.params)))))

    return run_guarded(stage, go)
