"""Stage ``prepare``: verify the real target shapes and write them compactly.

Reads each domain's real data from the data directory (checked against its
sha256), and writes ``<out_dir>/<domain>.npz`` (bit-packed splits) plus
``<out_dir>/<domain>.json`` (counts and occupancy), atomically.
"""
from __future__ import annotations

import json
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plad.fsutil import atomic_write, atomic_write_text
from plad.stages import stage_main

SPLITS = ("train", "val", "test")


@dataclass
class PrepareConfig:
    #: directory holding the datasets; null means $PLAD_DATA_DIR, else ./data/datasets
    data_dir: str | None = None
    #: domains whose real data is prepared
    domains: list[str] = field(default_factory=lambda: ["csg2d"])
    out_dir: str = "data/prepared"


def prepare(cfg: PrepareConfig) -> dict[str, dict]:
    """Load, verify and pack every configured domain's real splits; returns the summaries."""
    from plad.domains import get_domain

    summaries = {}
    for name in cfg.domains:
        domain = get_domain(name)
        splits = {s: domain.target_data(s, cfg.data_dir) for s in SPLITS}
        arrays = {}
        for s, shapes in splits.items():
            arrays[s] = np.packbits(shapes.reshape(len(shapes), -1), axis=1)
        arrays["shape"] = np.asarray(domain.shape)
        summary = {
            "domain": name,
            "shape": list(domain.shape),
            **{f"{s}_count": int(len(x)) for s, x in splits.items()},
            **{f"{s}_occupancy": round(float(x.mean()), 6) for s, x in splits.items()},
        }
        out = Path(cfg.out_dir)
        atomic_write(out / f"{name}.npz", lambda fh: np.savez_compressed(fh, **arrays))
        atomic_write_text(out / f"{name}.json", json.dumps(summary, indent=2) + "\n")
        summaries[name] = summary
    return summaries


def load_prepared(path: str | os.PathLike, split: str) -> np.ndarray:
    """Read one split back from a prepared ``.npz``: bool (N, *shape)."""
    with np.load(path) as z:
        shape = tuple(int(v) for v in z["shape"])
        packed = z[split]
    return np.unpackbits(packed, axis=1, count=int(np.prod(shape))).astype(bool).reshape(-1, *shape)


def main(argv: list[str] | None = None) -> int:
    return stage_main("prepare", PrepareConfig, prepare, argv, __doc__.splitlines()[0])

if __name__ == "__main__":
    sys.exit(main())
