"""The ``plad`` command line.

    plad execute DOMAIN PROGRAM [-o shape.png | shape.npy | shape.ply ...]
    plad export DOMAIN PROGRAM --format FORMAT [-o FILE]
    plad score DOMAIN --pred pred.npy --target target.npy
    plad data check | download
    plad infer DOMAIN drawing.png shapes/ --beam 10 --out inferred/ [--effort fast|default|best | --no-refine]
    plad refine DOMAIN PROGRAM --target shape.png -o refined.txt [--effort fast|default|best]
    plad search DOMAIN shape.npy [--effort fast|default|best] [--set insertions=8]
    plad models
    plad models ship DOMAIN CHECKPOINT --metrics results/eval/METHOD/DOMAIN/metrics.json
    plad config SECTION [--profile P] [--set KEY=VALUE]

DOMAIN is a registered domain (``plad --help`` lists them); PROGRAM is
program text or a ``.txt`` file holding it. What a domain offers (its output
types, its export formats) it declares itself (:class:`plad.domains.base.Domain`).
Errors are one line on stderr, never a traceback, with the exit status of
:mod:`plad.errors` (0 ok, 1 a failure of the run or its data, 2 bad usage or
input: the convention and its cases are written there). Every command reads
the user's shapes with the one reader of :mod:`plad.data.inputs`.

This module assembles the parser and runs a command; each command is in its own module, with its
arguments: ``plad.serve.cli_program`` (execute, export, score), ``cli_data``, ``cli_infer``,
``cli_search`` (refine, search), ``cli_models`` and ``show_config``; what they share is ``cli_common``.
"""
from __future__ import annotations

import argparse
import sys

# The parser, --help, argument errors, `plad models` and `plad data check` import neither
# torch, MLflow nor open3d (a test checks it): every command imports what it needs itself.
from plad.serve import cli_data, cli_infer, cli_models, cli_program, cli_search, show_config


def build_parser() -> argparse.ArgumentParser:
    from plad.domains import domain_names

    parser = argparse.ArgumentParser(
        prog="plad", description=f"Infer shape programs from shapes (PLAD). DOMAIN is one of: "
                                 f"{', '.join(domain_names())}. `plad COMMAND --help` gives a command's arguments.")
    # one line per command: each help fits a line of an 80-column terminal (tests/plad/serve/test_cli.py)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", title="commands")
    for command in (cli_program, cli_data, cli_infer, cli_search, cli_models, show_config):
        command.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from plad.errors import run_guarded

    def describe(err: Exception) -> str:
        # plad.domains.grammar is looked up among the loaded modules: importing it here would import torch, and
        # a command that never imported it cannot raise its ProgramError
        grammar = sys.modules.get("plad.domains.grammar")
        if grammar is not None and isinstance(err, grammar.ProgramError):
            return f"invalid {args.domain} program: {err}"
        return str(err)

    return run_guarded("plad", lambda: args.func(args), describe)


if __name__ == "__main__":
    sys.exit(main())
