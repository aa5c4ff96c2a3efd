"""The ``plad`` command line.

    plad execute DOMAIN PROGRAM [-o shape.png | shape.npy | shape.ply ...]
    plad export DOMAIN PROGRAM --format FORMAT [-o FILE]
    plad score DOMAIN --pred pred.npy --target target.npy
    plad data check | download
    plad infer DOMAIN drawing.png shapes/ --beam 10 --out inferred/
    plad refine DOMAIN PROGRAM --target shape.png -o refined.txt
    plad search DOMAIN shape.npy --set insertions=8
    plad models

DOMAIN is a registered domain (``plad --help`` lists them); PROGRAM is
program text or a ``.txt`` file holding it. What a domain offers (its output
types, its export formats) it declares itself (:class:`plad.domains.base.Domain`).
Errors are one line on stderr, never a traceback, with the exit status of
:mod:`plad.errors`: 0 ok, 1 a failure of the run or its data (a missing
dataset or model store), 2 bad usage or input (an argument, a program, an
input file).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from plad.errors import BadInput


class UsageError(BadInput):
    """A problem with the user's input; printed as one line, exit status 2 (:mod:`plad.errors`)."""


# ---- shape files -------------------------------------------------------------------
def load_shapes(path: Path, shape: tuple[int, ...], targets: bool = True) -> np.ndarray:
    """Shapes for scoring or search, checked at the edge by :func:`plad.inputs.read_shapes`; bool (N, *shape).

    ``targets``: the empty-shape rule applies (a prediction may be empty).
    """
    from plad.inputs import InputError, read_shapes

    try:
        return read_shapes(path, tuple(shape), targets=targets)
    except InputError as err:
        raise UsageError(f"{path}: {err}") from None


# ---- commands --------------------------------------------------------------------------
def cmd_execute(args: argparse.Namespace) -> int:
    from plad.domains import get_domain
    from plad.grammar import ProgramError

    domain = get_domain(args.domain)
    text = _program_text(args.program)
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
    from plad.domains import get_domain
    from plad.grammar import ProgramError

    domain = get_domain(args.domain)
    formats = domain.export_formats
    if not formats:
        raise UsageError(f"the {args.domain} domain has no export formats")
    if args.format not in formats:
        raise UsageError(f"unknown export format {args.format!r} for {args.domain}; known: {', '.join(formats)}")
    try:
        out = domain.export_text(_program_text(args.program), args.format)
    except ValueError as err:
        if isinstance(err, ProgramError):
            raise
        raise UsageError(str(err)) from None
    if args.output:
        try:
            Path(args.output).write_text(out)
        except OSError as err:
            raise UsageError(f"{args.output}: cannot write ({err.strerror or err.__class__.__name__})") from None
    else:
        sys.stdout.write(out)
    return 0


def cmd_score(args: argparse.Namespace) -> int:
    import torch

    from plad.domains import get_domain

    domain = get_domain(args.domain)
    pred = load_shapes(Path(args.pred), domain.shape, targets=False)
    target = load_shapes(Path(args.target), domain.shape)
    if len(pred) != len(target):
        raise UsageError(f"{args.pred} holds {len(pred)} shapes but {args.target} holds {len(target)}")
    values = domain.metric(torch.from_numpy(pred), torch.from_numpy(target)).numpy()
    for v in values:
        print(f"{v:.6f}")
    if len(values) > 1:
        print(f"mean {values.mean():.6f}")
    return 0


def cmd_data(args: argparse.Namespace) -> int:
    from plad.data import resolve_data_dir
    from plad.datasets import cad

    if args.action == "download":
        path = cad.download_cad(resolve_data_dir(args.data_dir))
        print(f"downloaded and verified {path}")
        return 0
    for split in ("train", "val", "test"):
        shapes = cad.load_cad(args.data_dir, split)
        print(f"{cad.CAD.name} {split}: {len(shapes)} shapes {shapes.shape[1:]}")
    return 0


def cmd_infer(args: argparse.Namespace) -> int:
    """Programs for the user's shapes; a bad file is reported and the others still processed."""
    from plad.device import default_device
    from plad.domains import get_domain
    from plad.infer import ModelError, infer_items, new_run_dir, resolve_model
    from plad.inputs import read_inputs

    domain = get_domain(args.domain)
    if args.beam < 1:
        raise UsageError(f"--beam must be at least 1, got {args.beam}")
    items = read_inputs(args.inputs, tuple(domain.shape))
    if not items:
        raise UsageError(f"no supported files in {', '.join(args.inputs)}")
    try:
        model, source = resolve_model(args.domain, args.model, default_device())
    except ModelError as err:
        raise UsageError(str(err)) from None
    print(f"model: {source}", file=sys.stderr)
    try:
        run_dir = new_run_dir(args.out)
    except OSError as err:
        raise UsageError(f"--out {args.out}: cannot make this run's folder ({err.strerror or err})") from None
    results = infer_items(model, domain, items, args.beam, run_dir)
    failed = 0
    for r in results:
        where = r.item.source if r.item.source.name.startswith(r.item.name) else f"{r.item.source} [{r.item.name}]"
        if r.ok:
            notes = f"  ({'; '.join(r.item.notes)})" if r.item.notes else ""
            print(f"{where}: {domain.metric.name} {r.value:.4f}  {r.program}{notes}")
        else:
            failed += 1
            print(f"plad: error: {where}: {r.item.error}", file=sys.stderr)
    print(f"{len(results) - failed} of {len(results)} shapes inferred; this run's rows: {run_dir / 'results.csv'}",
          file=sys.stderr)
    return 2 if failed else 0


def _program_text(text: str) -> str:
    """A program given on the command line, or the text of a .txt file holding it.

    An argument that can only be a path (no whitespace, and a ``.txt`` suffix or a
    ``/``; no domain's program text looks like that) must name a readable file.
    """
    path = Path(text)
    looks_like_path = not any(c.isspace() for c in text) and (path.suffix == ".txt" or "/" in text)
    try:
        is_file = path.is_file()
    except (OSError, ValueError):   # a program text too long for a file name, or holding a NUL
        is_file = False
    if is_file and (path.suffix == ".txt" or looks_like_path):
        try:
            return path.read_text()
        except (OSError, UnicodeDecodeError) as err:
            raise UsageError(f"{text}: not a readable text file ({err.__class__.__name__})") from None
    if looks_like_path:
        raise UsageError(f"{text}: file not found")
    return text


def _search_setup(domain_name: str, overrides: list[str]):
    """(domain, search configuration with ``--set KEY=VALUE`` overrides)."""
    import yaml

    from plad.config import ConfigError
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
            values[key.strip()] = yaml.safe_load(text)
        except yaml.YAMLError:
            raise UsageError(f"--set {item!r}: value is not valid YAML") from None
    try:
        return domain, search_config(domain, **values)
    except ConfigError as err:
        raise UsageError(str(err)) from None


def cmd_refine(args: argparse.Namespace) -> int:
    """Rewrite a program towards a target shape; never returns a worse program."""
    import torch

    from plad.fsutil import atomic_write_text
    from plad.rewrite import refine
    from plad.rewrite.evaluate import Scorer

    domain, cfg = _search_setup(args.domain, args.set)
    ids = domain.parse(_program_text(args.program))
    target = load_shapes(Path(args.target), domain.shape)
    if len(target) != 1:
        raise UsageError(f"{args.target} holds {len(target)} shapes; refine takes one target shape")
    target = torch.from_numpy(target)
    before = float(Scorer(domain, target).values([ids])[0])
    result = refine(domain, [ids], target, cfg.refine)
    text = domain.format(result.programs[0])
    print(text)
    if args.output:
        atomic_write_text(Path(args.output), text + "\n")
    print(f"refined in {result.seconds:.1f} s", file=sys.stderr)
    print(f"{domain.metric.name} {before:.6f} -> {float(result.values[0]):.6f}")
    return 0


def cmd_search(args: argparse.Namespace) -> int:
    """Search from scratch (no network) for programs of the shapes in a file."""
    import torch

    from plad.fsutil import atomic_write_text
    from plad.rewrite import search

    domain, cfg = _search_setup(args.domain, args.set)
    targets = load_shapes(Path(args.file), domain.shape)
    result = search(domain, torch.from_numpy(targets), cfg)
    failed = 0
    lines = []
    for i, (ids, value) in enumerate(zip(result.programs, result.values.tolist())):
        where = args.file if len(targets) == 1 else f"{args.file} [{i}]"
        if not ids:
            failed += 1
            print(f"plad: error: {where}: no program scores better than the empty one (is the shape empty?)",
                  file=sys.stderr)
            lines.append("")
            continue
        lines.append(domain.format(ids))
        print(lines[-1])
        print(f"{domain.metric.name} {value:.6f}")
    if len(targets) > 1:
        print(f"mean {result.values.mean().item():.6f}")
    if args.output:
        atomic_write_text(Path(args.output), "\n".join(lines) + "\n")
    print(f"searched {len(targets)} shape(s) in {result.seconds:.1f} s", file=sys.stderr)
    return 2 if failed else 0


def cmd_models(args: argparse.Namespace) -> int:
    from plad.tracking import registered_models, tracking_uri

    rows = registered_models()
    if not rows:
        print(f"no registered models in {tracking_uri()}", file=sys.stderr)
        return 0
    print(f"{'model':<24} {'version':>7}  {'aliases':<12} {'method':<18} test metric")
    for r in rows:
        print(f"{r['name']:<24} {r['version']:>7}  {','.join(r['aliases']) or '-':<12} "
              f"{r['method'] or '-':<18} {r['test'] or '-'}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from plad.domains import domain_names

    parser = argparse.ArgumentParser(prog="plad", description="Infer shape programs from shapes (PLAD).")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("execute", help="execute a program and write the shape")
    p.add_argument("domain", choices=domain_names())
    p.add_argument("program", help="program text (or a .txt file holding it)")
    p.add_argument("-o", "--output", help="output file, its type by suffix: .npy (the bool grid) for every "
                   "domain; 2D: .png (255 inside, 0 outside); 3D: .ply/.obj (mesh) or .png (three views). "
                   "Without it a 2D shape is printed as text, a 3D one summarized")
    p.set_defaults(func=cmd_execute)

    p = sub.add_parser("export", help="write a program in another tool's format (e.g. OpenSCAD .scad), "
                                      "for the domains that offer one")
    p.add_argument("domain", choices=domain_names())
    p.add_argument("program", help="program text (or a .txt file holding it)")
    p.add_argument("--format", required=True, help="output format, e.g. scad")
    p.add_argument("-o", "--output", help="output file (default: standard output)")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("score", help="score predicted shapes against targets with the domain metric")
    p.add_argument("domain", choices=domain_names())
    p.add_argument("--pred", required=True, help=".png or .npy (N, *shape)")
    p.add_argument("--target", required=True, help=".png or .npy (N, *shape)")
    p.set_defaults(func=cmd_score)

    p = sub.add_parser("data", help="check or download the real datasets")
    p.add_argument("action", choices=["check", "download"])
    p.add_argument("--data-dir", default=None, help="data directory (default: $PLAD_DATA_DIR or ./data/datasets)")
    p.set_defaults(func=cmd_data)

    p = sub.add_parser("infer", help="infer programs for your own shapes (images, meshes, .npy; folders)")
    p.add_argument("domain", choices=domain_names())
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="2D: .png/.jpg/... images or .npy; 3D: .obj/.ply/.off/.stl meshes or .npy voxels; "
                        "a folder means all supported files in it")
    p.add_argument("--model", default=None,
                   help="a checkpoint file or an MLflow model URI (default: models:/plad-DOMAIN@champion)")
    p.add_argument("--beam", type=int, default=10, help="beam width (default 10)")
    p.add_argument("--out", default="inferred",
                   help="output folder (default: ./inferred); each run writes into its own <time>-<pid>/ in it")
    p.set_defaults(func=cmd_infer)

    p = sub.add_parser("refine", help="rewrite a program towards a target shape (search from the program)")
    p.add_argument("domain", choices=domain_names())
    p.add_argument("program", help="program text (or a .txt file holding it)")
    p.add_argument("--target", required=True, help="the target shape: .png or .npy, as for plad score")
    p.add_argument("-o", "--output", help="also write the refined program's text to this file")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="search setting, e.g. refine.rounds=5 or refine.wide=false (repeatable)")
    p.set_defaults(func=cmd_refine)

    p = sub.add_parser("search", help="search for programs of shapes from scratch, without a network")
    p.add_argument("domain", choices=domain_names())
    p.add_argument("file", help="target shape(s): .png or .npy (N, *shape), as for plad score")
    p.add_argument("-o", "--output", help="also write the programs, one per line, to this file")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="search setting, e.g. insertions=5 or refine.rounds=1 (repeatable)")
    p.set_defaults(func=cmd_search)

    p = sub.add_parser("models", help="list the registered models (MLflow registry) with their test metric")
    p.set_defaults(func=cmd_models)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from plad.errors import run_guarded
    from plad.grammar import ProgramError

    def describe(err: Exception) -> str:
        return f"invalid {args.domain} program: {err}" if isinstance(err, ProgramError) else str(err)

    return run_guarded("plad", lambda: args.func(args), describe)


if __name__ == "__main__":
    sys.exit(main())
