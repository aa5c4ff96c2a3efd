"""Ancestral sampling of programs from p(z | prefix) under the grammar mask.

Shared by REINFORCE (prefix = the encoding of a real shape) and the
wake-sleep generator (prefix = the decoding of a latent code).
"""
from __future__ import annotations

import torch

from plad.domains.grammar import TokenTable
from plad.model.network import PLADNet

NEG = float("-inf")


@torch.no_grad()
def ancestral_sample(model: PLADNet, table: TokenTable, prefix: torch.Tensor,
                     generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """prefix (N, P, d) -> (tokens (N, L) long, zero padded; lengths (N,)); every row a complete valid program.

    The mask keeps only tokens that can still finish within the length cap,
    so sampling always ends in a valid program.
    """
    n, L = prefix.shape[0], table.max_len
    logits, caches = model.start(prefix)
    state = table.initial_state(n, prefix.device)
    tokens = torch.zeros(n, L, dtype=torch.long, device=prefix.device)
    lengths = torch.zeros(n, dtype=torch.long, device=prefix.device)
    for pos in range(L):
        live = ~state.done
        if not bool(live.any()):
            break
        probs = torch.softmax(logits.float().masked_fill(~table.mask(state), NEG), -1)
        # finished rows: any distribution (their draw is discarded below)
        probs = torch.where(live[:, None], probs, torch.full_like(probs, 1.0 / probs.shape[1]))
        tok = torch.multinomial(probs, 1, generator=generator)[:, 0]
        tokens[:, pos] = torch.where(live, tok, tokens[:, pos])
        lengths += live.long()
        state = table.advance(state, tok)
        if pos + 1 < L:
            logits, caches = model.step(tok, caches, pos + 1)
    return tokens, lengths
