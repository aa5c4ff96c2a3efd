"""Growing a network keeps what it computes (plad.model.grow): the grown network's logits equal the trained
one's in evaluation, its sizes are the ones asked for, its new capacity gets gradients from the first step,
and what cannot grow exactly is refused with a message naming the knob."""
from __future__ import annotations

import pytest
import torch

from plad.model.grow import grow, grown_config
from plad.model.network import ModelConfig, PLADNet

pytestmark = pytest.mark.unit

BASE = dict(d_model=32, n_layers=2, n_heads=4, dim_ff=48, dropout=0.1, vocab_size=20, max_len=9)


def _trained_like(cfg: ModelConfig, seed: int = 0) -> PLADNet:
    """A network whose weights and batch-norm statistics are all away from their initial values."""
    torch.manual_seed(seed)
    model = PLADNet(cfg)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
        for m in model.modules():
            if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                m.running_mean.uniform_(-0.3, 0.3)
                m.running_var.uniform_(0.5, 2.0)
    return model.eval()


def _inputs(cfg: ModelConfig, n: int = 5):
    g = torch.Generator().manual_seed(1)
    shapes = torch.rand(n, *cfg.input_shape, generator=g) > 0.6
    tokens = torch.randint(0, cfg.vocab_size, (n, cfg.max_len), generator=g)
    tokens[:, 0] = cfg.bos
    return shapes, tokens


CASES = {
    "2d": dict(input_shape=(64, 64), enc_channels=(4, 8, 8, 16)),
    "2d batch norm, prefix bos": dict(input_shape=(64, 64), enc_channels=(4, 8, 8, 16), enc_norm=True,
                                      prefix_bos=True),
    "3d coord channels": dict(input_shape=(32, 32, 32), enc_channels=(4, 8, 8), coord_channels=True),
    "3d prefix norm": dict(input_shape=(32, 32, 32), enc_channels=(4, 8, 8), enc_norm=True, prefix_norm=True),
}
GROW = {
    "encoder": dict(enc_channels=None),     # filled per case: every block doubled
    "feed-forward": dict(dim_ff=96),
    "two more layers": dict(n_layers=4),
    "all three": dict(enc_channels=None, dim_ff=64, n_layers=3),
}


@pytest.mark.parametrize("grow_name", list(GROW))
@pytest.mark.parametrize("case", list(CASES))
def test_grown_network_computes_the_same_logits(case, grow_name):
    cfg = ModelConfig(**BASE, **CASES[case])
    model = _trained_like(cfg)
    sizes = {k: (tuple(2 * c for c in cfg.enc_channels) if k == "enc_channels" else v)
             for k, v in GROW[grow_name].items()}
    torch.manual_seed(7)
    big = grow(model, **sizes)
    for k, v in sizes.items():
        assert getattr(big.cfg, k) == v
    assert not big.training
    assert sum(p.numel() for p in big.parameters()) > sum(p.numel() for p in model.parameters())
    shapes, tokens = _inputs(cfg)
    with torch.no_grad():
        want, got = model(shapes, tokens), big(shapes, tokens)
    assert want.shape == got.shape
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)


def test_growing_is_repeatable_from_the_seed_and_leaves_the_source_alone():
    cfg = ModelConfig(**BASE, input_shape=(64, 64), enc_channels=(4, 8, 8, 16))
    model = _trained_like(cfg)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    torch.manual_seed(3)
    a = grow(model, enc_channels=(8, 8, 16, 32), n_layers=3)
    torch.manual_seed(3)
    b = grow(model, enc_channels=(8, 8, 16, 32), n_layers=3)
    for k, v in a.state_dict().items():
        assert torch.equal(v, b.state_dict()[k]), k
    for k, v in model.state_dict().items():
        assert torch.equal(v, before[k]), k


def test_new_capacity_gets_gradients_from_the_first_step():
    cfg = ModelConfig(**BASE, input_shape=(64, 64), enc_channels=(4, 8, 8, 16))
    model = _trained_like(cfg)
    big = grow(model, enc_channels=(4, 8, 8, 32), n_layers=3, dim_ff=64).train()
    shapes, tokens = _inputs(cfg)
    programs = tokens[:, 1:].clamp(max=cfg.vocab_size - 1)
    loss, _ = big.loss(shapes, programs, torch.full((len(programs),), programs.shape[1]))
    loss.backward()
    assert big.encoder.mlp[0].weight.grad[:, 16:].abs().sum() > 0        # reads the new encoder channels
    assert big.layers[2].out.weight.grad.abs().sum() > 0                # the new layer's attention output
    assert big.layers[2].ff[3].weight.grad.abs().sum() > 0
    assert big.layers[0].ff[3].weight.grad[:, 48:].abs().sum() > 0      # the new hidden units


@pytest.mark.parametrize("sizes, message", [
    (dict(enc_channels=(4, 8, 16)), "has 4 encoder blocks"),
    (dict(enc_channels=(4, 8, 4, 16)), "at least the channels it has"),
    (dict(n_layers=1), "n_layers 1: the network has 2"),
    (dict(dim_ff=8), "dim_ff 8: the network has 48"),
])
def test_what_would_shrink_is_refused(sizes, message):
    cfg = ModelConfig(**BASE, input_shape=(64, 64), enc_channels=(4, 8, 8, 16))
    with pytest.raises(ValueError, match=message):
        grown_config(cfg, **sizes)


def test_nothing_asked_is_the_same_network():
    cfg = ModelConfig(**BASE, input_shape=(64, 64), enc_channels=(4, 8, 8, 16))
    model = _trained_like(cfg)
    same = grow(model)
    assert same.cfg == model.cfg
    for k, v in model.state_dict().items():
        assert torch.equal(v, same.state_dict()[k]), k
