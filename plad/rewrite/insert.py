"""Insertion: add one primitive (or part) where the residual says it helps.

The domain's candidate generator
(:meth:`~plad.domains.space.RewriteSpace.insertions`) proposes, for every
program, programs with one more primitive, from the program's execution and
its target (e.g. every draw token with each operator; a box around the
largest missed or extra region). All candidates of all programs are screened
and scored in one batch; a program takes its best candidate only if it is
strictly better (an insertion adds tokens, so a tie never wins).
"""
from __future__ import annotations

import torch

from plad.domains.space import Candidates
from plad.rewrite.evaluate import Scorer, improves
from plad.rewrite.po import optimize


def insert(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, only: list[int] | None = None,
           force: bool = False) -> tuple[list[list[int]], torch.Tensor, torch.Tensor]:
    """One insertion step for each program (or those in ``only``).

    Returns (programs, values, inserted (B,) bool). With ``force`` a program
    takes its best candidate even if it is worse (for a caller that tunes the
    new primitive and then keeps the result only if it improves: :func:`insert_tuned`).
    """
    programs = [list(p) for p in programs]
    values = values.clone()
    rows = list(range(len(programs))) if only is None else list(only)
    inserted = torch.zeros(len(programs), dtype=torch.bool)
    if not rows:
        return programs, values, inserted
    outputs = scorer.outputs([programs[i] for i in rows])
    cands = scorer.space.insertions([programs[i] for i in rows], outputs, scorer.targets[rows])
    if not len(cands):
        return programs, values, inserted
    cands.owner = torch.as_tensor(rows, dtype=torch.long)[cands.owner]   # back to indices of ``programs``
    programs, values, inserted = take_best(scorer, programs, values, cands, force)
    if not force:
        scorer.stats.accepted("insert", int(inserted.sum()))
    return programs, values, inserted


def take_best(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, cands: Candidates,
              force: bool = False) -> tuple[list[list[int]], torch.Tensor, torch.Tensor]:
    """Each program's best candidate (``cands.owner`` indexes ``programs``), taken if it improves the program
    (``force``: whenever there is one). Returns (programs, values, taken (B,) bool); counts nothing."""
    programs = [list(p) for p in programs]
    values = values.clone()
    taken = torch.zeros(len(programs), dtype=torch.bool)
    best, best_values = scorer.best(cands, len(programs))
    lengths = torch.tensor([len(p) for p in programs])
    has = best >= 0
    new_len = torch.where(has, cands.lengths[best.clamp(min=0)], lengths)
    ok = has & (force | improves(best_values, new_len, values, lengths, scorer.higher_is_better))
    for i in torch.nonzero(ok).flatten().tolist():
        programs[i] = cands.row(int(best[i]))
        values[i] = best_values[i]
    taken[ok] = True
    return programs, values, taken


def improve_repeatedly(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, propose, rounds: int,
                       name: str) -> tuple[list[list[int]], torch.Tensor]:
    """Rounds of: ``propose(programs, rows)`` -> (candidate programs, the index of the program each comes from),
    each program's best taken where it improves (:func:`take_best`); the next round proposes for the programs
    that changed, until none does or ``rounds`` are done. Counts the changes as ``name``; never worse."""
    programs = [list(p) for p in programs]
    values = values.clone()
    todo = [i for i, p in enumerate(programs) if p]
    kept = 0
    for _ in range(rounds):
        cands, owner = propose(programs, todo)
        if not cands:
            break
        programs, values, taken = take_best(scorer, programs, values, Candidates.from_lists(cands, owner))
        todo = torch.nonzero(taken).flatten().tolist()
        kept += len(todo)
        if not todo:
            break
    scorer.stats.accepted(name, kept)
    return programs, values


def keep_tuned(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, new: list[list[int]],
               new_values: torch.Tensor, tried: torch.Tensor, sweeps: int, wide: bool,
               deadline: float | None = None) -> tuple[list[list[int]], torch.Tensor, torch.Tensor]:
    """Tune the ``tried`` programs of ``new`` by PO over their last block (``sweeps`` 0: as they are), then keep
    each one that beats its program in ``programs``. Returns (programs, values, kept (B,) bool)."""
    rows = torch.nonzero(tried).flatten().tolist()
    if sweeps > 0:
        new, new_values = optimize(scorer, new, new_values, sweeps=sweeps, wide=wide, last_only=True, only=rows,
                                   deadline=deadline)
    lengths = torch.tensor([len(p) for p in programs])
    new_lengths = torch.tensor([len(p) for p in new])
    ok = tried & improves(new_values, new_lengths, values, lengths, scorer.higher_is_better)
    out = [new[i] if ok[i] else list(programs[i]) for i in range(len(programs))]
    return out, torch.where(ok, new_values, values), ok


def insert_tuned(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, sweeps: int, wide: bool,
                 only: list[int] | None = None, deadline: float | None = None,
                 ) -> tuple[list[list[int]], torch.Tensor, torch.Tensor]:
    """Insert the best candidate, tune it by PO over the program's last block, keep it if that improves.

    A fitted primitive often overshoots before tuning (a bounding box covers
    more than its component), so the decision to keep it is taken after
    tuning. With ``sweeps`` 0 this is :func:`insert`. Returns (programs,
    values, inserted (B,) bool).
    """
    if sweeps <= 0:
        return insert(scorer, programs, values, only)
    new, new_values, tried = insert(scorer, programs, values, only, force=True)
    out, out_values, ok = keep_tuned(scorer, programs, values, new, new_values, tried, sweeps, wide, deadline)
    scorer.stats.accepted("insert", int(ok.sum()))
    return out, out_values, ok
