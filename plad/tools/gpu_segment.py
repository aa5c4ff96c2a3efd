"""One pretraining segment on a lent GPU machine: the prepared command of issue 58 (step 6).

A lent GPU machine has torch, numpy and PyYAML but no MLflow, DVC or network, holds the repository's working
tree (the shipped networks included) and gives back at most eight small files. This command needs nothing more:

1. it samples fresh synthetic programs of the domain (the synthesize stage's sampler and canonical form) in
   ``--procs`` processes, chunk by chunk: chunk ``i`` of a split draws from its own generator (child ``i`` of
   the split's ``SeedSequence(seed)`` child), so the programs depend on ``--seed``, ``--programs`` and
   ``--chunk``, not on the number of processes. ``--seed`` defaults to one past the largest seed the shipped
   network's segments record: programs it never saw;
2. it continues the domain's shipped pretrained network on them with the pretrain stage's own function
   (:func:`plad.learn.pretrain.pretrain`: ``init: shipped``, ``continue_lr: restart``, resumable, the segment
   recorded in the checkpoint's provenance) for ``--minutes`` of training, on the GPU in bf16 where it computes
   it natively, its synthetic programs executed by ``--loader-workers`` processes (where the
   domain's executor runs on the CPU; default: the params' ``loader_workers``), the rest of the settings the
   params file's ``pretrain.<domain>`` section (and ``--set`` overrides, as a stage takes them);
3. it copies what a later session ships into ``--out``: ``last.pt`` (the whole state: ``plad models
   ship-pretrained DOMAIN last.pt`` ships it), ``summary.json``, ``history.csv``, ``provenance.json`` and
   ``synthetic.json``.

The prepared command (docs/gpu.md, section 1b, names the domain and the workers; at most ten minutes a call):
``python -m plad.tools.gpu_segment DOMAIN --out $OUT/<name> --minutes 7 --loader-workers 14``, with ``carry:
["data/prepared/<domain>.npz"]`` for the real validation shapes. CI runs it on the CPU as a dry run of a
few seconds (tests/plad/tools/test_gpu_segment.py), with MLflow, DVC and Prefect made unimportable, as they
are there: the command that failed a lease before had never run (docs/pretraining.md).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

#: what the command copies into ``--out`` (each well under the 16 MiB a lent machine gives back per file)
RESULTS = ("last.pt", "summary.json", "history.csv", "provenance.json")


def next_seed(domain: str) -> int:
    """One past the largest synthesis seed the shipped pretrained network's segments record (0 if none does)."""
    from plad.shipped import pretrained_model

    model = pretrained_model(domain)
    segments = (model.info.get("provenance") or {}).get("segments", []) if model is not None else []
    seeds = [s["synthetic"]["seed"] for s in segments if isinstance((s.get("synthetic") or {}).get("seed"), int)]
    return max(seeds, default=-1) + 1


def _chunk(args: tuple[str, str, np.random.SeedSequence, int]) -> np.ndarray:
    """The programs of one chunk, canonical, as the synthesize stage's padded int16 array."""
    from plad.device import torch_threads
    from plad.domains import get_domain
    from plad.stages.synthesize import to_array

    domain_name, sampler, seq, n = args
    domain = get_domain(domain_name)
    with torch_threads(1):   # the samplers' tiny operations only slow down on many threads (docs/gpu.md)
        programs = [domain.canonical(p) for p in domain.samplers()[sampler](n, np.random.default_rng(seq))]
    return to_array(programs, domain.tokens.max_len)


def sample_programs(domain_name: str, sampler: str, seed: int, counts: dict[str, int], chunk: int,
                    procs: int) -> dict[str, np.ndarray]:
    """``{split: (n, max_len) int16}`` and the complexities, the same for any ``procs`` (module docstring)."""
    from plad.config import ConfigError
    from plad.domains import get_domain

    domain = get_domain(domain_name)
    if sampler not in domain.samplers():
        raise ConfigError(f"--sampler {sampler!r}: the {domain_name} domain offers "
                          f"{', '.join(map(repr, domain.samplers()))}")
    split_seqs = dict(zip(("val", "train"), np.random.SeedSequence(seed).spawn(2)))
    jobs, owners = [], []
    for split, n in counts.items():
        sizes = [min(chunk, n - s) for s in range(0, n, chunk)]
        jobs += [(domain_name, sampler, seq, size) for seq, size in zip(split_seqs[split].spawn(len(sizes)), sizes)]
        owners += [split] * len(sizes)
    if procs > 1 and len(jobs) > 1:
        with ProcessPoolExecutor(procs) as pool:
            parts = list(pool.map(_chunk, jobs))
    else:
        parts = [_chunk(job) for job in jobs]
    arrays = {split: np.concatenate([p for p, o in zip(parts, owners) if o == split] or
                                    [np.zeros((0, domain.tokens.max_len), np.int16)]) for split in counts}
    if domain.complexity_kind is not None:
        for split in counts:
            arrays[f"{split}_complexity"] = domain.complexity(arrays[split]).astype(np.int16)
    return arrays


def write_synthetic(layout, domain_name: str, sampler: str, seed: int, chunk: int,
                    arrays: dict[str, np.ndarray], seconds: float) -> dict:
    """The programs where the pretraining reads them, and their summary (``synthetic.json``, which the segment's
    provenance quotes: sampler and seed)."""
    from plad.fsutil import atomic_write, atomic_write_text, savez

    atomic_write(layout.synthetic(domain_name), lambda fh: savez(fh, **arrays))
    lengths = (arrays["train"] >= 0).sum(1)
    summary = {"domain": domain_name, "sampler": sampler, "seed": seed, "chunk": chunk,
               "train": int(len(arrays["train"])), "val": int(len(arrays["val"])),
               "mean_length": round(float(lengths.mean()), 3) if len(lengths) else 0.0,
               "seconds": round(seconds, 1), "made_by": "plad.tools.gpu_segment"}
    atomic_write_text(layout.synthetic_summary(domain_name), json.dumps(summary, indent=2) + "\n")
    return summary


def segment_config(params: Path, profile: str | None, domain: str, sets: list[str], a: argparse.Namespace):
    """``pretrain.<domain>`` of the params file, ``--set`` applied, then this command's settings of a segment."""
    from plad.config import apply_overrides, build, load_params, lookup, section_class

    name = f"pretrain.{domain}"
    loaded = load_params(params, profile)
    raw = apply_overrides(lookup(loaded, name), sets, name)
    cfg = build(section_class("pretrain"), raw, name, str(params))
    train = replace(cfg.train, batch_size=a.batch_size or cfg.train.batch_size, max_epochs=a.max_epochs,
                    patience=a.max_epochs, lr=a.lr if a.lr is not None else cfg.train.lr)
    workers = a.loader_workers if a.loader_workers is not None else cfg.loader_workers
    return replace(cfg, device=a.device, precision=a.precision, init="shipped", continue_lr="restart",
                   max_minutes=a.minutes, loader_workers=workers, threads=a.threads, train=train,
                   real_val_shapes=cfg.real_val_shapes if a.real_val else 0)


def run(a: argparse.Namespace) -> dict:
    from plad.config import ConfigError
    from plad.layout import Layout
    from plad.learn.pretrain import pretrain
    from plad.provenance import stamp
    from plad.shipped import pretrained_checkpoint

    started = time.monotonic()
    work = Path(a.work) if a.work else Path(tempfile.gettempdir()) / "plad_gpu_segment"
    layout = Layout(work)
    cfg = segment_config(Path(a.params), a.profile, a.domain, a.set or [], a)
    if cfg.real_val_shapes:   # the prepared real shapes travel with `carry`; here, from the checkout
        target = layout.prepared(a.domain)
        source = Path(a.params).resolve().parent / "data" / "prepared" / target.name
        if not target.exists() and source.exists():
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source, target)
        if not target.exists():   # said before minutes go to the programs
            raise ConfigError(f"{source}: the real validation shapes are not there (carry data/prepared/"
                              f"{target.name} to the lent machine, or --no-real-val)")
    seed = a.seed if a.seed is not None else next_seed(a.domain)
    if not layout.synthetic(a.domain).exists():   # a resumed call keeps its programs
        t = time.monotonic()
        arrays = sample_programs(a.domain, a.sampler, seed, {"val": a.val_programs, "train": a.programs},
                                 a.chunk, a.procs)
        synthetic = write_synthetic(layout, a.domain, a.sampler, seed, a.chunk, arrays, time.monotonic() - t)
        print(f"synthesized {synthetic['train']:,} + {synthetic['val']:,} programs (seed {seed}) in "
              f"{synthetic['seconds']} s on {a.procs} processes", flush=True)
    summary = pretrain(cfg, layout, init_path=pretrained_checkpoint(a.domain))
    summary = {**summary, "provenance": stamp(cfg, started)}
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    folder = layout.pretrain_dir(a.domain)
    (folder / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    for name in RESULTS:
        if (folder / name).exists():
            shutil.copyfile(folder / name, out / name)
    shutil.copyfile(layout.synthetic_summary(a.domain), out / "synthetic.json")
    return summary


def parser() -> argparse.ArgumentParser:
    from plad.domains import domain_names

    p = argparse.ArgumentParser(prog="python -m plad.tools.gpu_segment", description=__doc__.splitlines()[0])
    p.add_argument("domain", choices=domain_names())
    p.add_argument("--out", required=True, help="where the results are copied (on a lent machine: under $OUT)")
    p.add_argument("--work", default=None,
                   help="layout root of the run (programs, state; default: plad_gpu_segment in the temporary folder)")
    p.add_argument("--params", default="params.yaml")
    p.add_argument("--profile", default=None, help="the params file's own profile unless given")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override of pretrain.<domain>")
    p.add_argument("--minutes", type=float, default=7.0, help="training budget of the segment")
    p.add_argument("--max-epochs", type=int, default=100_000, help="epochs of the segment (the minutes end it first)")
    p.add_argument("--programs", type=int, default=150_000, help="fresh training programs")
    p.add_argument("--val-programs", type=int, default=1_000)
    p.add_argument("--seed", type=int, default=None, help="synthesis seed (default: one the shipped network never saw)")
    p.add_argument("--sampler", default="paper")
    p.add_argument("--chunk", type=int, default=2_000, help="programs per synthesis chunk")
    p.add_argument("--procs", type=int, default=os.cpu_count() or 1, help="synthesis processes")
    p.add_argument("--device", default="auto")
    p.add_argument("--precision", default="auto", help="auto: bf16 on a GPU that computes it natively")
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--lr", type=float, default=None)
    p.add_argument("--loader-workers", type=int, default=None,
                   help="program-executing processes (default: the params' loader_workers; 0: executed in the "
                        "training process, on its device)")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads of the training process")
    p.add_argument("--no-real-val", dest="real_val", action="store_false",
                   help="no real validation shapes (when data/prepared/<domain>.npz did not travel)")
    return p


def main(argv: list[str] | None = None) -> int:
    from plad.errors import PladError

    a = parser().parse_args(argv)
    try:
        summary = run(a)
    except PladError as err:
        print(f"gpu_segment: error: {err}", file=sys.stderr)
        return 2
    keys = ("units", "best_unit", "stopped", "train_seconds", "wall_seconds_this_call", "val_loss", "val_iou",
            "val_chamfer", "real_val_iou", "real_val_chamfer")
    print(json.dumps({k: summary[k] for k in keys if k in summary}))
    return 0


if __name__ == "__main__":   # loader and synthesis processes import this module: nothing runs on import
    sys.exit(main())
