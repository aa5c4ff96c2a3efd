"""What hours of pretraining buy: the real-validation metric against cumulative training hours.

Reads pretraining histories (``runs/pretrain/<domain>/history.csv``, every segment of a continued run in
one file; the hours are the epochs' own seconds summed, so the time of validation is counted and idle time
between segments is not) and draws one curve per run, one panel per domain::

    python -m plad.tools.pretraining_hours -o docs/pretraining-hours.png \\
        "LABEL=runs/pretrain/DOMAIN/history.csv" ...

The hours are those of the process: with one thread each, CPU hours; a segment that ran on a GPU counts its
own (far fewer) hours. ``--x shapes`` puts the synthetic shapes seen on the x axis instead, from the
``provenance.json`` beside the history (its segments' epochs and shapes seen): the axis on which a CPU
segment and a GPU segment of other batch sizes compare.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path

from plad.data.pictures import save_figure


def curve(history: Path) -> dict[str, list[float]]:
    """``{"hours", "epoch", <every real_val_/val_ column>}`` of one history file (rows without the column: NaN)."""
    try:
        rows = list(csv.DictReader(history.open()))
    except OSError as err:
        raise ValueError(f"{history}: cannot read ({err.strerror})") from None
    if not rows or "epoch_seconds" not in rows[0]:
        raise ValueError(f"{history}: not a pretraining history (no epoch_seconds column)")
    out: dict[str, list[float]] = {"hours": [], "epoch": []}
    total = 0.0
    metrics = [k for k in rows[0] if k.startswith(("real_val_", "val_")) or k == "prefix_gap"]
    for row in rows:
        total += float(row["epoch_seconds"])
        out["hours"].append(total / 3600)
        out["epoch"].append(float(row["epoch"]))
        for k in metrics:
            out.setdefault(k, []).append(float(row[k]) if row.get(k) not in (None, "") else float("nan"))
    shapes = shapes_seen(history, out["epoch"])
    if shapes is not None:
        out["shapes"] = shapes
    return out


def shapes_seen(history: Path, epochs: list[float]) -> list[float] | None:
    """Cumulative synthetic shapes seen (millions) at the end of each epoch, from the segments of the
    ``provenance.json`` beside ``history`` (a segment's shapes spread evenly over its epochs); None where there
    is no such file. An epoch no segment covers is NaN."""
    path = history.parent / "provenance.json"
    if not path.exists():
        return None
    try:
        segments = json.loads(path.read_text())["segments"]
        per_epoch = {}
        for seg in segments:
            first, last = seg["epochs"]
            for e in range(first, last + 1):
                per_epoch[e] = seg["shapes_seen"] / (last - first + 1)
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path}: not a pretraining provenance ({err})") from None
    total, out = 0.0, []
    for e in epochs:
        if int(e) not in per_epoch:
            out.append(math.nan)
            continue
        total += per_epoch[int(e)]
        out.append(total / 1e6)
    return out


def best_epoch(column: str, values: list[float]) -> int:
    """The index of a history column's best value (``real_val_<metric>``, ``val_<metric>``) in its metric's
    direction (Chamfer: lowest; another column: highest); NaN epochs never win, the first wins ties."""
    from plad.metrics import IOU, chamfer_metric

    name = column.rsplit("_", 1)[-1]
    metric = next((m for m in (IOU, chamfer_metric()) if m.name == name), IOU)
    best = metric.best_value(values)
    return 0 if best is None else values.index(best)


X_LABELS = {"hours": "training hours (one CPU thread; a GPU segment its own hours)",
            "shapes": "synthetic shapes seen (millions)"}


def plot(runs: dict[str, Path], out: Path, metric: str = "real_val_iou", x: str = "hours") -> None:
    """One panel per metric family (real validation, synthetic validation), one line per run, against
    ``x``: ``hours`` or ``shapes`` (every run needs its ``provenance.json`` for that)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for label, path in runs.items():
        c = curve(path)
        if x not in c:
            raise ValueError(f"{path}: no provenance.json beside it, so no shapes seen to plot against")
        synthetic = metric.replace("real_val_", "val_")
        if metric in c:
            axes[0].plot(c[x], c[metric], label=label)
        if synthetic in c:
            axes[1].plot(c[x], c[synthetic], label=label)
    for ax, title in zip(axes, (f"{metric} (greedy, real validation shapes)",
                                f"{metric.replace('real_val_', 'val_')} (greedy, synthetic validation programs)")):
        ax.set_xlabel(X_LABELS[x])
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out, dpi=110)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="LABEL=PATH of a history.csv")
    parser.add_argument("-o", "--out", required=True, type=Path, help="the PNG to write")
    parser.add_argument("--metric", default="real_val_iou", help="the real-validation column (default real_val_iou)")
    parser.add_argument("--x", choices=sorted(X_LABELS), default="hours",
                        help="the x axis: training hours (default) or synthetic shapes seen (needs provenance.json)")
    args = parser.parse_args(argv)
    runs = {}
    for item in args.runs:
        label, sep, path = item.rpartition("=")
        if not sep:
            parser.error(f"{item!r}: expected LABEL=PATH")
        runs[label] = Path(path)
    try:
        plot(runs, args.out, args.metric, args.x)
        for label, path in runs.items():
            c = curve(path)
            values = c.get(args.metric, [float("nan")] * len(c["epoch"]))
            best = best_epoch(args.metric, values)
            seen = f", {c['shapes'][-1]:.2f} M shapes" if "shapes" in c else ""
            print(f"{label}: {len(values)} epochs, {c['hours'][-1]:.2f} h{seen}; best {args.metric} {values[best]:.4f} "
                  f"at epoch {c['epoch'][best]:.0f} ({c['hours'][best]:.2f} h)")
    except ValueError as err:
        print(f"plad.tools.pretraining_hours: error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
