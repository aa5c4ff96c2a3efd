"""Grammar-constrained batched beam search and best-of-beam program inference.

Generic over domains: the only grammar knowledge is the token table's mask,
so every returned program is valid. Rows of the search are (shape, beam)
pairs, (B * K) of them, decoded together one token per step with the
model's key/value caches.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm

from plad.device import to_device
from plad.domains.base import Domain
from plad.domains.grammar import TokenTable
from plad.model.network import PLADNet, reorder_caches

NEG = float("-inf")


@dataclass
class BeamResult:
    """Complete programs per shape, best log-probability first.

    programs: (B, K, L) long token ids, right-padded with the table's first token
              after the end (padding is ignored by executors; use ``lengths``).
    lengths:  (B, K) long, tokens of each program.
    logp:     (B, K) float, total log-probability (-inf for an empty slot when
              fewer than K distinct programs exist).
    """

    programs: torch.Tensor
    lengths: torch.Tensor
    logp: torch.Tensor

    def program(self, b: int, k: int = 0) -> list[int]:
        return self.programs[b, k, : int(self.lengths[b, k])].tolist()


@torch.no_grad()
def beam_search(model: PLADNet, table: TokenTable, shapes: torch.Tensor, beam: int,
                prefix: torch.Tensor | None = None) -> BeamResult:
    """Top-``beam`` complete programs for each shape by log-probability.

    shapes (B, *input_shape) bool on the model's device (or ``prefix``: the
    visual tokens (B, P, d), e.g. from the wake-sleep generator).
    Finished hypotheses stay in the beam with their score frozen, so the K
    returned programs are the K best complete programs the search found.
    With ``beam=1`` this is exactly greedy decoding under the mask.
    """
    model.eval()
    if prefix is None:
        prefix = model.encode(shapes)
    B = prefix.shape[0]
    K = beam
    V = len(table)
    L = table.max_len
    dev = prefix.device

    logits, caches = model.start(prefix)                                       # (B, V)
    state = table.initial_state(B, dev)
    logp0 = torch.log_softmax(logits.float(), -1).masked_fill(~table.mask(state), NEG)
    # first step: the K best first tokens of each shape (fewer may be allowed)
    k0 = min(K, V)
    top, tok = logp0.topk(k0, dim=-1)                                          # (B, k0)
    if k0 < K:
        top = torch.cat([top, torch.full((B, K - k0), NEG, device=dev)], 1)
        tok = torch.cat([tok, tok[:, :1].expand(B, K - k0)], 1)
    if K > 1:
        rows = torch.arange(B, device=dev).repeat_interleave(K)                # (B*K,) parent shape
        caches = reorder_caches(caches, rows)
        state = state.select(rows)
    state = table.advance(state, tok.reshape(-1))
    scores = top.reshape(-1)                                                   # (B*K,)
    seqs = torch.zeros(B * K, L, dtype=torch.long, device=dev)
    seqs[:, 0] = tok.reshape(-1)
    lengths = torch.ones(B * K, dtype=torch.long, device=dev)

    for pos in range(1, L):
        done = state.done
        if bool(done.all()):
            break
        logits, caches = model.step(seqs[:, pos - 1], caches, pos)
        logp = torch.log_softmax(logits.float(), -1).masked_fill(~table.mask(state), NEG)
        # a finished row continues with exactly one candidate that keeps its score
        keep = torch.full_like(logp, NEG)
        keep[:, 0] = 0.0
        logp = torch.where(done[:, None], keep, logp)
        cand = (scores[:, None] + logp).view(B, K * V)
        best, flat = cand.topk(K, dim=-1)                                      # (B, K)
        parent = (flat // V) + torch.arange(B, device=dev)[:, None] * K       # row in (B*K)
        token = flat % V
        parent, token = parent.reshape(-1), token.reshape(-1)
        # with one hypothesis per shape (greedy) every row is its own parent: nothing to reorder
        if K > 1:
            done = done[parent]
            seqs = seqs[parent]
            lengths = lengths[parent]
            state = state.select(parent)
            caches = reorder_caches(caches, parent)
        seqs[:, pos] = torch.where(done, seqs[:, pos], token)
        lengths = lengths + (~done).long()
        state = table.advance(state, token)
        scores = best.reshape(-1)

    # pad past each program's end with 0 (executors ignore it after the program completes)
    pos = torch.arange(L, device=dev)[None, :]
    seqs = torch.where(pos < lengths[:, None], seqs, torch.zeros_like(seqs))
    return BeamResult(seqs.view(B, K, L), lengths.view(B, K), scores.view(B, K))


@dataclass
class Inferred:
    """Best-of-beam inference for a batch of target shapes."""

    programs: list[list[int]]      # best program per shape (by the domain metric)
    values: torch.Tensor           # (B,) float64 metric of the best program
    shapes: torch.Tensor           # (B, *shape) bool executions of the best programs
    beam: BeamResult               # all candidates


@torch.no_grad()
def infer_programs(model: PLADNet, domain: Domain, targets: torch.Tensor, beam: int) -> Inferred:
    """Beam search, execute every candidate, keep the best by the domain metric per shape.

    targets (B, *shape) bool. Empty slots of the beam (fewer complete programs
    than ``beam``) score the metric's worst value.
    """
    device = next(model.parameters()).device
    targets = targets.to(device)
    result = beam_search(model, domain.tokens, targets, beam)
    B, K, L = result.programs.shape
    flat = result.programs.view(B * K, L)
    executed = domain.execute(flat).view(B, K, *domain.shape)
    values = domain.metric.score_candidates(executed, targets)
    values = torch.where(torch.isfinite(result.logp), values, torch.full_like(values, domain.metric.worst))
    best_value, best = domain.metric.best(values, dim=1)
    rows = torch.arange(B, device=device)
    programs = [result.program(b, int(best[b])) for b in range(B)]
    return Inferred(programs, best_value, executed[rows, best], result)


def infer_batched(model: PLADNet, domain: Domain, targets: np.ndarray, beam: int, batch_size: int,
                  desc: str = "infer") -> tuple[np.ndarray, list[list[int]], np.ndarray]:
    """:func:`infer_programs` over many shapes in batches, with a progress bar.

    targets bool (N, *shape) -> (metric values (N,), best programs, executions bool (N, *shape)).
    """
    device = next(model.parameters()).device
    values, programs, shapes = [], [], []
    for start in tqdm(range(0, len(targets), batch_size), desc=desc, unit="batch", disable=None):
        inferred = infer_programs(model, domain, to_device(targets[start:start + batch_size], device), beam)
        values.append(inferred.values.cpu().numpy())
        programs.extend(inferred.programs)
        shapes.append(inferred.shapes.cpu().numpy())
    return (np.concatenate(values) if values else np.zeros(0), programs,
            np.concatenate(shapes) if shapes else np.zeros((0, *domain.shape), bool))


@torch.no_grad()
def greedy_decode(model: PLADNet, table: TokenTable, shapes: torch.Tensor) -> list[list[int]]:
    """Most likely token at every step under the grammar mask (reference for beam 1)."""
    model.eval()
    logits, caches = model.start(model.encode(shapes))
    state = table.initial_state(shapes.shape[0], shapes.device)
    out: list[list[int]] = [[] for _ in range(shapes.shape[0])]
    for pos in range(1, table.max_len + 1):
        live = ~state.done
        tok = logits.masked_fill(~table.mask(state), NEG).argmax(-1)
        for i in torch.nonzero(live).flatten().tolist():
            out[i].append(int(tok[i]))
        state = table.advance(state, tok)
        if bool(state.done.all()) or pos == table.max_len:
            break
        logits, caches = model.step(tok, caches, pos)
    return out
