"""Synthetic training batches (plad/learn/synthetic.py): executed in the training process, or ahead of time by
worker processes, the same batches in the same order; and pretraining with workers trains on exactly them."""
from __future__ import annotations

import csv

import numpy as np
import torch

from plad.domains import get_domain
from plad.learn.synthetic import ExecutorPool, make_batch

CPU = torch.device("cpu")


def rows(domain: str, n: int, seed: int) -> torch.Tensor:
    """``n`` sampled programs of ``domain`` as -1-padded rows (N, max_len), as the synthetic file holds them."""
    dom = get_domain(domain)
    out = torch.full((n, dom.tokens.max_len), -1, dtype=torch.long)
    for i, p in enumerate(dom.sample(n, np.random.default_rng(seed))):
        out[i, :len(p)] = torch.tensor(p)
    return out


def test_make_batch_executes_and_trims():
    dom = get_domain("shapeassembly")
    r = rows("shapeassembly", 5, 0)
    shapes, programs, lengths = make_batch(dom, r, CPU)
    assert lengths.tolist() == (r >= 0).sum(1).tolist() and programs.shape == (5, int(lengths.max()))
    assert torch.equal(shapes, dom.execute(programs)) and shapes.shape == (5, 32, 32, 32)


def test_the_pool_gives_make_batch_batches_in_order():
    dom = get_domain("shapeassembly")
    stream = [rows("shapeassembly", 6, seed) for seed in range(5)]
    with ExecutorPool("shapeassembly", workers=2, ahead=3) as pool:
        got = list(pool.batches(iter(stream), CPU))
    assert len(got) == len(stream)
    for batch, r in zip(got, stream):
        want = make_batch(dom, r, CPU)
        assert all(torch.equal(a, b) and a.dtype == b.dtype for a, b in zip(batch, want))


def history(path) -> list[dict]:
    with path.open() as fh:
        return [{k: v for k, v in row.items() if k != "epoch_seconds"} for row in csv.DictReader(fh)]


def test_pretraining_with_loader_workers_trains_on_the_same_batches(tmp_path):
    from plad.layout import HISTORY, Layout
    from plad.learn.pretrain import PretrainConfig, pretrain
    from plad.learn.train import TrainConfig
    from plad.model.network import Architecture
    from plad.stages.synthesize import SynthesizeConfig, synthesize
    from tests.tiny import ARCHITECTURE

    synthetic = Layout(tmp_path / "data")
    synthesize(SynthesizeConfig(domain="csg2d", train_programs=120, val_programs=16), synthetic)
    runs = {}
    for workers in (0, 1):
        layout = Layout(tmp_path / f"w{workers}")
        layout.synthetic("csg2d").parent.mkdir(parents=True)
        layout.synthetic("csg2d").write_bytes(synthetic.synthetic("csg2d").read_bytes())
        cfg = PretrainConfig(domain="csg2d", device="cpu", val_metric_shapes=4, gap_programs=8,
                             loader_workers=workers, model=Architecture(**ARCHITECTURE),
                             train=TrainConfig(batch_size=16, steps_per_epoch=3, max_epochs=1, bucket_pool=2))
        pretrain(cfg, layout)
        runs[workers] = history(layout.pretrain_dir("csg2d") / HISTORY)
    assert len(runs[0]) == 1 and runs[0] == runs[1]
