"""``plad data check | download``: the real datasets, checked or downloaded (:mod:`plad.serve.cli`)."""
from __future__ import annotations

import argparse
import sys
from typing import Any


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


def add_parser(sub: Any) -> None:
    """The ``data`` command of ``plad``."""
    p = sub.add_parser("data", help="check or download the real datasets",
                       description="Check (found, verified, split sizes) or download the real datasets.")
    p.add_argument("action", choices=["check", "download"])
    p.add_argument("--data-dir", default=None, help="data directory (default: $PLAD_DATA_DIR or ./data/datasets)")
    p.set_defaults(func=cmd_data)
