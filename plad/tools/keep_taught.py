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
import subprocess
import sys
from pathlib import Path


def shipping_commit(path: Path) -> str:
    """The short hash of the last commit that changed ``path`` (git), or "unknown" outside a checkout."""
    try:
        out = subprocess.run(["git", "log", "-1", "--format=%h", "--", path.name], cwd=path.parent,
                             capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return out or "unknown"


def keep(domain: str, folder: Path | None = None, commit: str | None = None) -> dict:
    """:func:`plad.shipped.keep_taught`, the commit named by git where ``commit`` is not given."""
    from plad.shipped import keep_taught, shipped_dir

    folder = Path(folder) if folder is not None else shipped_dir()
    return keep_taught(domain, commit or shipping_commit(folder / domain / "model.pt"), folder)


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
