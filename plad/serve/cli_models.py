"""``plad models``, ``plad models ship`` and ``plad models ship-pretrained``: the shipped and registered models
listed (the default one of each domain marked, and why), a trained checkpoint shipped (:mod:`plad.serve.cli`)."""
from __future__ import annotations

import argparse
import os
import sys
from typing import Any


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


def add_parser(sub: Any) -> None:
    """The ``models`` command of ``plad`` and its ``ship`` and ``ship-pretrained`` subcommands."""
    from plad.domains import domain_names

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
