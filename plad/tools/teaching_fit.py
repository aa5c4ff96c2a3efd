"""The fit of a taught network beside its validation, against CPU hours of teaching (issue 58).

Reads the histories of teach runs (``runs/finetune/<domain>/taught/history.csv``: one row per epoch, row 0
the starting network; or the committed summary ``results/finetune/<domain>/taught.json``, whose ``history``
holds the epochs after the start with their cumulative seconds, so the plot survives a lost DVC cache) and
draws, per run, the metric on a fixed sample of labelled training shapes (``fit``:
greedy, ``fit_wide``: beam 10) and on the validation shapes (``val``) against the hours of the epochs
(their own seconds summed: training and measuring, one thread), one panel per domain, with the labels' own
metric on the fit sample (the ceiling, from the run's ``summary.json``) as a dotted line::

    python -m plad.tools.teaching_fit -o docs/teaching-fit.png runs/finetune/*/taught/history.csv
    python -m plad.tools.teaching_fit -o docs/teaching-fit.png results/finetune/*/taught.json

Several runs of one domain share its panel, one colour each, named by the sizes their start was grown to;
``--against epoch`` draws them at equal steps instead of equal hours. A run that continues a kept taught network
(``init: taught``) is drawn after the run listed before it for its domain (its hours and epochs added to that
run's last), as the earlier run of its kept network: list them in that order, e.g. the committed summary of the
earlier run (``git show <commit>:results/finetune/<domain>/taught.json``) before today's.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path

from plad.data.pictures import save_figure

#: the curves of a history, with their line styles
CURVES = (("fit", "fit: labelled training shapes, beam 1", "-"),
          ("fit_wide", "fit: labelled training shapes, beam 10", "--"),
          ("val", "validation", ":"))


def curve(history: Path) -> dict[str, list[float]]:
    """``{"hours", "epoch", "fit", "fit_wide", "val"}`` of one teach history (a missing value: NaN)."""
    if history.suffix == ".json":
        return summary_curve(history, read_summary(history))
    try:
        with history.open(newline="") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as err:
        raise ValueError(f"{history}: cannot read ({err.strerror})") from None
    if not rows or "unit" not in rows[0] or "val" not in rows[0]:
        raise ValueError(f"{history}: not a teach history (no unit and val columns)")

    def number(row: dict, key: str) -> float:
        try:
            return float(row.get(key) or "nan")
        except ValueError:
            return math.nan

    out: dict[str, list[float]] = {"hours": [], "epoch": [], "fit": [], "fit_wide": [], "val": []}
    total = 0.0
    for row in rows:
        seconds = number(row, "unit_seconds")
        total += 0.0 if math.isnan(seconds) else seconds
        out["hours"].append(total / 3600)
        out["epoch"].append(number(row, "unit"))
        for key in ("fit", "fit_wide", "val"):
            out[key].append(number(row, key))
    return out


def read_summary(path: Path, history: bool = True) -> dict:
    """A teach run's summary json, with its ``history`` list unless ``history`` is false (``ValueError``
    naming the file when it cannot be read as one)."""
    try:
        summary = json.loads(path.read_text())
    except OSError as err:
        raise ValueError(f"{path}: cannot read ({err.strerror})") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not JSON ({err.msg}, line {err.lineno})") from None
    if not isinstance(summary, dict) or (history and not isinstance(summary.get("history"), list)):
        raise ValueError(f"{path}: not a teach summary (no history list)")
    return summary


def load_run(path: Path) -> tuple[str, dict[str, list[float]], dict]:
    """(domain, curve, summary) of a committed summary ``results/finetune/<domain>/taught.json`` or of a run's
    ``runs/finetune/<domain>/taught/history.csv`` (its summary: the ``summary.json`` beside it, if any)."""
    if path.suffix == ".json":
        summary = read_summary(path)
        return summary.get("domain") or path.parent.name, summary_curve(path, summary), summary
    beside = path.parent / "summary.json"
    summary = read_summary(beside, history=False) if beside.exists() else {}
    return summary.get("domain") or path.parent.parent.name, curve(path), summary


def summary_curve(path: Path, summary: dict) -> dict[str, list[float]]:
    """The curve of a summary's ``history``: epochs 1.. (the start is not in it), ``seconds`` cumulative."""
    out: dict[str, list[float]] = {"hours": [], "epoch": [], "fit": [], "fit_wide": [], "val": []}
    for epoch, row in enumerate(summary["history"], start=1):
        if not isinstance(row, dict) or "val" not in row or "seconds" not in row:
            raise ValueError(f"{path}: history row {epoch} has no val and seconds")
        out["hours"].append(float(row["seconds"]) / 3600)
        out["epoch"].append(float(epoch))
        for key in ("fit", "fit_wide", "val"):
            value = row.get(key)
            out[key].append(math.nan if value is None else float(value))
    return out


def run_name(summary: dict) -> str:
    """How a run is told apart from others of its domain in one panel: the sizes its start was grown to
    (``teach.<domain>.grow``), else the start's own size, and those of a second segment (``then``)."""
    def sizes(grow: dict) -> str:
        return ", ".join(f"{k} {'-'.join(map(str, v)) if isinstance(v, list) else v}" for k, v in grow.items())

    grow = summary.get("grow")
    name = "grown: " + sizes(grow) if grow else "the start's size"
    if summary.get("init") == "taught":
        name = "continued, " + name
    then = summary.get("then")
    if isinstance(then, dict) and then.get("grow"):
        name += "; then " + sizes(then["grow"])
    return name


def continued(runs: list[tuple[str, dict, dict]]) -> list[tuple[str, dict, dict]]:
    """``runs`` with each run that starts from a kept taught network (``init: taught``) moved to after the run
    listed before it for its domain: its hours and epochs plus that run's last (as drawn, so chains add up)."""
    out: list[tuple[str, dict, dict]] = []
    for domain, c, summary in runs:
        before = [prev for d, prev, _ in out if d == domain]
        if summary.get("init") == "taught" and before and before[-1]["epoch"]:
            last = before[-1]
            c = {**c, "hours": [h + last["hours"][-1] for h in c["hours"]],
                 "epoch": [e + last["epoch"][-1] for e in c["epoch"]]}
        out.append((domain, c, summary))
    return out


def plot(histories: list[Path], output: Path, against: str = "hours") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = continued([load_run(h) for h in histories])
    domains = sorted({d for d, _, _ in runs})
    shared = any(sum(d == domain for d, _, _ in runs) > 1 for domain in domains)
    fig, axes = plt.subplots(1, len(domains), figsize=(5.2 * len(domains), 6.0 if shared else 4.2), squeeze=False)
    for ax, domain in zip(axes[0], domains):
        mine = [(c, summary) for d, c, summary in runs if d == domain]
        ceilings = set()
        for i, (c, summary) in enumerate(mine):
            # one colour per run where several share the panel (e.g. a grown start beside the start's size)
            prefix, color = (f"{run_name(summary)}: ", f"C{i}") if len(mine) > 1 else ("", None)
            for key, label, style in CURVES:
                ax.plot(c[against], c[key], style, marker="o", markersize=3, label=prefix + label, color=color)
            ceiling = summary.get("fit_labels_mean")
            if ceiling is not None and ceiling not in ceilings:
                ceilings.add(ceiling)
                ax.axhline(ceiling, color="gray", linestyle="dotted", label=f"labels on the fit sample ({ceiling:.3f})")
            ax.set_ylabel(summary.get("metric", "metric"))
        ax.set_title(f"{domain}: taught by search labels")
        ax.set_xlabel("hours of teaching (one thread, wall clock)" if against == "hours" else "epochs of teaching")
        ax.grid(alpha=0.3)
        if len(mine) == 1:
            ax.legend(fontsize=7)
        else:   # several runs' long names: under the panel, not over its curves
            ax.legend(fontsize=6, loc="upper center", bbox_to_anchor=(0.5, -0.16))
    fig.tight_layout()
    save_figure(fig, output, dpi=110)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("histories", nargs="+", type=Path)
    parser.add_argument("-o", "--output", type=Path, required=True)
    parser.add_argument("--against", choices=("hours", "epoch"), default="hours",
                        help="the x axis: hours of teaching (default) or epochs (equal steps)")
    args = parser.parse_args(argv)
    try:
        plot(args.histories, args.output, args.against)
    except ValueError as err:
        print(err, file=sys.stderr)
        return 1
    print(args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
