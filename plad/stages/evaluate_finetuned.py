"""Stage ``evaluate_finetuned``: every fine-tuned model of a domain, and the amortization sweep, in one process.

One DVC stage per domain (``evaluate_finetuned@<domain>``), configured by the
domain's ``evaluate`` section like ``evaluate@<domain>``: the test evaluation
(:func:`plad.stages.evaluate.tracked_evaluate`, beam ``beam``) of the
fine-tuned model of each method of the top-level ``methods``, into
``results/eval/<method>/<domain>/``; then the amortization sweep, the model
of ``--sweep-method`` at each beam of the top-level ``beams``, network only,
into ``results/eval/<method>_beam<k>/<domain>/``. The files and MLflow runs
(one per evaluation) are those of one ``plad.stages.evaluate`` run per model.

Why one process: a stage process pays about 4 s of CPU to import torch and
MLflow and open the store before its work, and DVC a per-stage cost that
grows with ``dvc.lock``; in the smoke profile an evaluation's own work is
about a second (docs/performance.md, "What the smoke run costs").
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field, replace

from plad.stages import StageContext, stage_main
from plad.stages.evaluate import EvaluateConfig, result_key, tracked_evaluate

#: top-level keys of params.yaml this stage reads besides its ``evaluate.<domain>`` section (DVC params deps)
TOP_LEVEL_PARAMS = ("methods", "beams")


@dataclass
class SweepKeys:
    """The top-level keys the stage reads (:data:`TOP_LEVEL_PARAMS`), typed."""

    methods: list[str] = field(default_factory=list)
    beams: list[int] = field(default_factory=list)


@dataclass(frozen=True)
class FinetunedEvaluations:
    """What one ``evaluate_finetuned@<domain>`` run evaluates."""

    #: the domain's evaluate section (its ``method`` and ``sweep_beam`` are set per evaluation)
    evaluate: EvaluateConfig
    #: every fine-tuned method whose model is evaluated with ``evaluate.beam``
    methods: list[str]
    #: the beams of the amortization sweep (network only) of ``sweep_method``'s model
    beams: list[int]
    sweep_method: str


def evaluations(plan: FinetunedEvaluations) -> list[EvaluateConfig]:
    """The evaluations of a run, in order: each method's model, then each beam of the sweep."""
    return [*(replace(plan.evaluate, method=m, sweep_beam=None) for m in plan.methods),
            *(replace(plan.evaluate, method=plan.sweep_method, sweep_beam=b) for b in plan.beams)]


def evaluate_finetuned(plan: FinetunedEvaluations, ctx: StageContext = StageContext()) -> dict:
    """Run :func:`evaluations` one after another; {result key: the evaluation's report}."""
    return {result_key(cfg): tracked_evaluate(cfg, ctx) for cfg in evaluations(plan)}


def _options(parser: argparse.ArgumentParser):
    parser.add_argument("--sweep-method", required=True, metavar="METHOD",
                        help="the fine-tuned model of the beam sweep (a method of `methods`)")

    def configure(cfg: EvaluateConfig, args: argparse.Namespace) -> FinetunedEvaluations:
        from plad.config import ConfigError, build, load_params

        params = load_params(args.params)
        top = build(SweepKeys, {k: params[k] for k in TOP_LEVEL_PARAMS if k in params}, "the top level",
                    source=args.params)
        if args.sweep_method not in top.methods:
            raise ConfigError(f"{args.params}: --sweep-method {args.sweep_method} is not one of methods "
                              f"({', '.join(top.methods)})")
        return FinetunedEvaluations(cfg, top.methods, top.beams, args.sweep_method)

    return configure


def main(argv: list[str] | None = None) -> int:
    return stage_main("evaluate_finetuned", EvaluateConfig, evaluate_finetuned, argv, __doc__.splitlines()[0],
                      options=_options)


if __name__ == "__main__":
    sys.exit(main())
