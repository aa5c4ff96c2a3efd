"""The ``plad`` command line.

    plad execute DOMAIN PROGRAM [-o shape.png | shape.npy | shape.ply ...]
    plad export DOMAIN PROGRAM --format FORMAT [-o FILE]
    plad score DOMAIN --pred pred.npy --target target.npy
    plad data check | download
    plad infer DOMAIN drawing.png shapes/ --beam 10 --out inferred/
    plad refine DOMAIN PROGRAM --target shape.png -o refined.txt
    plad search DOMAIN shape.npy --set insertions=8
    plad models
    plad models ship DOMAIN CHECKPOINT --metrics results/eval/METHOD/DOMAIN/metrics.json

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
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

# The parser, --help, argument errors, `plad models` and `plad data check` import neither
# torch, MLflow nor open3d (a test checks it): every command imports what it needs itself.
if TYPE_CHECKING:
    import numpy as np

from plad.errors import BadInput


class UsageError(BadInput):
    """A problem with the user's input; printed as one line, exit status 2 (:mod:`plad.errors`)."""


# ---- shape files -------------------------------------------------------------------
def load_shapes(path: Path, shape: tuple[int, ...], targets: bool = True) -> np.ndarray:
    """Shapes for scoring or search, checked at the edge by :func:`plad.data.inputs.read_shapes`; bool (N, *shape).

    ``targets``: the empty-shape rule applies (a prediction may be empty).
    """
    from plad.data.inputs import InputError, read_shapes

    try:
        return read_shapes(path, tuple(shape), targets=targets)
    except InputError as err:
        raise UsageError(f"{path}: {err}") from None


# ---- commands --------------------------------------------------------------------------
def cmd_execute(args: argparse.Namespace) -> int:
    from plad.domains import get_domain
    from plad.domains.grammar import ProgramError

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
    from plad.domains.grammar import ProgramError

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
    print(f"mean {values.mean():.6f}")   # for one shape too: scripts read the last line
    return 0


def cmd_data(args: argparse.Namespace) -> int:
    import importlib

    from plad.data.datasets import CHECKS, cad
    from plad.data.files import DataError, resolve_data_dir

    if args.action == "download":
        path = cad.download_cad(resolve_data_dir(args.data_dir))
        print(f"downloaded and verified {path}")
        return 0
    # every target source the domains read (the CAD file; the PartNet programs of both 3D domains),
    # each reported on its own, so that one missing file does not hide the state of the others
    failed = 0
    for target in CHECKS.values():
        module, attr = target.split(":")
        try:
            for line in getattr(importlib.import_module(module), attr)(args.data_dir):
                print(line)
        except DataError as err:
            failed += 1
            print(f"plad: error: {err}", file=sys.stderr)
    return 1 if failed else 0


def cmd_infer(args: argparse.Namespace) -> int:
    """Programs for the user's shapes; a bad file is reported and the others still processed."""
    from plad.data.inputs import read_inputs
    from plad.device import default_device
    from plad.domains import get_domain
    from plad.serve.infer import ModelError, infer_items, new_run_dir, resolve_model

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
    refine = None
    if args.refine:
        from plad.rewrite import RefineConfig

        refine = RefineConfig()
    results = infer_items(model, domain, items, args.beam, run_dir, refine=refine)
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
    """List the shipped and the registered models (the default one of each domain marked), or ship one."""
    if args.models_command == "ship":
        return _ship(args)
    if args.models_command == "ship-pretrained":
        return _ship_pretrained(args)
    from plad.domains import domain_names
    from plad.serve.resolve import configured_store
    from plad.shipped import ShipError, describe_totals, list_pretrained, list_shipped, shipped_dir

    rows = []   # (domain, source, model, method, test)
    try:
        for m in list_shipped():
            t = m.test
            test = f"{t.get('metric', '?')} {t.get('mean', '?')} (n {t.get('n', '?')}, beam {t.get('beam', '?')})"
            rows.append((m.domain, "shipped", str(m.checkpoint), m.info.get("method") or "-", test))
        # the pretrained networks: what they hold (the SP row of the results is their test metric)
        for m in list_pretrained():
            rows.append((m.domain, "pretrained", str(m.checkpoint), "sp", describe_totals(m)))
    except ShipError as err:
        raise UsageError(str(err)) from None
    store = configured_store()
    if store is not None:   # MLflow is imported only to read a configured store
        from plad.tracking import registered_models

        for r in registered_models():
            domain = r["name"].removeprefix("plad-")
            aliases = "".join(f"@{a}" for a in r["aliases"])
            rows.append((domain if domain in domain_names() else r["name"], "registered",
                         f"models:/{r['name']}/{r['version']} {aliases}".rstrip(), r["method"] or "-",
                         r["test"] or "-"))
    # the model `plad infer DOMAIN` uses without --model: the champion, else the shipped one
    default = {}
    for domain, source, model, *_ in rows:
        if source == "registered" and "@champion" in model or source == "shipped" and domain not in default:
            default[domain] = model
    print(f"{'domain':<14} {'source':<10} {'method':<18} {'test metric':<36} model  (* = used by default)")
    for domain, source, model, method, test in sorted(rows, key=lambda r: (r[0], r[1] != "shipped")):
        mark = "*" if default.get(domain) == model else " "
        print(f"{domain:<14} {source:<10} {method:<18} {test:<36} {mark}{model}")
    if not rows:
        print("(no shipped or registered models)")
    env = os.environ.get("MLFLOW_TRACKING_URI")
    none = f"none ($MLFLOW_TRACKING_URI={env} does not exist yet)" if env else \
        "none configured ($MLFLOW_TRACKING_URI unset, no ./mlflow.db)"
    print(f"shipped models: {shipped_dir()}; MLflow store: {store or none}", file=sys.stderr)
    return 0


def _ship(args: argparse.Namespace) -> int:
    from plad.shipped import ShipError, ship

    try:
        shipped = ship(args.domain, args.checkpoint, args.metrics, dest=args.dest, root=args.root,
                       params=args.params, data_dir=args.data_dir)
    except ShipError as err:
        raise UsageError(str(err)) from None
    git = shipped.info["provenance"]["git"]
    print(f"shipped {shipped.checkpoint} ({shipped.info['checkpoint']['bytes']} bytes) and "
          f"{shipped.checkpoint.with_name('model.json')}: test {shipped.test.get('metric')} "
          f"{shipped.test.get('mean')}, git {git['revision']}{' (dirty)' if git['dirty'] else ''}")
    return 0


def _ship_pretrained(args: argparse.Namespace) -> int:
    from plad.shipped import ShipError, describe_totals, ship_pretrained

    try:
        shipped = ship_pretrained(args.domain, args.checkpoint, dest=args.dest)
    except ShipError as err:
        raise UsageError(str(err)) from None
    print(f"shipped {shipped.checkpoint} ({shipped.info['checkpoint']['bytes']} bytes): {describe_totals(shipped)}")
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
                   help="a checkpoint file or an MLflow model URI (default: models:/plad-DOMAIN@champion of the "
                        "MLflow store if one is configured and has it, else the model shipped with PLAD)")
    p.add_argument("--beam", type=int, default=10, help="beam width (default 10)")
    p.add_argument("--out", default="inferred",
                   help="output folder (default: ./inferred); each run writes into its own <time>-<pid>/ in it")
    p.add_argument("--refine", action="store_true",
                   help="rewrite each best-of-beam program with the rewriters (PO, pruning, insertion) before "
                        "writing it; never worse, slower")
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

    p = sub.add_parser("models", help="list the shipped and the registered models with their test metrics; "
                                      "`plad models ship` packages a trained checkpoint as a shipped model",
                       description="Without a subcommand: list the models shipped with PLAD and those registered "
                                   "in the MLflow store (if one is configured), with their test metrics; * marks "
                                   "the one `plad infer DOMAIN` uses without --model.")
    p.set_defaults(func=cmd_models, models_command=None)
    ms = p.add_subparsers(dest="models_command")
    q = ms.add_parser("ship", help="package a trained checkpoint as the shipped model of its domain")
    q.add_argument("domain", choices=domain_names())
    q.add_argument("checkpoint", help="the trained checkpoint, e.g. runs/finetune/DOMAIN/lest_st/best.pt")
    q.add_argument("--metrics", required=True,
                   help="the metrics.json of its test evaluation, e.g. results/eval/lest_st/DOMAIN/metrics.json")
    q.add_argument("--root", default=".", help="the layout root it was trained in (params, git, prepared data; "
                                               "default: .)")
    q.add_argument("--params", default="params.yaml", help="params file, relative to --root (default params.yaml)")
    q.add_argument("--data-dir", default=None, help="data directory (for the data files' checksums)")
    q.add_argument("--dest", default=None, help="folder of shipped models (default: the package's plad/shipped, "
                                                "or $PLAD_SHIPPED_DIR)")
    q = ms.add_parser("ship-pretrained", help="ship a pretraining's state as the pretrained network of its domain "
                                              "(continued by `pretrain.DOMAIN.init: shipped`)")
    q.add_argument("domain", choices=domain_names())
    q.add_argument("checkpoint", help="the pretraining's state, e.g. runs/pretrain/DOMAIN/last.pt")
    q.add_argument("--dest", default=None, help="folder of shipped models (default: the package's plad/shipped, "
                                                "or $PLAD_SHIPPED_DIR)")
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
