"""The quality-time curve of a domain's effort levels: search from scratch and network + refinement.

For each effort level (:data:`plad.rewrite.EFFORTS`) this measures, on the same shapes, one process, one torch
thread, its CPU seconds per shape (``time.process_time``: what the process got of a core, so a busy machine
does not inflate it):

* ``search``: :func:`plad.rewrite.search` at the level (``plad search --effort LEVEL``);
* ``network``: the model's best of beam 1 and of beam 10 (no refinement);
* ``network + refinement``: the beam-10 programs refined as ``plad infer --effort LEVEL`` refines them
  (:func:`plad.serve.infer.refinement`); its seconds include the network's.

::

    python -m plad.tools.effort measure DOMAIN [--spaced 50] [--prepared data/prepared] [--model PATH]
        --out results/effort/DOMAIN.json
    python -m plad.tools.effort plot results/effort/*.json -o results/effort.png

``--model``: a checkpoint; default, the model ``plad infer`` would use (the shipped one where no MLflow
store is configured). Every value is the domain metric of the executed program.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from plad.data.pictures import save_figure
from plad.fsutil import atomic_write_text

#: beams of the network-only points
BEAMS = (1, 10)
#: shapes per batch of the network and its refinement
BATCH = 25


def measure(domain_name: str, targets: np.ndarray, model=None, levels=None) -> list[dict]:
    """Points of the curve for ``targets`` (N, *shape) bool: one dict per configuration with ``kind``
    (search | network | network + refinement), ``config`` (level or beam), ``mean`` (metric) and ``s_per_shape``
    (CPU seconds). ``model`` None: no network points."""
    from plad.domains import get_domain
    from plad.model.decode import infer_programs
    from plad.rewrite import EFFORTS, search, search_config
    from plad.serve.infer import refine_inferred, refinement

    domain = get_domain(domain_name)
    levels = list(levels or EFFORTS)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    n = len(targets)
    shapes = torch.from_numpy(targets)
    points: list[dict] = []

    def point(kind: str, config: str, values, seconds: float) -> None:
        values = torch.as_tensor(values, dtype=torch.float64)
        points.append({"kind": kind, "config": config, "mean": round(float(values.mean()), 6),
                       "s_per_shape": round(seconds / n, 5)})

    try:
        for level in levels:
            began = time.process_time()
            result = search(domain, shapes, search_config(domain, effort=level))
            point("search", level, result.values, time.process_time() - began)
        if model is None:
            return points
        model.eval()
        batches: list = []
        network_seconds = 0.0
        for beam in BEAMS:
            began = time.process_time()
            batches = [infer_programs(model, domain, shapes[i:i + BATCH], beam) for i in range(0, n, BATCH)]
            network_seconds = time.process_time() - began
            point("network", f"beam {beam}", torch.cat([b.values.cpu() for b in batches]), network_seconds)
        for level in levels:   # the last beam's programs (the widest), refined; its network time counted
            how = refinement(domain, level)
            began = time.process_time()
            refined = [refine_inferred(domain, b, shapes[i * BATCH:(i + 1) * BATCH], how)[1]
                       for i, b in enumerate(batches)]
            point("network + refinement", level, torch.cat(refined), time.process_time() - began + network_seconds)
    finally:
        torch.set_num_threads(threads)
    return points


KIND_STYLE = {"search": ("o-", "search from scratch"), "network": ("s--", "network alone (beam 1, 10)"),
              "network + refinement": ("^-", "network (beam 10) + refinement")}


def _read(path: Path) -> dict:
    """A file written by ``measure``; a missing or malformed one is a :class:`~plad.errors.BadInput` naming it."""
    from plad.errors import BadInput

    try:
        run = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise BadInput(f"{path}: not a readable effort file ({type(err).__name__}: {err})") from None
    missing = [k for k in ("domain", "metric", "higher_is_better", "shapes", "points")
               if not isinstance(run, dict) or k not in run]
    if missing:
        raise BadInput(f"{path}: not an effort file of `measure` (missing {', '.join(missing)})")
    return run


def plot(files: list[Path], out: Path) -> None:
    """One panel per measured domain: metric against CPU seconds per shape (log), a line per kind, each point
    labelled with its level or beam."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [_read(Path(f)) for f in files]
    fig, axes = plt.subplots(1, len(runs), figsize=(5 * len(runs), 4), squeeze=False)
    for ax, run in zip(axes[0], runs):
        for kind, (style, label) in KIND_STYLE.items():
            pts = [p for p in run["points"] if p["kind"] == kind]
            if not pts:
                continue
            xs, ys = [p["s_per_shape"] for p in pts], [p["mean"] for p in pts]
            ax.plot(xs, ys, style, label=label)
            for p in pts:
                ax.annotate(p["config"], (p["s_per_shape"], p["mean"]), fontsize=7, xytext=(3, 3),
                            textcoords="offset points")
        ax.set_xscale("log")
        ax.set_xlabel("CPU s per shape (one thread)")
        ax.set_ylabel(f"{run['metric']} ({'higher' if run['higher_is_better'] else 'lower'} is better)")
        ax.set_title(f"{run['domain']}: {run['shapes']} test shapes")
        ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out, dpi=110)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m plad.tools.effort", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    m = sub.add_parser("measure", help="measure one domain's curve")
    m.add_argument("domain")
    m.add_argument("--spaced", type=int, default=50, help="test shapes, evenly spaced over the split")
    m.add_argument("--prepared", default="data/prepared", help="folder of the prepared <domain>.npz")
    m.add_argument("--model", default=None, help="checkpoint (default: the model plad infer would use)")
    m.add_argument("--no-network", action="store_true", help="search points only")
    m.add_argument("--out", required=True)
    p = sub.add_parser("plot", help="draw measured curves")
    p.add_argument("files", nargs="+")
    p.add_argument("-o", "--out", required=True)
    args = parser.parse_args(argv)

    if args.command == "plot":
        from plad.errors import PladError

        try:
            plot([Path(f) for f in args.files], Path(args.out))
        except PladError as err:
            sys.exit(str(err))
        return
    from plad.data.files import load_split
    from plad.domains import domain_names, get_domain
    from plad.errors import PladError
    from plad.provenance import stamp

    if args.domain not in domain_names():
        sys.exit(f"unknown domain {args.domain!r}: expected one of {', '.join(domain_names())}")
    try:
        targets, _ = load_split(Path(args.prepared) / f"{args.domain}.npz", "test", args.spaced)
        model, model_ref = None, None
        if not args.no_network:
            from plad.serve.infer import resolve_model
            model, model_ref = resolve_model(args.domain, args.model, torch.device("cpu"))
            model_ref = model_ref.replace(f"{Path.cwd()}/", "")   # a committed file names no machine's folders
    except PladError as err:
        sys.exit(str(err))
    domain = get_domain(args.domain)
    torch.set_num_threads(1)    # as measure() runs, so that the file's provenance records the count it ran with
    started = time.monotonic()
    points = measure(args.domain, targets, model)
    report = {"domain": args.domain, "metric": domain.metric.name,
              "higher_is_better": domain.metric.higher_is_better, "shapes": int(len(targets)),
              "spaced": args.spaced, "model": model_ref, "points": points}
    report["provenance"] = stamp({k: report[k] for k in ("domain", "spaced", "model")}, started)
    atomic_write_text(Path(args.out), json.dumps(report, indent=1) + "\n")
    for pt in points:
        print(f"{args.domain} {pt['kind']} {pt['config']}: {pt['mean']:.4f} at {pt['s_per_shape']:.3f} s per shape")


if __name__ == "__main__":
    main()
