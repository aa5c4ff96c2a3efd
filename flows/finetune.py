"""Prefect flow: PLAD fine-tuning rounds as tasks, test evaluation and the report.

    python -m flows.finetune --params params.yaml [--profile smoke] [--methods lest_st st] [--run-name NAME]
                             [--root DIR]
    python -m flows.finetune --params params.yaml --serve      # periodic retraining (needs `prefect server start`)

The flow calls the same functions as the DVC stages (``plad.stages.finetune``,
``plad.stages.evaluate``, ``plad.stages.report``); it only decides how the
steps run. Each step of a round (inference, wake-sleep generator, training,
validation) is a task; inference over the training shapes is split into
``flows.shards`` tasks, with retries, that run in parallel: on the flow's
threads by default, on a Dask cluster when ``flows.dask_address`` is set
(through prefect-dask; chosen when the flow runs, so deployments honour it
too). Every flow run starts from the project's prepared data and pretrained
model and writes under ``runs/flows/<run name>/``, in the project's layout
(:meth:`plad.layout.Layout.flow_run`), so that scheduled retrainings never
overwrite each other; a run started again with the same name resumes.
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from prefect import flow, task
from prefect.cache_policies import NONE

from flows import one_line_errors
from plad.config import ConfigError, load_params, section
from plad.errors import run_guarded
from plad.layout import SP, Layout
from plad.stages import StageContext


@dataclass
class FlowsConfig:
    #: the domain a flow run retrains (its sections finetune.<domain>, evaluate.<domain>)
    domain: str = "csg2d"
    #: the finetune.methods entries a flow run trains (empty: all of them)
    methods: list[str] = field(default_factory=list)
    #: inference tasks per round (shards of the training shapes)
    shards: int = 2
    #: retries of an inference shard
    retries: int = 2
    retry_delay_seconds: float = 10
    #: a Dask scheduler address ("tcp://host:8786"): run the tasks there; null: threads in this process
    dask_address: str | None = None
    #: torch threads per inference task (null: torch's default)
    threads_per_task: int | None = None
    #: cron of the served deployment (periodic retraining)
    cron: str = "0 3 * * 0"
    deployment: str = "plad-retrain"
    evaluate: bool = True


def _infer_shard(model, domain_name: str, shapes: np.ndarray, beam: int, batch: int, threads: int | None):
    import torch

    from plad.domains import get_domain
    from plad.model.decode import infer_batched

    if threads:
        torch.set_num_threads(threads)
    return infer_batched(model, get_domain(domain_name), shapes, beam, batch, desc="infer shard")


def sharded_infer(domain_name: str, beam: int, batch: int, cfg: FlowsConfig):
    """An ``Infer`` for :func:`plad.learn.rounds.run_rounds` that maps shards of the shapes over tasks."""
    shard_task = task(_infer_shard, name="infer shard", retries=cfg.retries,
                      retry_delay_seconds=cfg.retry_delay_seconds, cache_policy=NONE)

    def infer(model, shapes: np.ndarray):
        parts = [p for p in np.array_split(np.arange(len(shapes)), max(1, cfg.shards)) if len(p)]
        calls = [{"model": model, "domain_name": domain_name, "shapes": shapes[p], "beam": beam, "batch": batch,
                  "threads": cfg.threads_per_task} for p in parts]
        if cfg.dask_address:
            # a worker lost mid-shard: Dask runs the shard again on another worker
            from prefect_dask import DaskTaskRunner

            with DaskTaskRunner(address=cfg.dask_address) as runner:
                results = [f.result() for f in [runner.submit(shard_task, c) for c in calls]]
        else:
            results = [f.result() for f in [shard_task.submit(**c) for c in calls]]
        values = np.concatenate([r[0] for r in results])
        programs = [p for r in results for p in r[1]]
        executions = np.concatenate([r[2] for r in results])
        return values, programs, executions
    return infer


def task_step(name: str, fn, *args, **kwargs):
    """Run one step of a round as a Prefect task named after it."""
    return task(fn, name=name, cache_policy=NONE)(*args, **kwargs)


def run_configs(params: dict, source: str):
    """(flows, finetune, evaluate, report) configs of a flow run."""
    from plad.stages.evaluate import EvaluateConfig
    from plad.stages.finetune import FinetuneStageConfig
    from plad.stages.report import ReportConfig

    fcfg = section(params, "flows", FlowsConfig) if "flows" in params else FlowsConfig()
    ft = section(params, f"finetune.{fcfg.domain}", FinetuneStageConfig)
    ev = section(params, f"evaluate.{fcfg.domain}", EvaluateConfig)
    rp = section(params, "report", ReportConfig)
    unknown = [m for m in fcfg.methods if m not in ft.methods]
    if unknown:
        raise ConfigError(f"{source}: flows.methods {', '.join(unknown)} not in finetune.{fcfg.domain}.methods")
    return fcfg, ft, ev, rp


@flow(name="plad-finetune")
def finetune_flow(params_path: str = "params.yaml", methods: list[str] | None = None,
                  run_name: str | None = None, root: str = ".", profile: str | None = None) -> dict:
    """Fine-tune the configured methods, evaluate them on the test split, and write the report.

    ``root`` is the project's layout root (:mod:`plad.layout`): the run starts from its prepared data
    and pretrained model and writes under its ``runs/flows/<run_name>/``. ``profile`` (smoke, cpu,
    paper) replaces the params file's ``profile``: ``profiles/<profile>.yaml`` is applied on top.
    """
    from plad.stages.evaluate import tracked_evaluate
    from plad.stages.finetune import tracked_finetune
    from plad.stages.report import report

    run_name = run_name or dt.datetime.now(dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    params = load_params(params_path, profile=profile)
    fcfg, ft, ev, rp = run_configs(params, params_path)
    ctx = StageContext(Layout(root).flow_run(run_name), Path(params_path))
    keys = list(methods or fcfg.methods or ft.methods)
    out: dict = {"run_name": run_name, "out_dir": str(ctx.layout.root), "methods": {}}
    for key in keys:
        cfg = dataclasses.replace(ft, key=key)
        infer = sharded_infer(cfg.domain, cfg.plad.infer_beam, cfg.plad.infer_batch, fcfg)
        summary = tracked_finetune(cfg, ctx, infer=infer, step=task_step)
        out["methods"][key] = summary
        if fcfg.evaluate:
            ecfg = dataclasses.replace(ev, method=key)
            out["methods"][key]["test"] = task(tracked_evaluate, name=f"evaluate {key}", cache_policy=NONE)(
                ecfg, ctx)[ecfg.splits[-1]]["mean"]
    if fcfg.evaluate:
        task(tracked_evaluate, name="evaluate sp", cache_policy=NONE)(dataclasses.replace(ev, method=SP), ctx)
        rows = [SP, *[k for k in keys if k not in rp.per_round.values()]]
        rcfg = dataclasses.replace(rp, domains=[ft.domain], methods=rows,
                                   per_round={a: b for a, b in rp.per_round.items() if a in keys and b in keys},
                                   register=False)
        out["report"] = task(report, name="report", cache_policy=NONE)(rcfg, ctx.layout)
    return out


def deployment(params_path: str, root: str = ".", profile: str | None = None):
    """The scheduled deployment of the flow (cron and name from ``flows``), as ``serve`` runs it."""
    params = load_params(params_path, profile=profile)
    fcfg = section(params, "flows", FlowsConfig) if "flows" in params else FlowsConfig()
    parameters = {"params_path": str(Path(params_path).resolve()), "root": str(Path(root).resolve())}
    if profile is not None:
        parameters["profile"] = profile
    return finetune_flow.to_deployment(name=fcfg.deployment, cron=fcfg.cron, parameters=parameters)


def main(argv: list[str] | None = None) -> int:
    """The command line; the exit statuses of :mod:`plad.errors` (a params or data problem: one line, 1)."""
    parser = argparse.ArgumentParser(prog="python -m flows.finetune", description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--profile", help="apply profiles/<PROFILE>.yaml instead of the one the params name "
                                          "(smoke, cpu, paper)")
    parser.add_argument("--methods", nargs="*", help="finetune.methods keys (default: flows.methods, else all)")
    parser.add_argument("--run-name", help="output folder under runs/flows/ (default: the UTC time)")
    parser.add_argument("--root", default=".",
                        help="root folder of the project's artifacts (plad.layout; default: the working directory)")
    parser.add_argument("--serve", action="store_true",
                        help="serve the deployment on its cron (needs a running `prefect server start`)")
    args = parser.parse_args(argv)
    if args.serve:
        from prefect.settings import PREFECT_API_URL

        if not PREFECT_API_URL.value():   # a temporary server would start, serve nothing and keep no schedule
            parser.error("--serve needs a running Prefect server: start `prefect server start` and set "
                         'PREFECT_API_URL=http://127.0.0.1:4200/api (docs/pipeline.md, "Periodic retraining")')

    one_line_errors()

    def go() -> None:
        # a bad params file or profile is one line before Prefect starts its server
        run_configs(load_params(args.params, profile=args.profile), args.params)
        if args.serve:
            from prefect import serve

            serve(deployment(args.params, args.root, args.profile))
        else:
            print(finetune_flow(args.params, args.methods, args.run_name, args.root, args.profile))

    return run_guarded("flows.finetune", go)


if __name__ == "__main__":
    sys.exit(main())
