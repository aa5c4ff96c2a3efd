"""Length-bucketed batches (plad.data.batching): every example once, less padding, the same per-token loss."""
from __future__ import annotations

import numpy as np
import torch

from plad.data.batching import bucket_batches, bucketed, padding_share, split_batch, trim
from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.learn.methods import Mixture, mixture_batches
from plad.model.network import ModelConfig, PLADNet
from tests.tiny import ARCHITECTURE


def test_buckets_use_every_example_once_in_batches_of_similar_length():
    rng = np.random.default_rng(0)
    lengths = rng.integers(3, 100, size=250)
    batches = bucket_batches(lengths, 32, np.random.default_rng(1))
    assert sorted(np.concatenate(batches).tolist()) == list(range(250))
    assert sorted(len(b) for b in batches) == [26] + [32] * 7
    ranges = sorted((lengths[b].min(), lengths[b].max()) for b in batches)
    assert all(hi <= lo_next for (_, hi), (lo_next, _) in zip(ranges, ranges[1:]))   # disjoint length ranges
    plain = [lengths[i:i + 32] for i in range(0, 250, 32)]
    assert padding_share([lengths[b] for b in batches]) < padding_share(plain) / 3
    # the order of the batches is random, and fixed by the generator
    again = bucket_batches(lengths, 32, np.random.default_rng(1))
    assert all((a == b).all() for a, b in zip(batches, again))
    assert [int(lengths[b].max()) for b in batches] != sorted(int(lengths[b].max()) for b in batches)


def test_any_stream_of_batches_can_be_bucketed():
    """A sampler's stream (here a fixed list of index batches) regrouped pool by pool; pool 1 leaves it alone."""
    rng = np.random.default_rng(4)
    lengths = rng.integers(1, 100, size=1000)
    stream = [rng.choice(1000, size=16, replace=False) for _ in range(10)]
    assert all((a == b).all() for a, b in zip(bucketed(iter(stream), lengths, 1, rng), stream))
    out = list(bucketed(iter(stream), lengths, 4, np.random.default_rng(0)))
    assert len(out) == 8 and all(len(b) == 16 for b in out)      # two pools of four; the last two batches wait
    for k in range(2):
        pool = np.concatenate(stream[4 * k:4 * k + 4])
        got = out[4 * k:4 * k + 4]
        assert sorted(np.concatenate(got).tolist()) == sorted(pool.tolist())
        assert sum(int(lengths[b].max() - lengths[b].min()) for b in got) < \
            sum(int(lengths[b].max() - lengths[b].min()) for b in stream[4 * k:4 * k + 4]) / 3


def test_bucketing_leaves_the_loss_of_a_fixed_batch_unchanged():
    """The same examples as one batch padded to the length cap, or bucketed and trimmed: the same mean
    per-token loss and accuracy (the model in eval mode: no dropout)."""
    domain = get_domain("csg3d")
    programs = domain.sample(48, np.random.default_rng(2))
    full = pad_programs(programs)
    full = torch.cat([full, torch.zeros(48, domain.tokens.max_len - full.shape[1], dtype=torch.long)], 1)
    lengths = torch.tensor([len(p) for p in programs])
    shapes = domain.execute(full)
    torch.manual_seed(0)
    model = PLADNet(ModelConfig(vocab_size=len(domain.tokens), max_len=domain.tokens.max_len,
                                input_shape=domain.shape, **ARCHITECTURE)).eval()
    with torch.no_grad():
        loss, acc = model.loss(shapes, full, lengths)
        parts = split_batch((shapes, full, lengths), 8, np.random.default_rng(3))
        assert len(parts) == 6 and all(p[1].shape[1] == int(p[2].max()) < domain.tokens.max_len for p in parts)
        k = [int(p[2].sum()) for p in parts]
        results = [model.loss(*p) for p in parts]
    bucketed = sum(float(r[0]) * n for r, n in zip(results, k)) / sum(k)
    bucketed_acc = sum(float(r[1]) * n for r, n in zip(results, k)) / sum(k)
    assert abs(bucketed - float(loss)) < 1e-5
    assert abs(bucketed_acc - float(acc)) < 1e-6


def test_trim_cuts_to_the_longest_program():
    programs = torch.arange(20).reshape(2, 10)
    assert trim(programs, torch.tensor([3, 7])).shape == (2, 7)
    assert trim(programs, torch.tensor([0, 0])).shape == (2, 1)


def test_mixture_batches_bucket_each_source_and_keep_the_weights():
    def source(tag):
        def draw(rng, n):
            lengths = torch.from_numpy(rng.integers(1, 40, size=n))
            programs = torch.full((n, 50), tag)
            return torch.full((n,), tag), programs, lengths
        return draw

    batches = mixture_batches(Mixture(("lest", "st"), (0.75, 0.25)), {"lest": source(1), "st": source(2)}, 16,
                              seed=0, bucket_pool=8)
    stream = batches(0)
    drawn = [next(stream) for _ in range(800)]
    tags = np.array([int(b[0][0]) for b in drawn])
    assert all(len(set(b[0].tolist())) == 1 and len(b[0]) == 16 for b in drawn)
    assert abs((tags == 1).mean() - 0.75) < 0.05
    assert all(b[1].shape[1] == int(b[2].max()) for b in drawn)            # trimmed
    spread = np.mean([int(b[2].max() - b[2].min()) for b in drawn])
    assert spread < 10                                                     # plain batches: about 35
    first = [next(s)[2].tolist() for s in (batches(3), batches(3))]
    assert first[0] == first[1]                                            # fixed by (seed, epoch)


def test_pretraining_with_buckets_runs(tmp_path):
    from plad.layout import SUMMARY, Layout
    from plad.learn.pretrain import PretrainConfig, pretrain
    from plad.learn.train import TrainConfig
    from plad.model.network import Architecture
    from plad.stages.synthesize import SynthesizeConfig, synthesize

    layout = Layout(tmp_path)
    synthesize(SynthesizeConfig(domain="csg2d", train_programs=200, val_programs=20), layout)
    cfg = PretrainConfig(domain="csg2d", device="cpu", val_metric_shapes=4, model=Architecture(**ARCHITECTURE),
                         train=TrainConfig(batch_size=16, steps_per_epoch=5, max_epochs=2, bucket_pool=4))
    summary = pretrain(cfg, layout)
    assert summary["units"] == 2 and (layout.pretrain_dir("csg2d") / SUMMARY).exists()
