"""Benchmarks: each prints our speed and a baseline's, measured in the same run, and last ``ratio <ours/baseline>``."""
from __future__ import annotations

from pathlib import Path


def prepared_test_shapes(domain, n: int):
    """(bool tensor (n, *shape), description): the first ``n`` prepared test shapes of ``domain`` when
    ``data/prepared/<domain>.npz`` exists, else random occupancy."""
    import torch

    prepared = Path("data/prepared") / f"{domain.name}.npz"
    if prepared.exists():
        from plad.data.files import load_prepared

        x = torch.from_numpy(load_prepared(prepared, "test")[:n]).bool()
        return x, f"{len(x)} test shapes of {prepared}"
    x = torch.rand(n, *domain.shape) > 0.9
    return x, f"{len(x)} random shapes"
