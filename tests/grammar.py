"""Random programs of a domain drawn under its grammar mask (the decoder's view of the grammar)."""
from __future__ import annotations

import torch


def masked_rollouts(domain, n: int, seed: int) -> list[list[int]]:
    """Uniformly random decoding under the grammar mask, all rows in one batch."""
    table = domain.tokens
    gen = torch.Generator().manual_seed(seed)
    state = table.initial_state(n)
    out = [[] for _ in range(n)]
    for _ in range(table.max_len):
        mask = table.mask(state)
        live = ~state.done
        if not live.any():
            break
        # a live row must always have a way forward: the mask is never a dead end
        assert mask[live].any(dim=1).all()
        probs = mask.float() + (~live).float()[:, None] * 1e-9  # finished rows draw anything, ignored
        tok = torch.multinomial(probs, 1, generator=gen)[:, 0]
        for i in torch.nonzero(live).flatten().tolist():
            out[i].append(int(tok[i]))
        state = table.advance(state, tok)
    assert state.done.all(), "masked decoding must finish within the length cap"
    return out
