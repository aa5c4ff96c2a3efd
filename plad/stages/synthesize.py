"""Stage ``synthesize``: sample the synthetic pretraining programs of a domain.

Writes ``data/synthetic/<domain>.npz`` (:mod:`plad.layout`) with ``train``/``val`` token arrays
(N, max_len) int16 padded with -1, drawn with a fixed seed (train and val
from independent streams) and rewritten into the domain's canonical form
(:meth:`plad.domains.base.Domain.canonical`), and, where the domain defines a complexity
(:meth:`plad.domains.base.Domain.complexity`), ``train_complexity``/``val_complexity``
(N,) int16: what the pretraining curriculum orders by. Shapes are not stored: the executor renders them
on the fly far faster than they could be read back.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field

import numpy as np
from tqdm import tqdm

from plad.fsutil import atomic_write, atomic_write_text, savez
from plad.layout import Layout
from plad.stages import stage_main


@dataclass
class SynthesizeConfig:
    domain: str = field(kw_only=True)
    train_programs: int = 100_000
    val_programs: int = 1_000
    seed: int = 0
    #: which of the domain's samplers (:meth:`plad.domains.base.Domain.samplers`): "paper", or e.g. 3D CSG's
    #: "parts" (beyond the paper)
    sampler: str = "paper"


def to_array(programs: list[list[int]], max_len: int) -> np.ndarray:
    out = np.full((len(programs), max_len), -1, dtype=np.int16)
    for i, p in enumerate(programs):
        out[i, : len(p)] = p
    return out


def from_array(array: np.ndarray) -> list[list[int]]:
    return [row[row >= 0].tolist() for row in array]


def synthesize(cfg: SynthesizeConfig, layout: Layout = Layout(), chunk: int = 10_000) -> dict:
    from plad.config import ConfigError
    from plad.device import torch_threads
    from plad.domains import get_domain
    from plad.provenance import stamp

    started = time.monotonic()
    domain = get_domain(cfg.domain)
    samplers = domain.samplers()
    if cfg.sampler not in samplers:
        raise ConfigError(f"synthesize.{cfg.domain}.sampler {cfg.sampler!r}: the {cfg.domain} domain offers "
                          f"{', '.join(map(repr, samplers))}")
    sample = samplers[cfg.sampler]
    train_rng, val_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(cfg.seed).spawn(2))
    arrays = {}
    for split, n, rng in (("val", cfg.val_programs, val_rng), ("train", cfg.train_programs, train_rng)):
        parts = []
        for start in tqdm(range(0, n, chunk), desc=f"synthesize {split}", unit="chunk", disable=None):
            # labels in the domain's canonical form: the same shapes, no free choices left to guess. One torch
            # thread: the sampler's tiny operations only slow down on many (the same programs; plad.device)
            with torch_threads(1):
                programs = [domain.canonical(p) for p in sample(min(chunk, n - start), rng)]
            parts.append(to_array(programs, domain.tokens.max_len))
        arrays[split] = np.concatenate(parts) if parts else np.zeros((0, domain.tokens.max_len), np.int16)
    if domain.complexity_kind is not None:
        for split in ("val", "train"):
            arrays[f"{split}_complexity"] = domain.complexity(arrays[split]).astype(np.int16)
    atomic_write(layout.synthetic(cfg.domain), lambda fh: savez(fh, **arrays))
    lengths = (arrays["train"] >= 0).sum(1)
    summary = {"domain": cfg.domain, "sampler": cfg.sampler, "seed": cfg.seed, "train": int(len(arrays["train"])),
               "val": int(len(arrays["val"])),
               "mean_length": round(float(lengths.mean()), 3) if len(lengths) else 0.0}
    if "train_complexity" in arrays and len(lengths):
        values, counts = np.unique(arrays["train_complexity"], return_counts=True)
        summary["train_complexity"] = {int(v): int(c) for v, c in zip(values, counts)}
    summary["provenance"] = stamp(cfg, started)
    atomic_write_text(layout.synthetic_summary(cfg.domain), json.dumps(summary, indent=2) + "\n")
    return summary


def main(argv: list[str] | None = None) -> int:
    return stage_main("synthesize", SynthesizeConfig, lambda cfg, ctx: synthesize(cfg, ctx.layout), argv,
                      __doc__.splitlines()[0])

if __name__ == "__main__":
    sys.exit(main())
