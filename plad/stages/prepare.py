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
        summaries[name] = write_prepared(name, tuple(domain.shape), splits, cfg.out_dir)
    return summaries


def write_prepared(name: str, shape: tuple[int, ...], splits: dict[str, np.ndarray], out_dir: str | os.PathLike,
                   extra: dict | None = None) -> dict:
    """Write ``<out_dir>/<name>.npz`` (bit-packed splits) and its ``.json`` summary; returns the summary."""
    arrays = {s: np.packbits(x.reshape(len(x), -1), axis=1) for s, x in splits.items()}
    arrays["shape"] = np.asarray(shape)
    summary = {
        "domain": name,
        "shape": list(shape),
        **{f"{s}_count": int(len(x)) for s, x in splits.items()},
        **{f"{s}_occupancy": round(float(x.mean()), 6) if len(x) else 0.0 for s, x in splits.items()},
        **(extra or {}),
    }
    out = Path(out_dir)
    atomic_write(out / f"{name}.npz", lambda fh: np.savez_compressed(fh, **arrays))
    atomic_write_text(out / f"{name}.json", json.dumps(summary, indent=2) + "\n")
    return summary


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
