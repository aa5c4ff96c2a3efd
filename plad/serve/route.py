"""Which path ``plad infer`` takes per domain: the network with refinement, or search from scratch (issue 58).

A user should never get the slower-and-worse path. The route of each domain is measured on validation shapes
with the shipped network (:mod:`plad.tools.route`, a maintainer's command) and recorded, with both measured
points, in ``plad/shipped/routes.json``; ``plad infer`` follows it when it uses that very network (``--route``
overrides it).
"""
from __future__ import annotations

import json
from pathlib import Path

ROUTES = "routes.json"
#: the two paths of ``plad infer``
PATHS = ("network", "search")


def routes_file(folder: Path | None = None) -> Path:
    from plad.shipped import shipped_dir

    return Path(folder or shipped_dir()) / ROUTES


def read_routes(folder: Path | None = None) -> dict:
    """``{domain: entry}`` of the measured routes ({} where none is recorded or the file is unreadable)."""
    path = routes_file(folder)
    try:
        return json.loads(path.read_text()).get("domains", {})
    except (OSError, ValueError, AttributeError):
        return {}


def route_for(domain: str, model_sha256: str | None, folder: Path | None = None) -> tuple[str, str]:
    """(path, why) for ``plad infer`` with the network whose checkpoint has ``model_sha256``: the measured
    route where it was measured with that very network, else the network."""
    entry = read_routes(folder).get(domain)
    if entry is None:
        return "network", "no route measured for this domain"
    if entry.get("model_sha256") != model_sha256:
        return "network", "the route was measured with another network"
    net, srch = entry["network"], entry["search"]
    return entry["route"], (f"measured on {entry['shapes']} validation shapes at effort {entry['effort']}: "
                            f"network + refinement {net['mean']:.4f} in {net['s_per_shape']:.2f} s per shape, "
                            f"search {srch['mean']:.4f} in {srch['s_per_shape']:.2f} s per shape")
