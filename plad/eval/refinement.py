"""The refinement of a network's programs at an effort level: what ``plad infer --effort LEVEL`` refines and
from which of the beam's candidates, in one home for the CLI (:func:`plad.serve.infer.refine_inferred`) and
the evaluation of the report's effort rows (:mod:`plad.stages.evaluate`, ``refine_effort``)."""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from plad.domains.base import Domain
    from plad.rewrite import RefineConfig


@dataclass(frozen=True)
class Refinement:
    """How the network's programs are refined before they are written: the rewriters' budget, and which of each
    shape's beam candidates they start from."""

    config: RefineConfig
    #: refine every candidate of the shape's beam and keep the best refined one by the domain metric (else the
    #: best-of-beam program only); never worse than refining the best-of-beam only, which is one of them
    all_candidates: bool = False


def refinement(domain: Domain, effort: str = "default") -> Refinement:
    """The refinement of ``plad infer --effort LEVEL`` (:data:`plad.rewrite.EFFORTS`; a bad level: ValueError).

    * ``fast``: the best-of-beam program, refined as the domain's fast search refines
      (``search_config(domain, effort="fast").refine``; 2D CSG: one round; the domains that have not measured
      their levels: no rounds, the network's beam alone);
    * ``default``: the best-of-beam program, refined by :class:`~plad.rewrite.RefineConfig` ``()`` (3 rounds)
      with the domain's ``refine_defaults`` (ShapeAssembly: removal of parts; 2D CSG: grafting, from its library
      too); what ``plad infer`` did before the levels existed, but for those. Not ``search_config(domain).refine``,
      which is less work (2D and 3D CSG: one round; ShapeAssembly also fewer, narrower PO sweeps and no insertion);
    * ``best``: every candidate of the beam, each refined as for ``default``, the best kept per shape. Not
      ``search_config(domain, effort="best").refine`` either: no domain's is more work than ``RefineConfig()``
      (2D CSG: one round), so ``best`` would refine its best-of-beam program less than ``default`` does.
    """
    from plad.rewrite import EFFORTS, RefineConfig, search_config

    if effort not in EFFORTS:
        raise ValueError(f"effort = {effort!r}: expected one of {', '.join(EFFORTS)}")
    if effort == "fast":
        return Refinement(search_config(domain, effort="fast").refine)
    space = domain.rewrite
    return Refinement(RefineConfig(**(space.refine_defaults if space else {})), all_candidates=effort == "best")


def beam_starts(inferred, all_candidates: bool) -> tuple[list[list[int]], list[int]]:
    """The programs a refinement starts from for a batch's :class:`plad.model.decode.Inferred`, and the shape each
    belongs to: every shape's best-of-beam program first (in shape order), then, with ``all_candidates``, the
    other complete candidates of every shape's beam (an empty slot of the beam has no program)."""
    starts, owner = [list(p) for p in inferred.programs], list(range(len(inferred.programs)))
    if all_candidates:
        beam = inferred.beam
        finite = torch.isfinite(beam.logp).cpu()
        for b, best in enumerate(inferred.programs):
            for k in range(beam.programs.shape[1]):
                program = beam.program(b, k)
                if bool(finite[b, k]) and program != best:
                    starts.append(program)
                    owner.append(b)
    return starts, owner


def keep_best(better: Callable, n: int, owner: Sequence[int], values) -> list[int]:
    """Which refined start each of the ``n`` shapes keeps: its own best-of-beam start (index b, the first
    ``n`` of :func:`beam_starts`) unless a later start of the same shape is strictly ``better`` by the domain
    metric (so ties keep the best-of-beam program's refinement). ``values``: one per start."""
    values = torch.as_tensor(values)
    chosen = list(range(n))
    for k in range(n, len(owner)):
        b = owner[k]
        if bool(better(values[k], values[chosen[b]])):
            chosen[b] = k
    return chosen


def infer_starts(model, domain: Domain, targets, beam: int, batch_size: int, all_candidates: bool,
                 desc: str = "infer") -> tuple:
    """Best-of-beam inference over many shapes in batches (as :func:`plad.model.decode.infer_batched`), with the
    starts of their refinement (:func:`beam_starts` over all shapes: the ``N`` best-of-beam programs first, then
    the other candidates).

    targets bool (N, *shape) -> (values (N,), best programs, executions bool (N, *shape), starts, owner)."""
    import numpy as np
    from tqdm import tqdm

    from plad.device import to_device
    from plad.model.decode import infer_programs

    device = next(model.parameters()).device
    values, programs, shapes, extra, extra_owner = [], [], [], [], []
    for start in tqdm(range(0, len(targets), batch_size), desc=desc, unit="batch", disable=None):
        inferred = infer_programs(model, domain, to_device(targets[start:start + batch_size], device), beam)
        values.append(inferred.values.cpu().numpy())
        programs.extend(inferred.programs)
        shapes.append(inferred.shapes.cpu().numpy())
        starts, owner = beam_starts(inferred, all_candidates)
        extra.extend(starts[len(inferred.programs):])
        extra_owner.extend(start + b for b in owner[len(inferred.programs):])
    n = len(programs)
    return (np.concatenate(values) if values else np.zeros(0), programs,
            np.concatenate(shapes) if shapes else np.zeros((0, *domain.shape), bool),
            [list(p) for p in programs] + extra, list(range(n)) + extra_owner)
