"""Which path ``plad infer`` takes per domain: the network with refinement, or search from scratch (issue 58).

The measurement, a maintainer's command (:mod:`plad.serve.route` reads what it records). A user should never
get the slower-and-worse path. For each domain this measures, on validation shapes (never the test shapes:
the route is a choice, and choices are made on validation), one thread, CPU seconds per shape, at an effort
level (:func:`plad.tools.effort.measure`):

* ``network``: the shipped network's beam-10 programs refined as ``plad infer --effort LEVEL`` refines them;
* ``search``: search from scratch at the level, as ``plad search --effort LEVEL``.

The route is the path with the better metric (a tie: the faster one); both points are kept with it in
``plad/shipped/routes.json``, and ``plad infer`` follows it when it uses the shipped network (``--route``
overrides it)::

    python -m plad.tools.route measure DOMAIN [--spaced 50] [--effort default] [--prepared data/prepared]
"""
from __future__ import annotations

import argparse
import json
import sys
from datetime import datetime, timezone
from pathlib import Path

from plad.fsutil import atomic_write_text
from plad.serve.route import read_routes, routes_file


def choose(points: list[dict], effort: str, higher_is_better: bool) -> dict:
    """The route from :func:`plad.tools.effort.measure`'s points at ``effort``."""
    net = next(p for p in points if p["kind"] == "network + refinement" and p["config"] == effort)
    srch = next(p for p in points if p["kind"] == "search" and p["config"] == effort)
    sign = 1.0 if higher_is_better else -1.0
    if net["mean"] == srch["mean"]:
        route = "network" if net["s_per_shape"] <= srch["s_per_shape"] else "search"
    else:
        route = "network" if sign * (net["mean"] - srch["mean"]) > 0 else "search"
    return {"route": route, "effort": effort,
            "network": {"mean": net["mean"], "s_per_shape": net["s_per_shape"]},
            "search": {"mean": srch["mean"], "s_per_shape": srch["s_per_shape"]}}


def measure_route(domain_name: str, targets, effort: str = "default", folder: Path | None = None) -> dict:
    """Measure both paths on ``targets`` (validation shapes) with the shipped network; write the route."""
    import torch

    from plad.domains import get_domain
    from plad.model.checkpoint import load_model
    from plad.shipped import shipped_model
    from plad.tools.effort import measure

    shipped = shipped_model(domain_name, folder)
    if shipped is None:
        raise ValueError(f"no shipped {domain_name} network to measure")
    shipped.verify()
    model, _ = load_model(shipped.checkpoint, torch.device("cpu"), expect_domain=domain_name)
    domain = get_domain(domain_name)
    points = measure(domain_name, targets, model, levels=[effort])
    entry = {**choose(points, effort, domain.metric.higher_is_better), "shapes": int(len(targets)),
             "split": "val", "metric": domain.metric.name, "model_sha256": shipped.info["checkpoint"]["sha256"],
             "measured": datetime.now(timezone.utc).isoformat(timespec="seconds"), "points": points}
    path = routes_file(folder)
    data = {"format": 1, "domains": read_routes(folder)}
    data["domains"][domain_name] = entry
    atomic_write_text(path, json.dumps(data, indent=2, sort_keys=True) + "\n")
    return entry


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("measure", help="measure both paths on validation shapes and record the route")
    p.add_argument("domain")
    p.add_argument("--spaced", type=int, default=50, help="N validation shapes, evenly spaced (default 50)")
    p.add_argument("--effort", default="default")
    p.add_argument("--prepared", default="data/prepared", help="folder of the prepared <domain>.npz")
    p.add_argument("--dest", default=None, help="folder of the shipped models (default: the package's)")
    args = parser.parse_args(argv)
    from plad.data.files import load_split

    path = Path(args.prepared) / f"{args.domain}.npz"
    if not path.is_file():
        print(f"{path}: no such prepared dataset (run the prepare stage first)", file=sys.stderr)
        return 1
    targets = load_split(path, "val", args.spaced)[0]
    try:
        entry = measure_route(args.domain, targets, args.effort, Path(args.dest) if args.dest else None)
    except ValueError as err:
        print(err, file=sys.stderr)
        return 1
    print(json.dumps({k: v for k, v in entry.items() if k != "points"}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
