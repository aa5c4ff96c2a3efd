"""Reading finished runs back from the MLflow store: the latest finished run of some tags
(:func:`latest_finished_run`) and a metric's history (:func:`metric_history`).

Imported by :mod:`plad.tracking.runs` too, whose names they were.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from plad.tracking.store import client


@dataclasses.dataclass(frozen=True)
class RunRecord:
    """What a finished run left: its id, last metric values and tags."""
    run_id: str
    metrics: dict[str, float]
    tags: dict[str, str]


def latest_finished_run(experiment_ids: str | list[str], tags: Mapping[str, str]) -> RunRecord | None:
    """The FINISHED run of the experiment(s) with all these tag values that ended last, or ``None``."""
    ids = [experiment_ids] if isinstance(experiment_ids, str) else list(experiment_ids)
    where = " and ".join(f"tags.`{k}` = '{v}'" for k, v in tags.items())
    runs = client().search_runs(ids, f"{where} and attributes.status = 'FINISHED'",
                                order_by=["attributes.end_time DESC"], max_results=1)
    if not runs:
        return None
    run = runs[0]
    return RunRecord(run.info.run_id, dict(run.data.metrics), dict(run.data.tags))


def metric_history(run_id: str, key: str) -> list[tuple[int, float]]:
    """Every logged (step, value) of one metric of a run, in the store's order."""
    return [(m.step, m.value) for m in client().get_metric_history(run_id, key)]
