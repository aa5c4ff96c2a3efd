"""A small MLflow store filled by real stage runs, for the browser check of MLflow's UI (test_mlflow_ui.py).

Two domains (2D and 3D CSG), each: SP's evaluation (with its floor baseline), fine-tuning with ST (two
short rounds) and its evaluation; then the report over both domains: rows SP, ST and the floor per
domain. The model is the tests' tiny untrained network and the shapes are a few random ones (its numbers
mean nothing, they are real outputs of the stages); every stage goes through its ``tracked_*`` function,
as under DVC.

``python -m tests.plad.tracking.ui_store <folder>`` builds one there (store: ``<folder>/mlflow.db``).
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

DOMAINS = {"csg2d": (64, 64), "csg3d": (32, 32, 32)}
METHODS = ["st"]
PROFILE = "ui-check"


def build(root: Path) -> dict:
    """Fill the store at ``$MLFLOW_TRACKING_URI`` from a project at ``root``; returns the report's summary."""
    import numpy as np

    from plad.data.files import write_prepared
    from plad.layout import Layout
    from plad.learn.methods import MethodConfig
    from plad.learn.rounds import RoundsConfig
    from plad.learn.train import TrainConfig
    from plad.stages import StageContext
    from plad.stages.evaluate import EvaluateConfig, tracked_evaluate
    from plad.stages.finetune import FinetuneStageConfig, tracked_finetune
    from plad.stages.report import ReportConfig, tracked_report
    from tests.tiny import tiny_checkpoint

    layout = Layout(root)
    root.mkdir(parents=True, exist_ok=True)
    params = root / "params.yaml"
    params.write_text(f"profile: {PROFILE}\n")
    ctx = StageContext(layout, params)
    rng = np.random.default_rng(0)
    for domain, shape in DOMAINS.items():
        splits = {s: rng.random((n, *shape)) < 0.3 for s, n in (("train", 8), ("val", 4), ("test", 4))}
        write_prepared(domain, shape, splits, layout.prepared(domain), layout.prepared_summary(domain))
        tiny_checkpoint(layout.model(domain), domain)
        evaluate = EvaluateConfig(domain=domain, beam=1, batch_size=4, grid_shapes=2, device="cpu", threads=1)
        tracked_evaluate(evaluate, ctx)
        rounds = RoundsConfig(infer_beam=1, infer_batch=8, val_beam_epoch=1, val_beam_round=1, max_rounds=2,
                              train=TrainConfig(batch_size=4, steps_per_epoch=2, max_epochs=1))
        methods = {key: MethodConfig(method=key) for key in METHODS}
        for key in METHODS:
            tracked_finetune(FinetuneStageConfig(domain=domain, key=key, device="cpu", threads=1, plad=rounds,
                                                 methods=methods), ctx)
            tracked_evaluate(EvaluateConfig(domain=domain, method=key, beam=1, batch_size=4, grid_shapes=2,
                                            device="cpu", threads=1), ctx)
    report = ReportConfig(domains=list(DOMAINS), methods=["sp", *METHODS], per_round={}, profile=PROFILE)
    return tracked_report(report, ctx)


if __name__ == "__main__":
    folder = Path(sys.argv[1]).resolve()
    folder.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("MLFLOW_TRACKING_URI", f"sqlite:///{folder / 'mlflow.db'}")
    build(folder / "project")
