"""The report's tables (:mod:`plad.eval.report`), in markdown: the paper's Table 1 layout with the fine-tuning
runs and the P_BEST supplement, the rows beyond the paper, the amortization table, and where each column's numbers
come from (also as ``report.json``'s ``columns``). Rendering is a pure function of the gathered records
(:mod:`plad.eval.report_gather`)."""
from __future__ import annotations

import math
from collections.abc import Mapping

from plad.domains import get_domain
from plad.eval.report_gather import NOT_RECORDED, Column, MethodResult, Timed, amortization_keys
from plad.layout import FLOOR, SEARCH, split_effort
from plad.learn.method_registry import key_label

#: the rows that are no fine-tuning method; a method's label is what it declares (:func:`key_label`)
LABELS = {"sp": "SP", SEARCH: "search, no network", FLOOR: "floor"}

def label(key: str) -> str:
    if key in LABELS:
        return LABELS[key]
    if (declared := key_label(key)) is not None:
        return declared
    head, level = split_effort(key)
    if level is not None:
        return f"{label(head)}, effort {level}"
    if key.endswith("_refined"):
        return label(key[: -len("_refined")]) + " + test-time refinement"
    head, _, beam = key.rpartition("_beam")
    if head and beam.isdigit():
        return f"{label(head)}, beam {beam}"
    return key.replace("_per_round", " (per-round)").replace("_", "+").upper().replace("(PER-ROUND)", "(per-round)")

def floor_label(domains: list[str]) -> str:
    """The floor row's label: what each domain's floor is, e.g. ``Floor: one box (3D CSG, ShapeAssembly)``."""
    by: dict[str, list[str]] = {}
    for d in domains:
        name = get_domain(d).floor_name
        if name:
            by.setdefault(name, []).append(domain_title(d))
    return "Floor: " + ", ".join(f"{name} ({', '.join(titles)})" for name, titles in by.items())

def _hours(seconds: float) -> str:
    minutes = round(seconds / 60)
    return f"{minutes // 60} h {minutes % 60} min" if minutes >= 60 else f"{seconds / 60:.1f} min"


def _short(commit: str | None) -> str:
    return commit[:7] if commit and commit != NOT_RECORDED else (commit or NOT_RECORDED)

#: marks of a number in the tables (explained under the tables)
OTHER_COMMIT, BY_TIME = "*", "†"


def marks(columns: dict[str, Column] | None, domain: str, key: str) -> str:
    """The marks of result ``key`` in ``domain``'s column: another commit, stopped by time."""
    c = (columns or {}).get(domain)
    if c is None:
        return ""
    return (OTHER_COMMIT if key in c.others else "") + (BY_TIME if key in c.stopped_by_time else "")


def columns_markdown(columns: dict[str, Column], listed: list[str] | None = None) -> str:
    """Per column: its commit, the numbers from another commit, the stages' wall time, what stopped by time.

    ``listed``: the result keys named in the rows on other commits and stops (the floor always; default: all);
    the commit and the wall time count every number of the column.
    """
    domains = list(columns)
    named = None if listed is None else {*listed, FLOOR}

    def keys(found) -> list[str]:
        return [k for k in found if named is None or k in named]
    lines = ["## Where the numbers come from", "",
             f"Per column: the commit of its numbers (the one most of its files name; {OTHER_COMMIT}: a number "
             f"from another commit, or without one recorded), the wall time of the stages behind them (summed: "
             f"pretraining, fine-tuning, evaluations, search; the files that recorded it), and the "
             f"numbers a wall-clock limit shaped ({BY_TIME}, stopped by time: rerunning them on another machine "
             f"gives other numbers; the others are a function of code, params and data).", "",
             "| | " + " | ".join(domain_title(d) for d in domains) + " |", "|---|" + "---|" * len(domains)]

    def row(name: str, cell) -> None:
        lines.append(f"| {name} | " + " | ".join(cell(columns[d]) for d in domains) + " |")

    row("commit", lambda c: _short(c.commit) + (" (dirty)" if c.dirty else ""))
    row(f"{OTHER_COMMIT} from another commit",
        lambda c: ", ".join(f"{label(k)} ({', '.join(_short(x) for x in c.others[k])})" for k in keys(c.others))
        or "—")
    row("stages' wall time", lambda c: (f"{_hours(c.wall_seconds)} ({c.timed_files} of {c.files} files)"
                                        if c.timed_files else NOT_RECORDED))

    def stop(c: Column) -> str:
        parts = []
        if keys(c.stopped_by_time):
            parts.append(f"{BY_TIME} by time: " + ", ".join(label(k) for k in keys(c.stopped_by_time)))
        if keys(c.stop_unknown):
            parts.append("not recorded: " + ", ".join(label(k) for k in keys(c.stop_unknown)))
        return "; ".join(parts) or "work (every run ended on its epochs, rounds or patience)"

    row("stop", stop)
    return "\n".join(lines) + "\n"


def columns_json(columns: dict[str, Column]) -> dict[str, dict]:
    """The columns for ``report.json``: commit, other commits, wall time, stops, and each number's commits."""
    return {d: {"commit": c.commit, "dirty": c.dirty, "other_commits": c.others,
                "wall_seconds": round(c.wall_seconds, 1), "wall_seconds_files": [c.timed_files, c.files],
                "stopped_by_time": c.stopped_by_time, "stop_not_recorded": c.stop_unknown,
                "numbers": {k: {"commits": dict(r.commits), "stopped_by_time": r.stopped_by_time}
                            for k, r in c.records.items()}}
            for d, c in columns.items()}

# -- rendering ------------------------------------------------------------------------------------
# A domain declares how it is shown (display name, scale and digits of its metric) and the paper's
# numbers for it (plad.domains.base.Domain); the report only lays them out.
def _fmt(v: float | None, digits: int) -> str:
    return "—" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def _column(domain: str) -> tuple[str, float, int]:
    """(header, scale, digits) of a domain's metric column."""
    d = get_domain(domain)
    k = d.display_scale
    arrow = "higher is better" if d.metric.higher_is_better else "lower is better"
    name = f"{d.metric.name} x{k:g}" if k != 1 else d.metric.name
    return f"{d.display_name}: {name}, {arrow}", k, d.display_digits


def domain_title(domain: str) -> str:
    return get_domain(domain).display_name


def _paper(domain: str, per_round: bool = False) -> Mapping[str, float]:
    """The paper's numbers for ``domain`` (Table 1, or the supplement's per-round P_BEST), in display units."""
    d = get_domain(domain)
    return d.paper_per_round if per_round else d.paper_table

def table_markdown(results: dict[str, list[MethodResult]], methods: list[str], per_round: dict[str, str],
                   profile: str | None = None, floors: dict[str, float | None] | None = None,
                   columns: dict[str, Column] | None = None) -> str:
    """Table 1 layout: a row per method, per domain our value and the paper's; then times and P_BEST.

    ``floors`` (domain -> the floor baseline's test value) adds the row of the domains' floors (no paper value).
    ``columns`` (domain -> :class:`Column`) marks the numbers from another commit or stopped by time, with a
    note under the table when any is marked (:func:`columns_markdown` is the section that says more).
    """
    domains = list(results)
    by = {d: {r.key: r for r in rs} for d, rs in results.items()}
    lines = ["# Results" + (f" ({profile} profile)" if profile else ""), "",
             "Test sets, best of beam 10 by the domain metric. The paper's numbers (Table 1) are for reference.", ""]
    head, rule = "| method |", "|---|"
    for d in domains:
        title, _, _ = _column(d)
        head += f" {title} (ours) | paper |"
        rule += "---|---|"
    lines += [head, rule]
    for key in methods:
        row = f"| {label(key)} |"
        for d in domains:
            _, k, digits = _column(d)
            r = by[d].get(key)
            row += f" {_fmt(r.test * k if r and r.test is not None else None, digits)}{marks(columns, d, key)} |" \
                   f" {_fmt(_paper(d).get(key), digits)} |"
        lines.append(row)
    if floors and any(v is not None for v in floors.values()):
        row = f"| {floor_label(domains)} |"
        for d in domains:
            _, k, digits = _column(d)
            v = floors.get(d)
            row += f" {_fmt(v * k if v is not None else None, digits)}{marks(columns, d, FLOOR)} | — |"
        lines += [row, "", "The floor row is no method: the best program of a trivial family per test shape "
                  "(one primitive, or the tightest axis-aligned box), found without a network."]
    shown = [*methods, FLOOR, *per_round.values()]
    if any(marks(columns, d, k) for d in domains for k in shown):
        lines += ["", f"{OTHER_COMMIT}: a number from another commit than its column's; {BY_TIME}: stopped by time, "
                  f"a wall-clock limit shaped it (\"Where the numbers come from\", below)."]
    lines += ["", "## Fine-tuning runs", "",
              "| method | " + " | ".join(f"{domain_title(d)}: minutes, rounds (RL: epochs), training shapes, stop"
                                        for d in domains) + " |",
              "|---|" + "---|" * len(domains)]
    for key in [m for m in methods if m != "sp"] + [v for v in per_round.values() if v not in methods]:
        cells = []
        for d in domains:
            r = by[d].get(key)
            if r is None or r.train_seconds is None:
                cells.append("—")
            else:
                stop = f"{BY_TIME} stopped by time" if r.stopped_by_time else r.stopped
                shapes = "—" if r.train_shapes is None else f"{r.train_shapes:,}"
                cells.append(f"{r.train_seconds / 60:.1f} min, {r.rounds}, {shapes}, {stop}")
        lines.append(f"| {label(key)} | " + " | ".join(cells) + " |")
    if per_round:
        lines += ["", "## P_BEST: all-time vs per-round (supplement)", ""]
        for d in domains:
            _, k, digits = _column(d)
            ref, paper = _paper(d, per_round=True), _paper(d)
            lines += [f"{domain_title(d)}:", "",
                      "| method | all-time (ours) | per-round (ours) | all-time (paper) | per-round (paper) |",
                      "|---|---|---|---|---|"]
            for a, b in per_round.items():
                ra, rb = by[d].get(a), by[d].get(b)
                va = ra.test * k if ra and ra.test is not None else None
                vb = rb.test * k if rb and rb.test is not None else None
                lines.append(f"| {label(a)} | {_fmt(va, digits)}{marks(columns, d, a)} | "
                             f"{_fmt(vb, digits)}{marks(columns, d, b)} | "
                             f"{_fmt(paper.get(a), digits)} | {_fmt(ref.get(a), digits)} |")
            lines.append("")
    return "\n".join(lines).rstrip("\n") + "\n"

def _seconds(v: float | None) -> str:
    if v is None:
        return "—"
    return f"{v * 1000:.1f} ms" if v < 1 else f"{v:.2f} s"

def missing_note(missing: list[str]) -> list[str]:
    return [f"Not computed (no metrics.json): {', '.join(missing)}.", ""] if missing else []

def beyond_markdown(rows: dict[str, dict[str, Timed | None]], keys: list[str],
                    columns: dict[str, Column] | None = None) -> str:
    """The rows beyond the paper: per domain our value and seconds per shape (no paper number exists); marked as
    :func:`table_markdown` marks its numbers."""
    domains = list(rows)
    lines = ["## Beyond the paper: search beside learning", "",
             "Not in the paper: search from scratch without a network, LEST+ST+WS trained on a P_BEST seeded and "
             "rewritten by search, and the same with test-time refinement of the beam's outputs. Test sets, "
             "wall-clock seconds per shape on this machine.", ""]
    head, rule = "| method |", "|---|"
    for d in domains:
        title, _, _ = _column(d)
        head += f" {title} | s per shape |"
        rule += "---|---|"
    lines += [head, rule]
    missing = []
    for key in keys:
        row = f"| {label(key)} |"
        for d in domains:
            _, k, digits = _column(d)
            t = rows[d].get(key)
            if t is None:
                missing.append(f"{d}/{key}")
            row += f" {_fmt(t.test * k if t else None, digits)}{marks(columns, d, key) if t else ''} |" \
                   f" {_seconds(t.seconds_per_shape if t else None)} |"
        lines.append(row)
    lines.append("")
    lines += missing_note(missing)
    return "\n".join(lines)

def amortization_markdown(points: dict[str, dict[str, Timed | None]], method: str, beams: list[int],
                          profile: str | None = None, efforts: list[str] | tuple[str, ...] = ()) -> str:
    """Metric against seconds per shape, per domain: network only (each beam), network + refinement, search only,
    and both of those at each effort level."""
    keys = amortization_keys(method, beams, efforts)
    lines = ["# Amortization: metric against seconds per shape" + (f" ({profile} profile)" if profile else ""), "",
             f"The network is {label(method)}'s model; refinement rewrites its best-of-beam program "
             f"(beam of the evaluation stage); search starts from scratch. Wall-clock seconds per shape on this "
             f"machine (a shared machine's numbers include waiting for a core).", ""]
    if efforts:
        lines += [f"At each effort level ({', '.join(efforts)}): search as `plad search --effort LEVEL` searches, "
                  f"and the network's beam refined as `plad infer --effort LEVEL` refines it (at `best`, every "
                  f"candidate of the beam, the best kept).", ""]
    lines += ["\"x search\" is how many times faster than search only a configuration is (search's seconds per "
              "shape over its own).", ""]
    missing = []
    for d, got in points.items():
        title, k, digits = _column(d)
        search = got.get(SEARCH)
        lines += [f"## {domain_title(d)}", "",
                  f"| configuration | {title} | s per shape | x search | network | refinement |",
                  "|---|---|---|---|---|---|"]
        for key, kind in keys:
            t = got.get(key)
            if t is None:
                missing.append(f"{d}/{key}")
                continue
            faster = (f"{search.seconds_per_shape / t.seconds_per_shape:.1f}"
                      if search is not None and t.seconds_per_shape > 0 else "—")
            lines.append(f"| {label(key)} ({kind}) | {_fmt(t.test * k, digits)} | {_seconds(t.seconds_per_shape)} | "
                         f"{faster} | {_seconds(t.network_seconds_per_shape)} | "
                         f"{_seconds(t.refine_seconds_per_shape)} |")
        lines.append("")
    lines += missing_note(missing)
    return "\n".join(lines).rstrip("\n") + "\n"
