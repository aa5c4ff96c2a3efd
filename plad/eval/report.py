"""The results report: the paper's Table 1 layout, convergence curves, the P_BEST ablation.

Beyond the paper: rows with search (search only, a search-seeded P_BEST,
test-time refinement) with their seconds per shape, and the amortization
picture (metric against seconds per shape). These come from the evaluation
files only (:class:`Timed`); a missing one is named in the report, never an
error, so a profile or a partial run without them still gets its report.

Inputs are gathered per method either from the pipeline's files (the
evaluation ``metrics.json`` and fine-tuning ``state.json``/``summary.json``)
or from MLflow alone (the ``evaluate`` and ``finetune`` runs' metrics), into
the same :class:`MethodResult` records, so the report can be rebuilt from
either. Rendering is a pure function of those records.

Where each column's numbers come from (:class:`Column`, from the files'
``provenance`` blocks, :mod:`plad.provenance`; files only, whatever the
source): the commit most of them were computed at, the numbers from another
commit (or with none recorded), the stages' wall time, and the results a
wall-clock limit shaped ("stopped by time"). The tables mark those numbers.

The report is three modules, whose public names are all importable from here (the report stage's entry points,
:mod:`plad.stages.report`): :mod:`plad.eval.report_gather` (the records, from the files or MLflow; where the
numbers come from), :mod:`plad.eval.report_tables` (the markdown tables, ``report.json``'s columns) and
:mod:`plad.eval.report_pictures` (the convergence and amortization pictures).
"""
from __future__ import annotations

from plad.eval.report_gather import (
    NOT_RECORDED,
    Column,
    MethodResult,
    NumberRecord,
    Timed,
    amortization_keys,
    column,
    domain_experiments,
    floor_from_files,
    floor_from_mlflow,
    from_files,
    from_mlflow,
    number_record,
    timed_from_files,
    wall_totals,
)
from plad.eval.report_pictures import amortization_png, convergence_png
from plad.eval.report_tables import (
    BY_TIME,
    LABELS,
    OTHER_COMMIT,
    amortization_markdown,
    beyond_markdown,
    columns_json,
    columns_markdown,
    domain_title,
    floor_label,
    label,
    marks,
    missing_note,
    table_markdown,
)

__all__ = [
    "BY_TIME", "LABELS", "NOT_RECORDED", "OTHER_COMMIT", "Column", "MethodResult", "NumberRecord", "Timed",
    "amortization_keys", "amortization_markdown", "amortization_png", "beyond_markdown", "column", "columns_json",
    "columns_markdown", "convergence_png", "domain_experiments", "domain_title", "floor_from_files",
    "floor_from_mlflow", "floor_label", "from_files", "from_mlflow", "label", "marks", "missing_note",
    "number_record", "table_markdown", "timed_from_files", "wall_totals",
]
