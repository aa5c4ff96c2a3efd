"""The method of every PLAD mixture of sources (``st``, ``lest+st``, ``lest:2+st:1+ws:1``, ...).

Registered as :data:`plad.learn.method_registry.MIXTURE`: the PLAD rounds (:func:`plad.learn.rounds.run_rounds`)
on the sources the entry's ``method`` names and its P_BEST mode, for the entry's ``max_rounds`` (at most
``plad.max_rounds``); an entry with a ``search`` block seeds and rewrites P_BEST by search after each round's
inference (:mod:`plad.learn.pbest_search`).
"""
from __future__ import annotations

from dataclasses import replace

from plad.learn.job import Job
from plad.learn.method_registry import Method
from plad.learn.methods import MethodConfig
from plad.learn.rounds import RoundHooks, run_rounds


class _PLADRounds(Method):
    """The PLAD mixtures (``lest+st``, ...): :func:`run_rounds` on the entry's sources and P_BEST mode, with
    P_BEST seeded and rewritten by search where the entry has a ``search`` block."""

    checkpoint = "current.pt"

    def check(self, spec: MethodConfig, cfg, where: str) -> None:
        super().check(spec, cfg, where)
        if spec.search is not None:
            from plad.domains import get_domain
            from plad.learn.pbest_search import check

            check(spec.search, get_domain(cfg.domain), f"{where}.search")

    def run(self, job: Job, spec: MethodConfig, cfg, hooks: RoundHooks) -> dict:
        if spec.search is not None:   # P_BEST seeded and rewritten by search after each round's inference
            from plad.learn.pbest_search import PBestSearch

            hooks = replace(hooks, after_infer=PBestSearch(job.domain, spec.search, job.out_dir, cfg.seed).after_infer)
        return run_rounds(job, spec, self.rounds(spec, cfg), hooks)


#: the registered method of the PLAD mixtures
PLAD_ROUNDS = _PLADRounds()
