"""``plad infer``: programs for the user's shapes, by the network (and refinement) or by search from scratch
(:mod:`plad.serve.cli`; the work itself is :mod:`plad.serve.infer`'s)."""
from __future__ import annotations

import argparse
import sys
from typing import Any

from plad.serve.cli_common import UsageError, check_out_dir, checked_beam, quoted


def cmd_infer(args: argparse.Namespace) -> int:
    """Programs for the user's shapes; a bad file is reported and the others still processed."""
    from plad.config import check_beam
    from plad.data.inputs import read_inputs
    from plad.device import default_device
    from plad.domains import get_domain
    from plad.serve.infer import infer_items, new_run_dir, refinement, resolve_model

    domain = get_domain(args.domain)
    if args.effort is not None and not args.refine:
        raise UsageError(f"--effort {args.effort} sets the refinement, which --no-refine turns off: give one of them")
    refine = None
    if args.refine:
        try:
            refine = refinement(domain, args.effort or "default")
        except ValueError as err:
            raise UsageError(str(err)) from None
    beam = checked_beam(check_beam, args.beam)
    check_out_dir(args.out)
    items = read_inputs(args.inputs, tuple(domain.shape))
    if not items:
        raise UsageError(f"no supported files in {', '.join(map(quoted, args.inputs))}")
    if all(it.error for it in items):   # nothing to infer: report, and leave no run folder behind
        for it in items:
            print(f"plad: error: {it.where}: {it.error}", file=sys.stderr)
        raise UsageError(f"none of the {len(items)} input shape(s) can be used; nothing was written")
    model, source = resolve_model(args.domain, args.model, default_device())   # ModelError: exit status 1
    route, why = _route(args)
    search = None
    if route == "search":   # the path measured better on validation shapes: search from scratch, no network
        from plad.rewrite import search_config

        search = search_config(domain, effort=args.effort or "default")
        print(f"route: search from scratch ({why})", file=sys.stderr)
    else:
        print(f"model: {source}", file=sys.stderr)
        if args.route == "auto":
            print(f"route: network ({why})", file=sys.stderr)
    try:
        run_dir = new_run_dir(args.out)
    except OSError as err:
        raise UsageError(f"--out {quoted(args.out)}: cannot make this run's folder ({err.strerror or err})") from None
    from plad.fsutil import WriteError

    shown: list = []

    def show(r) -> None:   # each result as soon as it is done: nothing computed is lost to a later failure
        shown.append(r)
        where = _shown_as(r.item)
        if r.ok:
            notes = f"  ({'; '.join(r.item.notes)})" if r.item.notes else ""
            print(f"{where}: {domain.metric.name} {r.value:.4f}  {r.seconds:.2f} s  {r.program}{notes}", flush=True)
        if not r.ok or r.write_error:
            print(f"plad: error: {where}: {r.item.error or r.write_error}", file=sys.stderr, flush=True)

    table = run_dir / "results.csv"
    unwritten = None
    try:
        results = infer_items(model, domain, items, beam, run_dir, refine=refine, search=search, on_result=show)
    except WriteError as err:   # results.csv: every result is printed above and every file written is kept
        results, unwritten = shown, err.cause
    failed = sum(1 for r in results if not r.ok)
    lost = sum(1 for r in results if r.ok and r.write_error)
    seconds = sum(r.seconds for r in results if r.ok)
    print(f"{len(results) - failed} of {len(results)} shapes inferred{' and refined' if args.refine else ''} in "
          f"{seconds:.1f} s" + (f" ({lost} of them not all written)" if lost else "") + "; "
          + (f"this run's rows: {table}" if unwritten is None else f"the files written are kept in {quoted(run_dir)}"),
          file=sys.stderr)
    failed += lost
    if unwritten is not None:
        raise UsageError(f"{quoted(table)}: cannot write ({unwritten}); the results are printed above")
    return 2 if failed else 0


def _route(args: argparse.Namespace) -> tuple[str, str]:
    """(network | search, why) for ``plad infer``: ``--route``, or with ``auto`` the route measured for the
    domain's shipped network (:mod:`plad.serve.route`) when that is the network in use."""
    from plad.serve.resolve import default_model
    from plad.serve.route import route_for

    if args.route != "auto":
        return args.route, f"--route {args.route}"
    if not args.refine:
        return "network", "--no-refine asks for the network's own programs"
    if args.model is not None:
        return "network", "--model names the network"
    chosen = default_model(args.domain)
    if chosen.kind != "shipped" or chosen.shipped is None or chosen.shipped.kind != "model":
        return "network", "the network in use is not the shipped one"
    return route_for(args.domain, chosen.shipped.info.get("checkpoint", {}).get("sha256"))


def _shown_as(item) -> str:
    """Where an item came from, and its output name when that is not the file's own stem."""
    from plad.data.inputs import safe_name

    natural = safe_name(item.source.stem) + ("" if item.index is None else f"_{item.index}")
    return item.where if item.name == natural else f"{item.where} (as {item.name})"


def add_parser(sub: Any) -> None:
    """The ``infer`` command of ``plad``."""
    from plad.domains import domain_names

    p = sub.add_parser("infer", help="infer programs for your shapes (images, meshes, .npy)",
                       description="Infer programs for your own shapes (images, meshes, .npy; folders) with the "
                                   "shipped or a registered network, each then refined by search.")
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
    p.add_argument("--refine", action=argparse.BooleanOptionalAction, default=True,
                   help="rewrite each best-of-beam program (--effort best: every beam candidate) with the "
                        "rewriters (PO, pruning, insertion) before writing it: never worse, often much better, "
                        "slower (default); --no-refine: the network's beam alone")
    p.add_argument("--route", choices=("auto", "network", "search"), default="auto",
                   help="network (+ refinement) or search from scratch; auto (default): the path measured better "
                        "for the domain's shipped network on validation shapes (plad/shipped/routes.json)")
    p.add_argument("--effort", default=None, metavar="LEVEL",
                   help="how hard to refine: fast (the best-of-beam program, refined as `plad search --effort "
                        "fast` refines), default (the best-of-beam program, up to 3 rounds) or best (every beam "
                        "candidate refined as for default, the best kept: slower, never worse); docs/inference.md")
    p.set_defaults(func=cmd_infer)
