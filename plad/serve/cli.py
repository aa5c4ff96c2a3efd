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
    plad config finetune.csg3d [--profile smoke] [--set key=lest]

DOMAIN is a registered domain (``plad --help`` lists them); PROGRAM is
program text or a ``.txt`` file holding it. What a domain offers (its output
types, its export formats) it declares itself (:class:`plad.domains.base.Domain`).
Errors are one line on stderr, never a traceback, with the exit status of
:mod:`plad.errors` (0 ok, 1 a failure of the run or its data, 2 bad usage or
input: the convention and its cases are written there). Every command reads
the user's shapes with the one reader of :mod:`plad.data.inputs`.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

# The parser, --help, argument errors, `plad models` and `plad data check` import neither
# torch, MLflow nor open3d (a test checks it): every command imports what it needs itself.
from plad.errors import BadInput, one_line
from plad.serve import show_config


class UsageError(BadInput):
    """A problem with the user's input; printed as one line, exit status 2 (:mod:`plad.errors`)."""


# ---- shapes and output files ----------------------------------------------------------------
def read_shapes(path: str, shape: tuple[int, ...], target: bool = True, frames=None) -> list:
    """The shapes of one file by the one reader (:func:`plad.data.inputs.read_file`): one item per shape, a bad
    shape of a batch an item with its error. A file that gives one item, in error, is a :class:`UsageError`."""
    from plad.data.inputs import quote, read_file

    items = read_file(path, tuple(shape), target=target, frames=frames)
    if len(items) == 1 and items[0].error:
        raise UsageError(f"{quote(path)}: {items[0].error}")
    return items


def check_output(path: str | None, inputs: tuple[str, ...] = ()) -> Path | None:
    """The output file ``path``, checked before any work: not a folder, not one of the ``inputs`` (never written
    over), and in a folder this process can write to. None when no output was asked for."""
    import tempfile

    from plad.data.inputs import quote

    if path is None:
        return None
    out = Path(path)

    def refuse(reason: str):
        return UsageError(f"{quote(path)}: cannot write ({reason})")

    try:
        if out.is_dir():
            raise refuse("it is a folder; name a file")
        if out.exists() and any(_same_file(source, out) for source in inputs):
            raise refuse("it is an input of this command, which is never written over")
        if not out.parent.is_dir():
            raise refuse(f"No such file or directory: no folder {quote(out.parent)}")
        # the real test of a writable folder: create (and remove) a file in it, as the atomic write will
        with tempfile.NamedTemporaryFile(dir=out.parent, prefix=".plad-check-"):
            pass
    except (OSError, ValueError) as err:
        raise refuse(getattr(err, "strerror", None) or one_line(err)) from None
    return out


def _same_file(source: str, out: Path) -> bool:
    """Whether the argument ``source`` (a path, or text such as a program) names the file ``out``."""
    try:
        return Path(source).exists() and os.path.samefile(source, out)
    except (OSError, ValueError):   # not a path at all (too long, a NUL): not that file
        return False


def check_out_dir(path: str, flag: str = "--out") -> None:
    """A folder that runs write into: it exists as a folder, or can be made in the nearest existing folder
    above it (checked before any work; nothing is created here)."""
    from plad.data.inputs import quote

    folder = Path(path)
    probe = folder
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        raise UsageError(f"{flag} {quote(path)}: {quote(probe)} is a file, not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise UsageError(f"{flag} {quote(path)}: cannot write in {quote(probe)}")


def write_output(out: Path, text: str) -> None:
    """``text`` into ``out`` (atomically); a failure is one line."""
    from plad.data.inputs import quote
    from plad.fsutil import atomic_write_text

    try:
        atomic_write_text(out, text)
    except OSError as err:
        raise UsageError(f"{quote(out)}: cannot write ({err.strerror or err.__class__.__name__})") from None


# ---- commands --------------------------------------------------------------------------
def cmd_execute(args: argparse.Namespace) -> int:
    from plad.domains import get_domain
    from plad.domains.grammar import ProgramError

    domain = get_domain(args.domain)
    check_output(args.output, (args.program,))
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
    text = _program_text(args.program)
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
    beam = _beam(check_beam, args.beam)
    check_out_dir(args.out)
    items = read_inputs(args.inputs, tuple(domain.shape))
    if not items:
        raise UsageError(f"no supported files in {', '.join(map(_quote, args.inputs))}")
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
        raise UsageError(f"--out {_quote(args.out)}: cannot make this run's folder ({err.strerror or err})") from None
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
          + (f"this run's rows: {table}" if unwritten is None else f"the files written are kept in {_quote(run_dir)}"),
          file=sys.stderr)
    failed += lost
    if unwritten is not None:
        raise UsageError(f"{_quote(table)}: cannot write ({unwritten}); the results are printed above")
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


def _quote(path: object) -> str:
    from plad.data.inputs import quote

    return quote(path)


def _shown_as(item) -> str:
    """Where an item came from, and its output name when that is not the file's own stem."""
    from plad.data.inputs import safe_name

    natural = safe_name(item.source.stem) + ("" if item.index is None else f"_{item.index}")
    return item.where if item.name == natural else f"{item.where} (as {item.name})"


def _beam(check, beam: int) -> int:
    try:
        return check(beam)
    except ValueError as err:
        raise UsageError(f"--beam {beam}: {err}") from None


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
    ids = domain.parse(_program_text(args.program))
    items = read_shapes(args.target, domain.shape)
    if len(items) != 1:
        raise UsageError(f"{_quote(args.target)} holds {len(items)} shapes; refine takes one target shape")
    if items[0].error:
        raise UsageError(f"{items[0].where}: {items[0].error}")
    for note in items[0].notes:
        print(f"{_quote(args.target)}: {note}", file=sys.stderr)
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


def cmd_models(args: argparse.Namespace) -> int:
    """List the shipped and the registered models (the default one of each domain marked, and why), or ship one."""
    if args.models_command == "ship":
        return _ship(args)
    if args.models_command == "ship-pretrained":
        return _ship_pretrained(args)
    from plad.domains import domain_names
    from plad.serve.resolve import ModelError, configured_store, default_model
    from plad.shipped import describe_totals, list_pretrained, list_shipped, shipped_dir

    rows = []   # (domain, source, model, method, test, provenance)
    # damaged shipped files are listed with what is wrong (one line each, stderr) and make the status 1; the
    # others are still listed
    damaged: list[str] = []
    for m in list_shipped(errors=damaged):
        t = m.test
        test = f"{t.get('metric', '?')} {t.get('mean', '?')} (n {t.get('n', '?')}, beam {t.get('beam', '?')})"
        problem = m.problem()
        damaged += [problem] if problem else []
        rows.append((m.domain, "shipped", str(m.checkpoint), m.info.get("method") or "-", test,
                     f"DAMAGED: {problem}" if problem else _provenance(m.info)))
    # the pretrained networks: what they hold (the SP row of the results is their test metric)
    for m in list_pretrained(errors=damaged):
        problem = m.problem()
        damaged += [problem] if problem else []
        rows.append((m.domain, "pretrained", str(m.checkpoint), "sp", describe_totals(m),
                     f"DAMAGED: {problem}" if problem else _provenance(m.info)))
    store = configured_store()
    if store is not None:   # MLflow is imported only to read a configured store
        from plad.tracking import registered_models

        for r in registered_models():
            aliases = "".join(f"@{a}" for a in r["aliases"])
            where = [f"MLflow run {r['run_id']}"] if r.get("run_id") else []
            where += [f"profile {r['profile']}"] if r.get("profile") else []
            where += [f"{r['test_set']} test set"] if r.get("test_set") else []
            rows.append((_registered_domain(r["name"], domain_names()), "registered",
                         f"models:/{r['name']}/{r['version']} {aliases}".rstrip(), r["method"] or "-",
                         r["test"] or "-", ", ".join(where)))
    # the model `plad infer DOMAIN` uses without --model (plad.serve.resolve, which `plad infer` follows): the
    # champion if it was evaluated on the full test set, else the shipped one; and why
    defaults, unusable = {}, {}
    for d in domain_names():
        try:
            defaults[d] = default_model(d)
        except ModelError as err:   # a damaged shipped file: said below, the listing goes on
            unusable[d] = str(err)
    print(f"{'domain':<14} {'source':<10} {'method':<18} {'test metric':<36} model  (* = used by default)")
    for domain, source, model, method, test, provenance in sorted(rows, key=lambda r: (r[0], r[1] != "shipped")):
        used = defaults.get(domain)
        mark = "*" if used is not None and used.model and model.split(" ")[0] == used.model else " "
        print(f"{domain:<14} {source:<10} {method:<18} {test:<36} {mark}{model}")
        if provenance:
            print(f"{'':<14} provenance: {provenance}")
    if not rows:
        print("(no shipped or registered models)")
    for domain, used in defaults.items():
        if used.kind == "none":
            print(f"plad infer {domain} has no model without --model: {used.why}")
        else:
            print(f"plad infer {domain} uses {used.model}: {used.why}")
    for domain, why in unusable.items():
        print(f"plad infer {domain} has no usable model without --model: {why}")
    env = os.environ.get("MLFLOW_TRACKING_URI")
    none = f"none ($MLFLOW_TRACKING_URI={env} does not exist yet)" if env else \
        "none configured ($MLFLOW_TRACKING_URI unset, no ./mlflow.db)"
    print(f"shipped models: {shipped_dir()}; MLflow store: {store or none}", file=sys.stderr)
    for problem in dict.fromkeys([*damaged, *unusable.values()]):
        print(f"plad: error: {problem}", file=sys.stderr)
    return 1 if damaged or unusable else 0


def _registered_domain(name: str, domains: list[str]) -> str:
    """The domain of a registered model's name: ``plad-<domain>``, or ``plad-<domain>-<profile>`` (the models of
    a profile that evaluates a few test shapes, :func:`plad.tracking.registry.model_name`); else the name."""
    rest = name.removeprefix("plad-")
    for domain in sorted(domains, key=len, reverse=True):
        if rest == domain or rest.startswith(f"{domain}-"):
            return domain
    return name


def _provenance(info: dict) -> str:
    """Where a shipped model came from, in one line: its checkpoint, the git revision and params it was
    trained with, and its checksum (the sidecar's ``provenance``, :mod:`plad.shipped`)."""
    prov = info.get("provenance") or {}
    git = prov.get("git") or {}
    parts = []
    if info.get("checkpoint", {}).get("shipped_from"):
        parts.append(f"from {info['checkpoint']['shipped_from']}")
    if git.get("revision"):
        parts.append(f"git {str(git['revision'])[:7]}{' (dirty)' if git.get('dirty') else ''}")
    if prov.get("params_file"):
        parts.append(f"params {prov['params_file']}" + (f" (profile {prov['profile']})" if prov.get("profile") else ""))
    if info.get("checkpoint", {}).get("sha256"):
        parts.append(f"sha256 {str(info['checkpoint']['sha256'])[:12]}")
    return ", ".join(parts)


def _ship(args: argparse.Namespace) -> int:
    from plad.shipped import ship

    shipped = ship(args.domain, args.checkpoint, args.metrics, dest=args.dest, root=args.root,   # ShipError: 1
                   params=args.params, data_dir=args.data_dir, force=args.force)
    git = shipped.info["provenance"]["git"]
    for note in shipped.notes:
        print(f"plad: note: {note}", file=sys.stderr)
    print(f"shipped {shipped.checkpoint} ({shipped.info['checkpoint']['bytes']} bytes) and "
          f"{shipped.checkpoint.with_name('model.json')}: test {shipped.test.get('metric')} "
          f"{shipped.test.get('mean')}, git {git['revision']}{' (dirty)' if git['dirty'] else ''}")
    return 0


def _ship_pretrained(args: argparse.Namespace) -> int:
    from plad.shipped import describe_totals, ship_pretrained

    shipped = ship_pretrained(args.domain, args.checkpoint, dest=args.dest)   # ShipError: exit status 1
    print(f"shipped {shipped.checkpoint} ({shipped.info['checkpoint']['bytes']} bytes): {describe_totals(shipped)}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from plad.domains import domain_names

    parser = argparse.ArgumentParser(
        prog="plad", description=f"Infer shape programs from shapes (PLAD). DOMAIN is one of: "
                                 f"{', '.join(domain_names())}. `plad COMMAND --help` gives a command's arguments.")
    # one line per command: each help fits a line of an 80-column terminal (tests/plad/serve/test_cli.py)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", title="commands")

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

    p = sub.add_parser("data", help="check or download the real datasets",
                       description="Check (found, verified, split sizes) or download the real datasets.")
    p.add_argument("action", choices=["check", "download"])
    p.add_argument("--data-dir", default=None, help="data directory (default: $PLAD_DATA_DIR or ./data/datasets)")
    p.set_defaults(func=cmd_data)

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

    p = sub.add_parser("models", help="list the models and the default one; ship a model",
                       description="Without a subcommand: list the models shipped with PLAD and those registered "
                                   "in the MLflow store (if one is configured), with their test metrics; * marks "
                                   "the one `plad infer DOMAIN` uses without --model, and a line per domain says "
                                   "which and why (a champion only if evaluated on the full test set). "
                                   "`plad models ship` packages a trained checkpoint as a shipped model.")
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
    q.add_argument("--force", action="store_true",
                   help="ship it even when it does not beat the shipped model's test metric on the same test "
                        "(the replaced model is kept in DOMAIN/previous/ either way)")
    q = ms.add_parser("ship-pretrained", help="ship a pretraining's state as the pretrained network of its domain "
                                              "(continued by `pretrain.DOMAIN.init: shipped`)")
    q.add_argument("domain", choices=domain_names())
    q.add_argument("checkpoint", help="the pretraining's state, e.g. runs/pretrain/DOMAIN/last.pt")
    q.add_argument("--dest", default=None, help="folder of shipped models (default: the package's plad/shipped, "
                                                "or $PLAD_SHIPPED_DIR)")
    show_config.add_parser(sub)
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
