"""The floor baseline of a domain: a trivial program per shape, found without a network.

The domain says what the floor is (:attr:`plad.domains.base.Domain.floor_name`,
e.g. "one box") and finds its programs (:meth:`~plad.domains.base.Domain.floor`);
here they are executed and scored with the domain's metric like any
inference, so the floor row of the results table is measured the same way
as the methods' rows.
"""
from __future__ import annotations

import numpy as np
import torch

from plad.domains.base import Domain, pad_programs


def evaluate_floor(domain: Domain, targets: np.ndarray, chunk: int = 500) -> tuple[np.ndarray, list[list[int]]]:
    """(metric values (N,), floor programs) of ``targets`` (bool (N, *shape)); the domain must offer a floor."""
    programs = domain.floor(targets)
    if len(programs) != len(targets):
        raise ValueError(f"{domain.name}.floor returned {len(programs)} programs for {len(targets)} targets")
    values = []
    for start in range(0, len(targets), chunk):
        part = programs[start:start + chunk]
        for p in part:
            domain.check(p)
        shapes = domain.execute(pad_programs(part))
        values.append(domain.metric(shapes, torch.from_numpy(targets[start:start + chunk])).numpy())
    return (np.concatenate(values) if values else np.zeros(0)), programs


__all__ = ["evaluate_floor"]
