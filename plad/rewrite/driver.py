"""Rewriting and search entry points: :func:`refine` (from given programs) and :func:`search` (from scratch).

Both work on many shapes at once: the rewriters batch all candidates of all
programs of a batch of shapes into single calls of the domain's executor and
metric. ``refine`` repeats rounds of PO sweeps, (optional removals,) pruning, (optional grafting,) and one insertion
until a round changes nothing; ``search`` starts from the empty program and
either inserts primitives greedily (each new primitive optionally tuned by PO
on its own parameters) or runs a beam search over partial programs
(:mod:`.beam`), or both, then refines; it may also grow the domain's seed
programs (``seeded``) or grow past the length cap and shorten again
(``overshoot``), and keep per shape the better. No step ever makes a program worse, and every
returned value is re-executed and re-scored at the end.

One knob sets the effort of a search: ``effort`` (:data:`EFFORTS`), whose
levels each domain maps to settings (its
:attr:`~plad.domains.space.RewriteSpace.search_efforts`); settings given
beside it override the level's.
"""
from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch

from plad.rewrite.beam import beam_search
from plad.rewrite.evaluate import Scorer, Stats, improves
from plad.rewrite.graft import graft, load_library
from plad.rewrite.insert import insert_tuned
from plad.rewrite.po import optimize
from plad.rewrite.prune import TOLERANCE, eliminate, prune, remove
from plad.rewrite.swap import swap

if TYPE_CHECKING:  # pragma: no cover
    from plad.domains.base import Domain


@dataclass
class RefineConfig:
    """Budget and moves of :func:`refine`."""

    #: rounds of (PO sweeps, pruning, one insertion); stops early when a round changes nothing
    rounds: int = 3
    #: PO sweeps per round (a sweep tries every block once; stops early at a local optimum)
    po_sweeps: int = 10
    #: PO uses the domain's large choice sets (e.g. every draw token), else local neighbours only
    wide: bool = True
    prune: bool = True
    #: after each round's PO, remove primitives while that improves (:func:`plad.rewrite.prune.remove`; any domain,
    #: and the one rewrite that shortens a domain without an expression tree, whose programs ``prune`` leaves as
    #: they are: ShapeAssembly). What refining a network's program needs where it holds misplaced parts that
    #: insertion, which only adds, cannot undo
    remove: bool = False
    #: try insertions each round (each tunes the inserted primitive, then keeps it only if that improves)
    insert: bool = True
    #: insertions per round, one after another; a program stops growing at the first that does not improve it.
    #: More than 1 lets a refinement add the parts a network's program lacks (ShapeAssembly) in one round
    insertions: int = 1
    #: PO sweeps over the inserted primitive's own block after an insertion
    tune_sweeps: int = 10
    #: graft each round after pruning (:mod:`plad.rewrite.graft`, SIRI's code grafting): this many nearest
    #: sub-expressions of the batch's programs per node, by the node's desired execution (SIRI: 15); 0: off.
    #: Domains with an expression tree of boolean operators only (2D and 3D CSG)
    graft: int = 0
    #: sub-expressions grafted besides the batch's own: "shipped" (the domain's own library, package data of its
    #: plugin: sub-expressions of programs found for training shapes), a library file (``python -m
    #: plad.tools.graft_library``), or null (the batch's only: what grafting finds then grows with the batch)
    graft_library: str | None = None
    #: try one swap per round after the insertion (:mod:`plad.rewrite.swap`: remove a primitive, insert the
    #: best new one, tune it by ``tune_sweeps``); what helps where the length cap stops insertion
    swap: bool = False
    #: seconds for one batch of shapes (no new step starts after it); null: no limit. A safety net: the work is
    #: fixed by the counts above, and a result the limit cut short says so (:attr:`Result.stopped_by_time`)
    time_limit: float | None = None
    #: shapes processed together
    batch: int = 256
    #: use the domain's cheap screen before the exact metric (false: score every candidate exactly)
    screen: bool = True


#: the effort levels of a search, least work first (each domain maps them to settings: its ``search_efforts``)
EFFORTS = ("fast", "default", "best")


@dataclass
class SearchConfig:
    """Search from scratch: greedy insertion or a beam over partial programs, then :func:`refine`."""

    #: the effort level (:data:`EFFORTS`) whose settings (the domain's ``search_efforts``) this configuration
    #: starts from; only recorded here, applied by :func:`search_config`
    effort: str = "default"
    #: insertion steps from the empty program, greedy or of the beam (fewer if the language's length cap is
    #: reached)
    insertions: int = 12
    #: beam width: programs kept per shape at each step of a beam search over partial programs
    #: (:mod:`plad.rewrite.beam`); 0: greedy insertion instead
    beam_width: int = 0
    #: the best distinct programs the beam found that are each refined; the best refined one is returned
    beam_refine: int = 1
    #: with a beam: first the greedy insertion (tuned by ``tune_sweeps``) and its refinement, as without one; the
    #: beam's refined finds then replace its program only where they are better. The two explore differently
    #: (tuned one at a time against a lookahead without tuning), and per shape the better of both pays (3D CSG)
    greedy_first: bool = False
    #: also the greedy insertion (tuned by ``tune_sweeps``) from the domain's seed program of each shape
    #: (:meth:`~plad.domains.space.RewriteSpace.seeds`: 3D CSG's bounding box, which differences carve), refined
    #: as the others; it replaces the shape's program where better. Another start explores another part of the
    #: programs within the length cap (3D CSG). A domain without seeds ignores it
    seeded: bool = False
    #: tokens beyond the language's length cap (at most the domain's ``max_overshoot``) that one more greedy
    #: insertion from the empty program (tuned by ``tune_sweeps``) may use; backward elimination
    #: (:func:`~plad.rewrite.prune.eliminate`) then shortens its program back within the cap, the refinement
    #: follows, and the result replaces the shape's program where better. Choosing which primitives to keep
    #: among more than fit is what the cap leaves to do (3D CSG); 0: none
    overshoot: int = 0
    #: PO sweeps over each inserted primitive's own block right after its insertion
    tune_sweeps: int = 0
    #: whether that tuning uses the large choice sets
    tune_wide: bool = False
    refine: RefineConfig = field(default_factory=RefineConfig)

    def __post_init__(self):
        if self.effort not in EFFORTS:
            raise ValueError(f"effort = {self.effort!r}: expected one of {', '.join(EFFORTS)}")
        if self.beam_refine < 1:
            raise ValueError(f"beam_refine = {self.beam_refine}: expected at least 1")
        if self.beam_width < 0:
            raise ValueError(f"beam_width = {self.beam_width}: expected 0 (greedy insertion) or a width of at least 1")
        if self.overshoot < 0:
            raise ValueError(f"overshoot = {self.overshoot}: expected a number of tokens, 0 or more")
        if self.greedy_first and self.beam_width == 0:
            raise ValueError("greedy_first = true needs a beam (beam_width of at least 1): without one the search "
                             "is the greedy insertion alone")


@dataclass
class Result:
    """Programs (token id lists), their exact values (B,) float64, seconds and where the time went."""

    programs: list[list[int]]
    values: torch.Tensor
    seconds: float
    stats: Stats
    #: a batch's time limit passed before its work was done (steps may have been skipped): the programs depend
    #: on the machine's speed, not only on the inputs and the configuration
    stopped_by_time: bool = False


def search_config(domain: Domain, **overrides) -> SearchConfig:
    """The domain's search configuration at an effort level, with ``overrides``.

    The settings are, each overriding the one before: the domain's ``search_defaults``, its
    ``search_efforts`` of the level ``overrides["effort"]`` (default ``"default"``), the other
    ``overrides``. Keys ``refine.<field>`` (or a ``refine`` mapping) set fields of the refine part.
    """
    from plad.config import ConfigError, build

    effort = overrides.get("effort", "default")
    if effort not in EFFORTS:
        raise ConfigError(f"search configuration: effort = {effort!r}: expected one of {', '.join(EFFORTS)}")
    space = domain.rewrite
    raw: dict = {}
    for source in (dict(space.search_defaults) if space else {}, dict(space.search_efforts[effort]) if space else {},
                   overrides):
        for key, value in source.items():
            if key.startswith("refine."):
                raw.setdefault("refine", {})[key.split(".", 1)[1]] = value
            elif key == "refine":
                if not isinstance(value, dict):
                    raise ConfigError(f"search configuration: refine = {value!r}: expected a mapping of refine "
                                      f"settings (or set one with refine.KEY=VALUE, e.g. refine.rounds=3)")
                raw.setdefault("refine", {}).update(value)
            else:
                raw[key] = value
    config = build(SearchConfig, raw, "search", source="search configuration")
    try:
        check_refine(domain, config.refine)
    except ValueError as err:
        raise ConfigError(f"search configuration: {err}") from None
    allowed = space.max_overshoot if space else 0
    if config.overshoot > allowed:
        raise ConfigError(f"search configuration: overshoot = {config.overshoot}: the {domain.name} domain runs "
                          f"programs of at most {allowed} tokens beyond its length cap")
    return config


def check_refine(domain: Domain, cfg: RefineConfig) -> None:
    """ValueError for settings the domain cannot run: grafting (``graft``) without boolean operators."""
    if cfg.graft < 0:
        raise ValueError(f"refine.graft = {cfg.graft}: expected a number of sub-expressions per node, 0 for none")
    if cfg.graft and not (domain.rewrite is not None and domain.rewrite.grafts):
        raise ValueError(f"refine.graft = {cfg.graft}: the {domain.name} domain has no expression tree of boolean "
                         f"operators to graft into; set it to 0")
    if cfg.graft and cfg.graft_library is not None:
        load_library(domain, cfg.graft_library)   # a missing or corrupt file: one line now, not mid-search


def _confirm(scorer: Scorer, programs: list[list[int]], values: torch.Tensor) -> torch.Tensor:
    """Re-execute and re-score the final programs; the tracked values must agree exactly."""
    again = scorer.values(programs)
    if not torch.equal(again, values):
        bad = int(torch.nonzero(again != values)[0, 0])
        raise RuntimeError(f"re-scoring program {bad} gave {float(again[bad])}, tracked {float(values[bad])}: "
                           f"the executor or metric is not deterministic")
    return again


def _grow(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, steps: int, sweeps: int, wide: bool,
          deadline: float | None) -> tuple[list[list[int]], torch.Tensor]:
    """Up to ``steps`` tuned insertions (:func:`insert_tuned`) one after another; a program stops growing at the
    first that does not improve it, and no step starts after the deadline."""
    growing = list(range(len(programs)))
    for _ in range(steps):
        if not growing or (deadline is not None and time.perf_counter() > deadline):
            break
        programs, values, inserted = insert_tuned(scorer, programs, values, sweeps, wide, only=growing,
                                                  deadline=deadline)
        growing = torch.nonzero(inserted).flatten().tolist()
    return programs, values


def _refine_batch(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, cfg: RefineConfig,
                  deadline: float | None) -> tuple[list[list[int]], torch.Tensor]:
    for _ in range(cfg.rounds):
        if deadline is not None and time.perf_counter() > deadline:
            break
        before = [list(p) for p in programs]
        programs, values = optimize(scorer, programs, values, sweeps=cfg.po_sweeps, wide=cfg.wide, deadline=deadline)
        if cfg.remove:
            programs, values = remove(scorer, programs, values)
        if cfg.prune:
            programs, values = prune(scorer, programs, values, TOLERANCE)
        if cfg.graft:
            extra = None if cfg.graft_library is None else load_library(scorer.domain, cfg.graft_library)
            programs, values = graft(scorer, programs, values, k=cfg.graft, extra=extra)
        if cfg.insert:
            programs, values = _grow(scorer, programs, values, cfg.insertions, cfg.tune_sweeps, False, deadline)
        if cfg.swap and (deadline is None or time.perf_counter() <= deadline):
            programs, values, _ = swap(scorer, programs, values, cfg.tune_sweeps, deadline=deadline)
        if programs == before:
            break
    return programs, values


def _beam_then_refine(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, cfg: SearchConfig,
                      deadline: float | None) -> tuple[list[list[int]], torch.Tensor]:
    """Beam search, then refinement of each shape's ``beam_refine`` best finds; per shape the best result,
    if it beats the start (``programs``, ``values``)."""
    finds = beam_search(scorer, cfg.beam_width, cfg.insertions, cfg.beam_refine, deadline)
    starts = [p for f in finds for p, _ in f]
    owner = [i for i, f in enumerate(finds) for _ in f]
    if not starts:
        return programs, values
    start_values = torch.tensor([v for f in finds for _, v in f], dtype=torch.float64)
    if cfg.beam_refine == 1:
        sub = scorer
    else:   # each find refined against its own copy of its target
        sub = Scorer(scorer.domain, scorer.targets[owner], screen=scorer.use_screen)
    refined, refined_values = _refine_batch(sub, starts, start_values, cfg.refine, deadline)
    if sub is not scorer:
        scorer.stats.add(sub.stats)
    programs = [list(p) for p in programs]
    values = values.clone()
    for k, i in enumerate(owner):    # finds of a shape in order: the best refined one wins (ties: fewer tokens)
        if bool(improves(refined_values[k:k + 1], torch.tensor([len(refined[k])]), values[i:i + 1],
                         torch.tensor([len(programs[i])]), scorer.higher_is_better)):
            programs[i] = refined[k]
            values[i] = refined_values[k]
    return programs, values


def _refined_where_better(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, new: list[list[int]],
                          new_values: torch.Tensor, cfg: SearchConfig, deadline: float | None,
                          ) -> tuple[list[list[int]], torch.Tensor]:
    """``new`` refined (``cfg.refine``), then per shape where it beats ``programs`` (metric, then fewer tokens)."""
    new, new_values = _refine_batch(scorer, new, new_values, cfg.refine, deadline)
    better = improves(new_values, torch.tensor([len(p) for p in new]), values,
                      torch.tensor([len(p) for p in programs]), scorer.higher_is_better)
    programs = [new[i] if better[i] else list(programs[i]) for i in range(len(programs))]
    return programs, torch.where(better, new_values, values)


def _from_seeds(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, cfg: SearchConfig,
                deadline: float | None) -> tuple[list[list[int]], torch.Tensor]:
    """Greedy insertion from the domain's seeds, refined; per shape the result if it beats ``programs``."""
    seeds = scorer.space.seeds(scorer.targets)
    if seeds is None:
        return programs, values
    grown, grown_values = _grow(scorer, seeds, scorer.values(seeds), cfg.insertions, cfg.tune_sweeps,
                                cfg.tune_wide, deadline)
    return _refined_where_better(scorer, programs, values, grown, grown_values, cfg, deadline)


def _overshoot(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, cfg: SearchConfig,
               deadline: float | None) -> tuple[list[list[int]], torch.Tensor]:
    """Greedy insertion past the length cap, elimination back within it, refinement; per shape the result if
    it beats ``programs``."""
    space = scorer.space
    empty: list[list[int]] = [[] for _ in programs]
    with space.longer(cfg.overshoot):
        # the cap ends the growth: a step adds at least one token
        grown, grown_values = _grow(scorer, empty, scorer.values(empty), space.max_len, cfg.tune_sweeps,
                                    cfg.tune_wide, deadline)
    grown, grown_values = eliminate(scorer, grown, grown_values, space.max_len)
    return _refined_where_better(scorer, programs, values, grown, grown_values, cfg, deadline)


def _past(deadline: float | None) -> bool:
    """Whether a batch's work ended after its deadline. Every step checks the deadline before it starts (and PO
    and insertion between candidates), so a batch that ends past it may have skipped steps; one that ends
    before it did all its work. (A last step that merely overran counts too: the flag errs on the safe side.)"""
    return deadline is not None and time.perf_counter() > deadline


def _batches(n: int, size: int):
    for start in range(0, n, max(1, size)):
        yield slice(start, min(n, start + max(1, size)))


def refine(domain: Domain, programs: Sequence[Sequence[int]], targets: torch.Tensor,
           config: RefineConfig | None = None) -> Result:
    """Rewrite each program towards its target (targets (B, *shape) bool); never returns a worse program.

    An empty program (``[]``) is allowed: it scores the metric's worst value and
    is grown by insertion.
    """
    cfg = config or RefineConfig()
    check_refine(domain, cfg)
    start = time.perf_counter()
    stats = Stats()
    out_programs: list[list[int]] = []
    out_values = []
    timed = False
    for sl in _batches(len(programs), cfg.batch):
        scorer = Scorer(domain, targets[sl], screen=cfg.screen)
        batch = [list(p) for p in programs[sl]]
        values = scorer.values(batch)
        deadline = None if cfg.time_limit is None else time.perf_counter() + cfg.time_limit
        batch, values = _refine_batch(scorer, batch, values, cfg, deadline)
        timed |= _past(deadline)
        out_values.append(_confirm(scorer, batch, values))
        out_programs += batch
        stats.add(scorer.stats)
    values = torch.cat(out_values) if out_values else torch.zeros(0, dtype=torch.float64)
    return Result(out_programs, values, time.perf_counter() - start, stats, timed)


def search(domain: Domain, targets: torch.Tensor, config: SearchConfig | None = None) -> Result:
    """Search from scratch for each target (B, *shape) bool: greedy insertion or a beam search (or both,
    ``greedy_first``: the better per shape), then refinement; with ``seeded`` also the greedy insertion from the
    domain's seed programs, and with ``overshoot`` one past the length cap and shortened again, each the better
    per shape."""
    cfg = config or search_config(domain)
    check_refine(domain, cfg.refine)
    start = time.perf_counter()
    stats = Stats()
    out_programs: list[list[int]] = []
    out_values = []
    timed = False
    for sl in _batches(len(targets), cfg.refine.batch):
        scorer = Scorer(domain, targets[sl], screen=cfg.refine.screen)
        n = sl.stop - sl.start
        programs: list[list[int]] = [[] for _ in range(n)]
        values = scorer.values(programs)
        deadline = None if cfg.refine.time_limit is None else time.perf_counter() + cfg.refine.time_limit
        if cfg.beam_width == 0 or cfg.greedy_first:
            programs, values = _grow(scorer, programs, values, cfg.insertions, cfg.tune_sweeps, cfg.tune_wide,
                                     deadline)
            programs, values = _refine_batch(scorer, programs, values, cfg.refine, deadline)
        if cfg.beam_width > 0:
            programs, values = _beam_then_refine(scorer, programs, values, cfg, deadline)
        if cfg.seeded:
            programs, values = _from_seeds(scorer, programs, values, cfg, deadline)
        if cfg.overshoot:
            programs, values = _overshoot(scorer, programs, values, cfg, deadline)
        timed |= _past(deadline)
        out_values.append(_confirm(scorer, programs, values))
        out_programs += programs
        stats.add(scorer.stats)
    values = torch.cat(out_values) if out_values else torch.zeros(0, dtype=torch.float64)
    return Result(out_programs, values, time.perf_counter() - start, stats, timed)


__all__ = ["EFFORTS", "RefineConfig", "Result", "SearchConfig", "check_refine", "refine", "search", "search_config"]
