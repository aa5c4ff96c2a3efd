"""Keep the shipped taught network of a domain as the start of a longer teaching run (issue 58).

``teach.<domain>.init: taught`` starts from ``plad/shipped/<domain>/taught.pt``, a copy of a shipped taught
network indexed with its sha256 and the commit that shipped it in ``plad/shipped/taught.json``
(:func:`plad.shipped.kept_checkpoint`). A network is only ever shipped from a finished run, so a run that starts
from its kept copy continues it on any clone without training the earlier runs again. This copies the shipped
model there (a maintainer's step, before params.yaml names ``init: taught`` for a new continuation; the teach@
stage that starts from the kept copy depends on it, so replacing it makes that stage stale)::

    python -m plad.tools.keep_taught DOMAIN [--commit HASH]

``--commit`` names the commit that shipped the model (default: git's last commit touching it).
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

from plad.fsutil import atomic_write, atomic_write_text, sha256_file


def shipping_commit(path: Path) -> str:
    """The short hash of the last commit that changed ``path`` (git), or "unknown" outside a checkout."""
    try:
        out = subprocess.run(["git", "log", "-1", "--format=%h", "--", path.name], cwd=path.parent,
                             capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return out or "unknown"


def keep(domain: str, folder: Path | None = None, commit: str | None = None) -> dict:
    """Copy the shipped taught model of ``domain`` to ``<domain>/taught.pt`` and index it; returns the entry.

    ShipError when there is no shipped model, it differs from its sidecar or it is not a taught network."""
    from plad.shipped import KEPT_STARTS, ShipError, shipped_dir, shipped_model

    folder = Path(folder) if folder is not None else shipped_dir()
    shipped = shipped_model(domain, folder)
    if shipped is None:
        raise ShipError(f"{folder / domain}: no shipped model to keep")
    shipped.verify()
    if shipped.info.get("method") != "taught":
        raise ShipError(f"{shipped.checkpoint}: method {shipped.info.get('method')!r}, not a taught network")
    target = folder / domain / "taught.pt"
    with shipped.checkpoint.open("rb") as src:
        atomic_write(target, lambda out: shutil.copyfileobj(src, out))
    index_path = folder / KEPT_STARTS["taught"]
    index = json.loads(index_path.read_text()) if index_path.exists() else {"format": "plad-taught-1", "models": {}}
    metrics = shipped.info.get("metrics") or {}
    entry = {"file": f"{domain}/taught.pt", "sha256": sha256_file(target),
             "from": shipped.info["checkpoint"].get("shipped_from"),
             "shipped_as": f"plad/shipped/{domain}/model.pt at {commit or shipping_commit(shipped.checkpoint)}",
             "test": {k: metrics[k] for k in ("metric", "beam", "mean", "n") if k in metrics}}
    index["models"] = {**index.get("models", {}), domain: entry}
    atomic_write_text(index_path, json.dumps(index, indent=1) + "\n")
    return entry


def main(argv: list[str] | None = None) -> None:
    from plad.shipped import ShipError

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("domain")
    parser.add_argument("--commit", default=None, help="the commit that shipped the model (default: git's)")
    args = parser.parse_args(argv)
    try:
        print(json.dumps(keep(args.domain, commit=args.commit), indent=1))
    except ShipError as err:
        sys.exit(f"keep_taught: {err}")


if __name__ == "__main__":
    main()
