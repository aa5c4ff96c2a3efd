"""Growing a trained network without changing what it computes (issue 58: capacity from a trained start).

Teaching measures one factor at a time at equal steps from the same start; to measure the network's
size, a larger network has to start where the trained one is, not from scratch. :func:`grow` builds
the larger :class:`PLADNet` and copies the trained one into it so that, in evaluation, the two give the
same logits (up to float summation order):

* ``enc_channels``: every encoder block may get more channels. The new channels read every input
  (fresh weights) but are read by nothing yet: the next convolution's and the encoder MLP's weights
  from them are zero. Pooling, ReLU and channel dropout act per channel, so the old channels are
  untouched.
* ``dim_ff``: every layer's feed-forward hidden units may grow, the new units' outgoing weights zero.
* ``n_layers``: new layers go after the trained ones with their two residual branches' output
  projections zero: a pre-norm layer whose branches add zero is the identity.

Zero outgoing weights still get gradients (their inputs are not zero), so training opens the new
capacity from the first step. What cannot grow this way (``d_model``: layer normalization over more
features changes every value) is refused.
"""
from __future__ import annotations

from dataclasses import replace

import torch
from torch import nn

from plad.model.network import ModelConfig, PLADNet

#: the architecture knobs :func:`grow` can enlarge
GROWABLE = ("enc_channels", "n_layers", "dim_ff")


def grown_config(cfg: ModelConfig, enc_channels=None, n_layers=None, dim_ff=None) -> ModelConfig:
    """``cfg`` with the given sizes (None: unchanged); ValueError where a size would shrink or change the shape."""
    sizes = {}
    if enc_channels is not None:
        enc_channels = tuple(int(c) for c in enc_channels)
        if len(enc_channels) != len(cfg.enc_channels):
            raise ValueError(f"enc_channels {list(enc_channels)}: the network has {len(cfg.enc_channels)} "
                             f"encoder blocks ({list(cfg.enc_channels)}); growing keeps their number")
        if any(new < old for new, old in zip(enc_channels, cfg.enc_channels)):
            raise ValueError(f"enc_channels {list(enc_channels)}: every block needs at least the channels it has "
                             f"({list(cfg.enc_channels)})")
        sizes["enc_channels"] = enc_channels
    for name, value in (("n_layers", n_layers), ("dim_ff", dim_ff)):
        if value is None:
            continue
        if int(value) < getattr(cfg, name):
            raise ValueError(f"{name} {value}: the network has {getattr(cfg, name)}; growing cannot shrink it")
        sizes[name] = int(value)
    return replace(cfg, **sizes)


@torch.no_grad()
def _copy_weights(new: nn.Module, old: nn.Module) -> None:
    """A linear layer's or convolution's old weights ((out, in, *kernel)) in the corner of the new one's: the new
    outputs keep their fresh rows, the new inputs are read with weight zero."""
    o, i = old.weight.shape[:2]
    new.weight[:, i:] = 0
    new.weight[:o, :i] = old.weight
    if old.bias is not None:
        new.bias[:o] = old.bias


@torch.no_grad()
def _copy_norm(new: nn.Module, old: nn.Module) -> None:
    """A batch norm's affine map and running statistics for the old channels (the new keep their defaults)."""
    c = old.num_features
    for name in ("weight", "bias", "running_mean", "running_var"):
        if getattr(old, name) is not None:
            getattr(new, name)[:c] = getattr(old, name)
    if old.num_batches_tracked is not None:
        new.num_batches_tracked.copy_(old.num_batches_tracked)


@torch.no_grad()
def grow(model: PLADNet, enc_channels=None, n_layers=None, dim_ff=None) -> PLADNet:
    """A larger network (in ``model``'s mode and device) computing what ``model`` computes.

    The new weights are drawn from torch's global generator: seed it first for a repeatable network.
    """
    cfg = grown_config(model.cfg, enc_channels, n_layers, dim_ff)
    new = PLADNet(cfg).to(next(model.parameters()).device)
    # encoder: conv blocks, then the MLP whose first layer reads the last block's channels
    for m_new, m_old in zip(new.encoder.net, model.encoder.net):
        if isinstance(m_old, (nn.Conv2d, nn.Conv3d)):
            _copy_weights(m_new, m_old)
        elif isinstance(m_old, nn.modules.batchnorm._BatchNorm):
            _copy_norm(m_new, m_old)
    _copy_weights(new.encoder.mlp[0], model.encoder.mlp[0])
    new.encoder.mlp[1:].load_state_dict(model.encoder.mlp[1:].state_dict())
    # decoder layers: the trained ones (feed-forward widened), then identities
    for layer_new, layer_old in zip(new.layers, model.layers):
        for name in ("ln1", "qkv", "out", "ln2"):
            getattr(layer_new, name).load_state_dict(getattr(layer_old, name).state_dict())
        _copy_weights(layer_new.ff[0], layer_old.ff[0])
        _copy_weights(layer_new.ff[3], layer_old.ff[3])
        # the hidden units the old network lacks: their outgoing weights zero (ff[3]'s new columns, set above)
    for layer in new.layers[len(model.layers):]:
        for lin in (layer.out, layer.ff[3]):
            lin.weight.zero_()
            lin.bias.zero_()
    # everything else has the same shape
    for name in ("embed", "ln", "head", "bos_proj", "prefix_norm"):
        if getattr(model, name) is not None:
            getattr(new, name).load_state_dict(getattr(model, name).state_dict())
    new.pos.copy_(model.pos)
    return new.train(model.training)
