"""One process of the concurrency tests: open a StageRun on ``$MLFLOW_TRACKING_URI`` and log metrics.

``python -m tests.plad.tracking.stage_run_worker RUN_DIR INDEX [STEPS]``: imports mlflow, writes
``RUN_DIR/../ready<INDEX>``, waits until the file ``RUN_DIR/../go`` exists (so that every worker
opens the store at the same moment, after its imports), then opens
``StageRun("pretrain", "worker<INDEX>", {"index": INDEX}, RUN_DIR)``, logs ``loss`` = INDEX + step / 100
for ``STEPS`` steps (default 30) and prints the run id. A store error is one line on stderr and
status 1, as in the stages (:func:`plad.errors.run_guarded`).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

from plad.errors import run_guarded


def main(argv: list[str]) -> int:
    run_dir, index = Path(argv[0]), int(argv[1])
    steps = int(argv[2]) if len(argv) > 2 else 30
    from plad.tracking import StageRun
    from plad.tracking.store import mlflow_module

    mlflow_module()   # the 3 s import before the start line, so that the opens really coincide
    (run_dir.parent / f"ready{index}").touch()
    go = run_dir.parent / "go"
    deadline = time.monotonic() + 120
    while not go.exists():
        if time.monotonic() > deadline:
            print("stage_run_worker: no start signal", file=sys.stderr)
            return 3
        time.sleep(0.01)

    def work() -> None:
        with StageRun("pretrain", f"worker{index}", {"index": index}, run_dir) as run:
            for step in range(steps):
                run.log_metrics({"loss": index + step / 100}, step=step)
        print(run.run_id)

    return run_guarded("stage_run_worker", work)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
