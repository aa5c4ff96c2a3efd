"""The report's pictures (:mod:`plad.eval.report`), with matplotlib (imported only here, when a picture is drawn):
the convergence curves of the fine-tunings and the amortization picture (metric against seconds per shape)."""
from __future__ import annotations

import io
from pathlib import Path

from plad.domains import get_domain
from plad.eval.report_gather import MethodResult, Timed, amortization_keys
from plad.eval.report_tables import domain_title, label
from plad.fsutil import atomic_write
from plad.layout import SEARCH, eval_key, search_key, split_effort


def convergence_png(results: dict[str, list[MethodResult]], path: str | Path) -> None:
    """Validation metric (best so far) against fine-tuning wall-clock time: a panel per domain, a line per method."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = max(1, len(results))
    fig, axes = plt.subplots(1, n, figsize=(6.5 * n, 4.5), dpi=110, squeeze=False)
    for ax, (domain, rs) in zip(axes[0], results.items()):
        metric = get_domain(domain).metric
        k = get_domain(domain).display_scale
        start = None
        for r in rs:
            if len(r.curve) < 2:
                continue
            t, v = zip(*r.curve)
            start = v[0]
            best, shown = [], None
            for x in v:   # the selected model so far, as used for the table
                shown = x if shown is None or metric.better(x, shown) else shown
                best.append(shown * k)
            ax.step([s / 60 for s in t], best, where="post", label=label(r.key), marker="o", markersize=3)
        if start is not None:
            ax.axhline(start * k, color="grey", linestyle=":", label="SP (start)")
        ax.set_xlabel("fine-tuning wall-clock time (min)")
        ax.set_ylabel(f"validation {metric.name}" + (f" x{k:g}" if k != 1 else "") + " (best so far)")
        ax.set_title(domain_title(domain))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    atomic_write(path, lambda fh: fh.write(buf.getvalue()))

def amortization_png(points: dict[str, dict[str, Timed | None]], method: str, beams: list[int],
                     path: str | Path, efforts: list[str] | tuple[str, ...] = ()) -> None:
    """A panel per domain: metric (y) against seconds per shape (x, log), a marker per configuration; the beams
    of the network, and the effort levels of search and of network + refinement, each joined as a curve."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = max(1, len(points))
    fig, axes = plt.subplots(1, n, figsize=(6 * n, 4.5), dpi=110, squeeze=False)
    style = {"network": ("o", "C0"), "network + refinement": ("s", "C1"), "search only": ("^", "C2")}
    for ax, (d, got) in zip(axes[0], points.items()):
        metric, k = get_domain(d).metric, get_domain(d).display_scale
        net = [(t.seconds_per_shape, t.test * k, b) for b in beams
               if (t := got.get(eval_key(method, beam=b))) is not None]
        if net:
            ax.plot([x for x, _, _ in net], [y for _, y, _ in net], "-", color="C0", alpha=0.5)
            for x, y, b in net:
                ax.annotate(f"beam {b}", (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
        for keyed, color in ((lambda lv: search_key(lv), "C2"), (lambda lv: eval_key(method, effort=lv), "C1")):
            curve = [(t.seconds_per_shape, t.test * k, lv) for lv in efforts if (t := got.get(keyed(lv))) is not None]
            if len(curve) > 1:
                ax.plot([x for x, _, _ in curve], [y for _, y, _ in curve], "--", color=color, alpha=0.5)
            for x, y, lv in curve:
                ax.annotate(lv, (x, y), textcoords="offset points", xytext=(4, -10), fontsize=7, color=color)
        labelled = set()
        for key, kind in amortization_keys(method, beams, efforts):
            t = got.get(key)
            if t is not None:
                marker, color = style[kind]
                head, level = split_effort(key)
                # one legend entry per curve: search's levels are one, refinement's levels another
                name = (f"{label(method)}, network only" if kind == "network" else
                        label(head) + (", effort levels" if level and head != SEARCH else ""))
                ax.scatter([t.seconds_per_shape], [t.test * k], marker=marker, color=color, zorder=3,
                           label=None if name in labelled else name)
                labelled.add(name)
        ax.set_xscale("log")
        ax.set_xlabel("wall-clock seconds per shape (log)")
        ax.set_ylabel(f"test {metric.name}" + (f" x{k:g}" if k != 1 else "") +
                      (" (higher is better)" if metric.higher_is_better else " (lower is better)"))
        ax.set_title(domain_title(d))
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
        else:
            ax.text(0.5, 0.5, "no results yet", ha="center", va="center", transform=ax.transAxes)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    atomic_write(path, lambda fh: fh.write(buf.getvalue()))
