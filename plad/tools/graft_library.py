"""Build a grafting library (:mod:`plad.rewrite.graft`): search programs for evenly spaced training shapes and
keep every sub-expression, one per distinct execution, as SIRI's cache of P_BEST's sub-expressions.

``python -m plad.tools.graft_library DOMAIN --prepared data/prepared`` writes the domain's own library
(``plad/domains/<domain>/graft_library.npz``, package data), which ``refine.graft_library: shipped`` grafts from.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m plad.tools.graft_library DOMAIN``: search programs for evenly spaced training shapes and
    write the library of their sub-expressions (default: the domain's own library)."""
    import argparse
    import time

    from plad.config import ConfigError
    from plad.data.files import DataError, load_split
    from plad.domains import get_domain
    from plad.rewrite.driver import search, search_config
    from plad.rewrite.graft import shipped_library, sub_expressions

    parser = argparse.ArgumentParser(prog="python -m plad.tools.graft_library", description=main.__doc__)
    parser.add_argument("domain")
    parser.add_argument("--prepared", default="data/prepared", help="folder of the prepared <domain>.npz")
    parser.add_argument("--split", default="train")
    parser.add_argument("--spaced", type=int, default=2000, help="shapes, evenly spaced over the split")
    parser.add_argument("--effort", default="fast", help="the search's effort level")
    parser.add_argument("--out", default=None,
                        help="the library file (default: the domain's own, plad/domains/<domain>/graft_library.npz)")
    args = parser.parse_args(argv)
    domain = get_domain(args.domain)
    if not (domain.rewrite is not None and domain.rewrite.grafts):
        raise SystemExit(f"{args.domain}: the domain has no expression tree of boolean operators to graft into")
    path = Path(args.prepared) / f"{args.domain}.npz"
    if not path.is_file():
        raise SystemExit(f"{path}: no such prepared dataset (run the prepare stages first)")
    try:
        shapes, index = load_split(path, args.split, args.spaced)
    except DataError as err:
        raise SystemExit(str(err)) from None
    torch.set_num_threads(1)
    began = time.process_time()
    try:
        # the batch's programs only, never a library already shipped: the file is a function of the shapes and
        # the effort level, not of an earlier version of itself
        config = search_config(domain, effort=args.effort, **{"refine.graft_library": None})
    except ConfigError as err:
        raise SystemExit(str(err)) from None
    result = search(domain, torch.from_numpy(shapes).bool(), config)
    library = sub_expressions(domain, result.programs)
    out = shipped_library(domain) if args.out is None else Path(args.out)
    library.save(out, domain)
    print(f"{out}: {len(library)} sub-expressions of the programs found for {len(index)} {args.split} shapes "
          f"(search {args.effort}, mean {domain.metric.name} {float(result.values.mean()):.4f}, "
          f"{time.process_time() - began:.0f} CPU s)")


if __name__ == "__main__":
    main()


__all__ = ["main"]
