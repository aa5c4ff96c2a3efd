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
from typing import Any, TypeVar

T = TypeVar("T")


def stage_main(stage: str, cls: type[T], run: Callable[[T], Any], argv: list[str] | None = None,
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
    args = parser.parse_args(argv)
    try:
        params = load_params(args.params)
        raw = apply_overrides(lookup(params, args.section, args.params), args.set, args.section)
        cfg = build(cls, raw, args.section, source=args.params)
        print(json.dumps(run(cfg)))
    except (ConfigError, DataError, CheckpointError) as err:
        print(f"{stage}: error: {err}", file=sys.stderr)
        return 1
    return 0
