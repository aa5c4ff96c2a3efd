"""What hours of pretraining buy: the real-validation metric against cumulative training hours.

Reads pretraining histories (``runs/pretrain/<domain>/history.csv``, every segment of a continued run in
one file; the hours are the epochs' own seconds summed, so the time of validation is counted and idle time
between segments is not) and draws one curve per run, one panel per domain::

    python -m plad.eval.pretraining -o docs/pretraining-hours.png \\
        "LABEL=runs/pretrain/DOMAIN/history.csv" ...

The hours are those of the process: with one thread each, CPU hours.
"""
from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

from plad.fsutil import atomic_write


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
    return out


def plot(runs: dict[str, Path], out: Path, metric: str = "real_val_iou") -> None:
    """One panel per metric family (real validation, synthetic validation), one line per run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for label, path in runs.items():
        c = curve(path)
        synthetic = metric.replace("real_val_", "val_")
        if metric in c:
            axes[0].plot(c["hours"], c[metric], label=label)
        if synthetic in c:
            axes[1].plot(c["hours"], c[synthetic], label=label)
    for ax, title in zip(axes, (f"{metric} (greedy, real validation shapes)",
                                f"{metric.replace('real_val_', 'val_')} (greedy, synthetic validation programs)")):
        ax.set_xlabel("training hours (one thread)")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    atomic_write(out, lambda fh: fig.savefig(fh, format="png", dpi=110))
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="LABEL=PATH of a history.csv")
    parser.add_argument("-o", "--out", required=True, type=Path, help="the PNG to write")
    parser.add_argument("--metric", default="real_val_iou", help="the real-validation column (default real_val_iou)")
    args = parser.parse_args(argv)
    runs = {}
    for item in args.runs:
        label, sep, path = item.rpartition("=")
        if not sep:
            parser.error(f"{item!r}: expected LABEL=PATH")
        runs[label] = Path(path)
    try:
        plot(runs, args.out, args.metric)
        for label, path in runs.items():
            c = curve(path)
            values = c.get(args.metric, [float("nan")] * len(c["epoch"]))
            best = max(range(len(values)), key=lambda i: values[i] if values[i] == values[i] else -1e9)
            print(f"{label}: {len(values)} epochs, {c['hours'][-1]:.2f} h; best {args.metric} {values[best]:.4f} "
                  f"at epoch {c['epoch'][best]:.0f} ({c['hours'][best]:.2f} h)")
    except ValueError as err:
        print(f"plad.eval.pretraining: error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
