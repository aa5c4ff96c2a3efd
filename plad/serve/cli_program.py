"""``plad execute``, ``plad export`` and ``plad score``: a program's shape, a program in another tool's format,
shapes scored against targets (:mod:`plad.serve.cli`)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from plad.serve.cli_common import UsageError, check_output, program_text, read_shapes


def cmd_execute(args: argparse.Namespace) -> int:
    from plad.domains import get_domain
    from plad.domains.grammar import ProgramError

    domain = get_domain(args.domain)
    check_output(args.output, (args.program,))
    text = program_text(args.program)
    try:
        shown = domain.execute_text(text, args.output)
    except ValueError as err:
        if isinstance(err, ProgramError):
            raise
        raise UsageError(str(err)) from None
    except OSError as err:
        raise UsageError(f"{args.output}: cannot write ({err.strerror or err.__class__.__name__})") from None
    # the shape itself goes to stdout when no file was asked for; otherwise stdout stays empty
    print(shown, file=sys.stdout if args.output is None else sys.stderr)
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    """A program in another tool's format: the writers of ``plad infer``'s files (:meth:`Domain.write_export`)."""
    import tempfile

    from plad.domains import get_domain
    from plad.domains.grammar import ProgramError
    from plad.fsutil import atomic_write

    domain = get_domain(args.domain)
    formats = domain.export_formats
    if not formats:
        raise UsageError(f"the {args.domain} domain has no export formats")
    if args.format not in formats:
        raise UsageError(f"unknown export format {args.format!r} for {args.domain}; known: {', '.join(formats)}")
    out = check_output(args.output, (args.program,))
    text = program_text(args.program)
    with tempfile.TemporaryDirectory(prefix="plad-export-") as tmp:
        path = Path(tmp) / f"program.{args.format}"
        try:
            written = domain.export_program(text, args.format, path)
        except ValueError as err:
            if isinstance(err, ProgramError):
                raise
            raise UsageError(str(err)) from None
        if not written:
            raise UsageError(f"the program has nothing to write as .{args.format} (it executes to an empty shape)")
        data = path.read_bytes()
    if out is not None:
        try:
            atomic_write(out, lambda fh: fh.write(data))
        except OSError as err:
            raise UsageError(f"{args.output}: cannot write ({err.strerror or err.__class__.__name__})") from None
        return 0
    try:
        sys.stdout.write(data.decode())
    except UnicodeDecodeError:   # a binary format (e.g. PLY)
        sys.stdout.flush()
        sys.stdout.buffer.write(data)
    return 0


def cmd_score(args: argparse.Namespace) -> int:
    """The domain metric of each prediction against its target; a pair that cannot be scored prints ``nan``
    with its error on stderr, and the mean is over the others (exit status 2)."""
    import numpy as np
    import torch

    from plad.domains import get_domain

    domain = get_domain(args.domain)
    targets = read_shapes(args.target, domain.shape)
    # each prediction is placed where its target went (same source size), so both are compared on one grid
    preds = read_shapes(args.pred, domain.shape, target=False, frames=[t.frame for t in targets])
    if len(preds) != len(targets):
        raise UsageError(f"{args.pred} holds {len(preds)} shapes but {args.target} holds {len(targets)}")
    ok = [i for i, (p, t) in enumerate(zip(preds, targets)) if p.error is None and t.error is None]
    values = np.full(len(targets), np.nan)
    if ok:
        pred = torch.from_numpy(np.stack([preds[i].shape for i in ok]))
        target = torch.from_numpy(np.stack([targets[i].shape for i in ok]))
        values[ok] = domain.metric(pred, target).numpy()
    for p, t, v in zip(preds, targets, values):
        for it, role in ((t, "target"), (p, "pred")):
            if it.error:
                print(f"plad: error: {role} {it.where}: {it.error}", file=sys.stderr)
        print(f"{v:.6f}")
    # for one shape too: scripts read the last line
    print(f"mean {values[ok].mean():.6f}" if ok else "mean nan")
    return 0 if len(ok) == len(targets) else 2


def add_parser(sub: Any) -> None:
    """The ``execute``, ``export`` and ``score`` commands of ``plad``."""
    from plad.domains import domain_names

    p = sub.add_parser("execute", help="execute a program and write the shape (PNG, NPY, mesh)",
                       description="Execute a program and write the shape (or print it).")
    p.add_argument("domain", choices=domain_names())
    p.add_argument("program", help="program text (or a .txt file holding it)")
    p.add_argument("-o", "--output", help="output file, its type by suffix: .npy (the bool grid) for every "
                   "domain; 2D: .png (255 inside, 0 outside); 3D: .ply/.obj (mesh) or .png (three views). "
                   "Without it a 2D shape is printed as text, a 3D one summarized")
    p.set_defaults(func=cmd_execute)

    p = sub.add_parser("export", help="write a program in another tool's format (.scad)",
                       description="Write a program in another tool's format (e.g. OpenSCAD .scad), for the "
                                   "domains that offer one.")
    p.add_argument("domain", choices=domain_names())
    p.add_argument("program", help="program text (or a .txt file holding it)")
    p.add_argument("--format", required=True, help="output format, e.g. scad")
    p.add_argument("-o", "--output", help="output file (default: standard output)")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("score", help="score predicted shapes against targets",
                       description="Score predicted shapes against targets with the domain metric.")
    p.add_argument("domain", choices=domain_names())
    p.add_argument("--pred", required=True, help=".png or .npy (N, *shape)")
    p.add_argument("--target", required=True, help=".png or .npy (N, *shape)")
    p.set_defaults(func=cmd_score)
