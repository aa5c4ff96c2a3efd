"""``plad refine`` and ``plad search``: a program rewritten towards a target shape, programs searched from
scratch without a network (:mod:`plad.serve.cli`; the search itself is :mod:`plad.rewrite`'s)."""
from __future__ import annotations

import argparse
import sys
from typing import Any

from plad.errors import one_line
from plad.serve.cli_common import (
    UsageError,
    check_output,
    program_text,
    quoted,
    read_shapes,
    write_output,
)


def _search_setup(domain_name: str, overrides: list[str], effort: str | None = None):
    """(domain, search configuration at ``effort`` (None: the default level) with ``--set KEY=VALUE``
    overrides)."""
    import yaml

    from plad.config import ConfigError, safe_yaml
    from plad.domains import get_domain
    from plad.rewrite import search_config

    domain = get_domain(domain_name)
    if domain.rewrite is None:
        raise UsageError(f"the {domain_name} domain has no search support")
    values = {}
    for item in overrides:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"--set {item!r}: expected KEY=VALUE")
        try:
            values[key.strip()] = safe_yaml(text)
        except yaml.YAMLError:
            raise UsageError(f"--set {item!r}: value is not valid YAML") from None
        except (ValueError, RecursionError) as err:
            raise UsageError(f"--set {item!r}: refused: {one_line(err)}") from None
    if effort is not None:
        if "effort" in values and values["effort"] != effort:
            raise UsageError(f"--effort {effort} and --set effort={values['effort']}: give the effort once")
        values["effort"] = effort
    try:
        return domain, search_config(domain, **values)
    except ConfigError as err:
        raise UsageError(str(err)) from None


def cmd_refine(args: argparse.Namespace) -> int:
    """Rewrite a program towards a target shape; never returns a worse program."""
    import torch

    from plad.rewrite import refine
    from plad.rewrite.evaluate import Scorer

    domain, cfg = _search_setup(args.domain, args.set, args.effort)
    out = check_output(args.output, (args.program, args.target))
    ids = domain.parse(program_text(args.program))
    items = read_shapes(args.target, domain.shape)
    if len(items) != 1:
        raise UsageError(f"{quoted(args.target)} holds {len(items)} shapes; refine takes one target shape")
    if items[0].error:
        raise UsageError(f"{items[0].where}: {items[0].error}")
    for note in items[0].notes:
        print(f"{quoted(args.target)}: {note}", file=sys.stderr)
    target = torch.from_numpy(items[0].shape[None])
    before = float(Scorer(domain, target).values([ids])[0])
    result = refine(domain, [ids], target, cfg.refine)
    text = domain.format(result.programs[0])
    # the result first: a file that cannot be written (a full disk) is an error after it, never instead of it
    print(text)
    print(f"refined in {result.seconds:.1f} s", file=sys.stderr)
    print(f"{domain.metric.name} {before:.6f} -> {float(result.values[0]):.6f}", flush=True)
    if out is not None:
        write_output(out, text + "\n")
    return 0


def cmd_search(args: argparse.Namespace) -> int:
    """Search from scratch (no network) for programs of the shapes in a file; a bad shape of a batch is
    reported (its line in ``-o`` left empty) and the others searched."""
    import numpy as np
    import torch

    from plad.rewrite import search

    domain, cfg = _search_setup(args.domain, args.set, args.effort)
    out = check_output(args.output, (args.file,))
    items = read_shapes(args.file, domain.shape)
    good = [it for it in items if it.error is None]
    programs: dict[int, tuple[list[int], float]] = {}
    seconds = 0.0
    if good:
        result = search(domain, torch.from_numpy(np.stack([it.shape for it in good])), cfg)
        programs = {id(it): (ids, v) for it, ids, v in zip(good, result.programs, result.values.tolist())}
        seconds = result.seconds
    failed = 0
    lines = []
    for it in items:
        if it.error is None and not programs[id(it)][0]:
            it.error = "no program scores better than the empty one"
        if it.error:
            failed += 1
            print(f"plad: error: {it.where}: {it.error}", file=sys.stderr)
            lines.append("")
            continue
        for note in it.notes:
            print(f"{it.where}: {note}", file=sys.stderr)
        ids, value = programs[id(it)]
        lines.append(domain.format(ids))
        print(lines[-1])
        print(f"{domain.metric.name} {value:.6f}")
    if len(items) > 1:
        values = [programs[id(it)][1] for it in items if it.error is None]
        print(f"mean {np.mean(values):.6f}" if values else "mean nan")
    if out is not None:
        write_output(out, "\n".join(lines) + "\n")
    print(f"searched {len(good)} shape(s) in {seconds:.1f} s", file=sys.stderr)
    return 2 if failed else 0


def add_parser(sub: Any) -> None:
    """The ``refine`` and ``search`` commands of ``plad``."""
    from plad.domains import domain_names

    p = sub.add_parser("refine", help="rewrite a program towards a target shape",
                       description="Rewrite a program towards a target shape (search from the program).")
    p.add_argument("domain", choices=domain_names())
    p.add_argument("program", help="program text (or a .txt file holding it)")
    p.add_argument("--target", required=True, help="the target shape: .png or .npy, as for plad score")
    p.add_argument("-o", "--output", help="also write the refined program's text to this file")
    p.add_argument("--effort", default=None, metavar="LEVEL",
                   help="how hard to refine: fast, default or best, as `plad search` refines at that effort "
                        "level (2D CSG: the same at every level, whose levels differ in their beam; "
                        "docs/inference.md)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="search setting over the effort level's, e.g. refine.rounds=5 or refine.wide=false "
                        "(repeatable)")
    p.set_defaults(func=cmd_refine)

    p = sub.add_parser("search", help="search programs for shapes from scratch, no network",
                       description="Search for programs of shapes from scratch, without a network.")
    p.add_argument("domain", choices=domain_names())
    p.add_argument("file", help="target shape(s): .png or .npy (N, *shape), as for plad score")
    p.add_argument("-o", "--output", help="also write the programs, one per line, to this file")
    # not argparse choices: a bad value is the one-line error of the search configuration (exit status 2)
    p.add_argument("--effort", default=None, metavar="LEVEL",
                   help="how hard to search: fast, default or best (more time, better programs); what each "
                        "level means is the domain's (docs/inference.md)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="search setting over the effort level's, e.g. insertions=5 or refine.rounds=1 (repeatable)")
    p.set_defaults(func=cmd_search)
