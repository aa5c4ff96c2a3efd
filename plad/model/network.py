"""The inference network p(z|x): a CNN encoder and an autoregressive Transformer decoder.

Pure model code: a config dataclass and modules, no I/O.

The encoder turns a shape into a few "visual tokens": a 2D CNN for 64 x 64
canvases, a 3D CNN (the paper's supplement) for 32^3 voxels, chosen from the
input shape. The decoder is a prefix Transformer as in the paper's 3D model:
the sequence is [visual tokens, BOS, z_1, ..., z_t]; visual tokens attend to
each other fully, program tokens attend to all visual tokens and causally to
earlier program tokens; learned positional embeddings; a 2-layer MLP head.
(The paper's 2D model is CSGNet's GRU; this project uses the Transformer in 2D
too, provided it does at least as well, because one network for every domain
keeps the search and training code generic.)

Incremental decoding keeps per-layer key/value caches, so beam search costs
one position per step instead of re-running the whole prefix.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn


@dataclass
class Architecture:
    """The architecture knobs of :class:`PLADNet`: the params section ``pretrain.<domain>.model``.

    The one home of these knobs and their defaults; the sizes that come from
    the domain (vocabulary, length cap, input shape) are added by
    :class:`ModelConfig`.
    """

    d_model: int = 256
    n_layers: int = 4
    n_heads: int = 8
    dim_ff: int = 1024
    dropout: float = 0.1
    enc_channels: tuple[int, ...] = (32, 64, 128, 256)
    #: batch normalization after every encoder convolution
    enc_norm: bool = False
    #: append the voxel/pixel coordinates in [-1, 1] as input channels (CoordConv): parameters are
    #: positions and sizes, which translation-equivariant convolutions and max-pooling blur
    coord_channels: bool = False
    #: encoder kernel size (None: 3 in 2D, the paper's 4 in 3D); padding is kernel // 2
    enc_kernel: int | None = None
    #: initialization of the encoder convolutions: "default" (torch's, uniform with a = sqrt(5): the
    #: activations shrink by about half per block, so the visual tokens of different shapes start out
    #: nearly equal) or "kaiming" (He normal for ReLU, zero bias: the variance is kept through the blocks)
    enc_init: str = "default"
    #: condition the BOS token on the input: BOS's embedding plus a linear map of the mean visual token.
    #: The first program token then sees the shape through its own input as well as through attention,
    #: which early in training collapses onto BOS itself (issue 14)
    prefix_bos: bool = False
    #: normalize every visual-token feature over the batch (batch norm without scale or shift; running
    #: statistics at evaluation): the prefix then varies across shapes by construction and cannot grow a
    #: large shape-independent part, which the ShapeAssembly decoder learned to ignore (docs/pretraining-probes.md)
    prefix_norm: bool = False

    def __post_init__(self) -> None:
        self.enc_channels = tuple(self.enc_channels)
        if self.enc_init not in ("default", "kaiming"):
            raise ValueError(f"enc_init {self.enc_init!r}: use 'default' or 'kaiming'")
        if self.d_model % self.n_heads:
            raise ValueError(f"d_model {self.d_model} must be divisible by n_heads {self.n_heads}")


@dataclass(kw_only=True)
class ModelConfig(Architecture):
    """Everything :class:`PLADNet` is built from: the architecture plus the domain's sizes. Stored in every checkpoint.

    A flat dict (``to_dict``), the same keys as before the architecture had its
    own class, so that every checkpoint loads with ``ModelConfig(**config)``; a
    knob added later defaults to the behaviour before it, so an older checkpoint
    (without its key) loads as the network it was.
    """

    vocab_size: int                    # number of domain tokens (output classes)
    max_len: int                       # program length cap (tokens, stop included)
    input_shape: tuple[int, ...]       # (64, 64) or (32, 32, 32)

    def __post_init__(self) -> None:
        super().__post_init__()
        self.input_shape = tuple(self.input_shape)
        if len(self.input_shape) not in (2, 3):
            raise ValueError(f"input shape {self.input_shape}: only 2D and 3D shapes are supported")

    @classmethod
    def for_domain(cls, arch: Architecture, domain) -> ModelConfig:
        """The network for ``domain`` (a :class:`plad.domains.base.Domain`) with architecture ``arch``."""
        return cls(**asdict(arch), vocab_size=len(domain.tokens), max_len=domain.tokens.max_len,
                   input_shape=domain.shape)

    @property
    def bos(self) -> int:
        """Index of the begin-of-sequence input token (not an output class)."""
        return self.vocab_size

    @property
    def pad(self) -> int:
        """Index of the padding input token (not an output class)."""
        return self.vocab_size + 1

    def to_dict(self) -> dict:
        return asdict(self)


class CNNEncoder(nn.Module):
    """Conv blocks (conv, [batch norm], ReLU, max-pool, channel dropout) -> visual tokens (N, P, d_model).

    2D: 3x3 convolutions, 64 -> 4 after four poolings: 16 tokens.
    3D (paper): kernel 4, padding 2, 32 -> 2 after four poolings: 8 tokens,
    followed by a 3-layer MLP. One pooling per entry of ``enc_channels``: three
    blocks leave 4^3 = 64 visual tokens, one per region of the grid.
    """

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        dims = len(cfg.input_shape)
        conv = nn.Conv2d if dims == 2 else nn.Conv3d
        pool = nn.MaxPool2d if dims == 2 else nn.MaxPool3d
        # Channel-wise dropout on feature maps: per-element dropout there cost
        # ~40% of a CPU training step (one random number per activation).
        drop = nn.Dropout2d if dims == 2 else nn.Dropout3d
        kernel = cfg.enc_kernel or (3 if dims == 2 else 4)
        pad = kernel // 2
        norm = nn.BatchNorm2d if dims == 2 else nn.BatchNorm3d
        layers: list[nn.Module] = []
        in_channels = c_in = 1 + (dims if cfg.coord_channels else 0)
        for c in cfg.enc_channels:
            layers += [conv(c_in, c, kernel, padding=pad, bias=not cfg.enc_norm)]
            layers += [norm(c)] if cfg.enc_norm else []
            # pool before ReLU: the same function (ReLU is monotone, so it commutes with max), on an
            # eighth of the values
            layers += [pool(2), nn.ReLU(), drop(cfg.dropout)]
            c_in = c
        self.net = nn.Sequential(*layers)
        if cfg.enc_init == "kaiming":
            for m in self.net:
                if isinstance(m, conv):
                    nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
                    if m.bias is not None:
                        nn.init.zeros_(m.bias)
        if cfg.coord_channels:
            axes = torch.meshgrid(*(torch.linspace(-1, 1, n) for n in cfg.input_shape), indexing="ij")
            self.register_buffer("coords", torch.stack(axes)[None], persistent=False)  # (1, dims, *spatial)
        else:
            self.coords = None
        # 3D: the first block (the full-resolution grid, most of the encoder's time with few channels) runs
        # channels-last, its convolution weight included: oneDNN's fast path on CPU (bench/encoder.py);
        # the later blocks, and 2D, stay contiguous, where channels-last was no faster. No value changes.
        self.memory_format = torch.contiguous_format if dims == 2 else torch.channels_last_3d
        self.first_block = len(layers) // len(cfg.enc_channels)     # layers of one block
        with torch.no_grad():
            # probe in eval mode: a training-mode probe would move the batch-norm running statistics
            out = self.net.eval()(torch.zeros(1, in_channels, *cfg.input_shape))
            self.net.train()
        self.num_tokens = int(math.prod(out.shape[2:]))
        self.mlp = nn.Sequential(
            nn.Linear(c_in, cfg.d_model), nn.ReLU(), nn.Dropout(cfg.dropout),
            nn.Linear(cfg.d_model, cfg.d_model), nn.ReLU(), nn.Dropout(cfg.dropout),
            nn.Linear(cfg.d_model, cfg.d_model))

    def _conv(self, start: int) -> tuple[nn.Module, torch.Tensor, torch.Tensor | None, bool]:
        """(convolution, weight, bias, folded) of the block starting at layer ``start``. In evaluation, a
        batch norm after the convolution is folded into its weight and bias (an affine map per channel):
        the same function without a pass over the full-resolution feature maps (ShapeAssembly's encoder at
        batch 200: batch norm was a fifth of its time)."""
        conv, norm = self.net[start], self.net[start + 1]
        if self.training or not isinstance(norm, nn.modules.batchnorm._BatchNorm):
            return conv, conv.weight, conv.bias, False
        scale = torch.rsqrt(norm.running_var + norm.eps)                   # (C,)
        if norm.weight is not None:
            scale = scale * norm.weight
        shift = -norm.running_mean * scale
        if norm.bias is not None:
            shift = shift + norm.bias
        if conv.bias is not None:
            shift = shift + conv.bias * scale
        weight = conv.weight * scale.view(-1, *[1] * (conv.weight.dim() - 1))
        return conv, weight, shift, True

    def forward(self, shapes: torch.Tensor) -> torch.Tensor:
        x = shapes.float().unsqueeze(1).contiguous(memory_format=self.memory_format)  # (N, 1, *spatial)
        conv = F.conv2d if x.dim() == 4 else F.conv3d
        block = self.first_block                                    # layers per block
        for start in range(0, len(self.net), block):
            layer, w, b, folded = self._conv(start)
            if start == 0:
                w = w.contiguous(memory_format=self.memory_format)  # (C, 1 [+ dims], *kernel)
            if start > 0 or self.coords is None:
                x = conv(x, w, b, padding=layer.padding)
            else:
                # the first convolution of [shape, coordinates] is a convolution of the shape plus one of the
                # coordinates, which is the same for every shape: computed once per batch, not per shape
                x = conv(x, w[:, :1].contiguous(memory_format=self.memory_format), None, padding=layer.padding)
                x = x + conv(self.coords, w[:, 1:], b, padding=layer.padding)  # (1, C, *spatial)
            x = self.net[start + 1 + folded:start + block](x)       # [norm,] pool, ReLU, dropout
            if start == 0:
                x = x.contiguous()
        x = x.flatten(2).transpose(1, 2)                            # (N, P, C)
        return self.mlp(x)

    def forward_plain(self, shapes: torch.Tensor) -> torch.Tensor:
        """The encoder as defined, without :meth:`forward`'s shortcuts (the reference of its test and bench)."""
        x = shapes.float().unsqueeze(1)                             # (N, 1, *spatial)
        if self.coords is not None:
            x = torch.cat([x, self.coords.expand(len(x), -1, *self.coords.shape[2:])], 1)
        x = self.net(x)                                             # (N, C, *spatial)
        x = x.flatten(2).transpose(1, 2)                            # (N, P, C)
        return self.mlp(x)


class _Layer(nn.Module):
    """Pre-norm Transformer layer whose attention can run on cached keys/values."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.h = cfg.n_heads
        self.ln1 = nn.LayerNorm(cfg.d_model)
        self.qkv = nn.Linear(cfg.d_model, 3 * cfg.d_model)
        self.out = nn.Linear(cfg.d_model, cfg.d_model)
        self.ln2 = nn.LayerNorm(cfg.d_model)
        self.ff = nn.Sequential(nn.Linear(cfg.d_model, cfg.dim_ff), nn.ReLU(), nn.Dropout(cfg.dropout),
                                nn.Linear(cfg.dim_ff, cfg.d_model))
        self.drop = nn.Dropout(cfg.dropout)
        self.p = cfg.dropout

    def _split(self, x: torch.Tensor) -> torch.Tensor:
        n, t, d = x.shape
        return x.view(n, t, self.h, d // self.h).transpose(1, 2)    # (N, H, T, dh)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None,
                cache: KVCache | None = None) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor] | KVCache]:
        """x (N, T, d) -> (x, (keys, values) (N, H, T, dh) each).

        With ``cache`` (earlier positions), x holds new positions only; their keys and values are appended to
        the cache in place and the cache is returned.
        """
        q, k, v = self.qkv(self.ln1(x)).chunk(3, dim=-1)
        q, k, v = self._split(q), self._split(k), self._split(v)
        kv = (k, v)
        if cache is not None:
            kv = cache
            k, v = cache.append(k, v)
        a = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=self.p if self.training else 0.0)
        a = a.transpose(1, 2).reshape(x.shape)
        x = x + self.drop(self.out(a))
        x = x + self.drop(self.ff(self.ln2(x)))
        return x, kv


class PLADNet(nn.Module):
    """p(z|x). Token ids 0..V-1 are the domain's; ``cfg.bos``/``cfg.pad`` are input-only."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = CNNEncoder(cfg)
        self.num_visual = self.encoder.num_tokens
        self.embed = nn.Embedding(cfg.vocab_size + 2, cfg.d_model)
        # positions: visual tokens first, then BOS + up to max_len program tokens
        self.pos = nn.Parameter(torch.zeros(self.num_visual + cfg.max_len + 1, cfg.d_model))
        nn.init.normal_(self.pos, std=0.02)
        self.layers = nn.ModuleList(_Layer(cfg) for _ in range(cfg.n_layers))
        self.ln = nn.LayerNorm(cfg.d_model)
        self.head = nn.Sequential(nn.Linear(cfg.d_model, cfg.d_model), nn.ReLU(), nn.Dropout(cfg.dropout),
                                  nn.Linear(cfg.d_model, cfg.vocab_size))
        # prefix_bos: mean visual token (N, d) -> an addition to BOS's embedding (N, d)
        self.bos_proj = nn.Linear(cfg.d_model, cfg.d_model) if cfg.prefix_bos else None
        # prefix_norm: over the batch, per feature of the flattened prefix (N, P * d)
        self.prefix_norm = (nn.BatchNorm1d(self.num_visual * cfg.d_model, affine=False) if cfg.prefix_norm
                            else None)

    def _bos(self, prefix: torch.Tensor) -> torch.Tensor:
        """The BOS input (N, 1, d) for visual prefix (N, P, d)."""
        bos = self.embed.weight[self.cfg.bos].expand(len(prefix), 1, -1)
        if self.bos_proj is not None:
            bos = bos + self.bos_proj(prefix.mean(1))[:, None, :]
        return bos

    # ---- teacher forcing --------------------------------------------------------
    def encode(self, shapes: torch.Tensor) -> torch.Tensor:
        """Shapes (N, *input_shape) -> visual prefix (N, P, d)."""
        prefix = self.encoder(shapes)
        if self.prefix_norm is None:
            return prefix
        flat, bn = prefix.flatten(1), self.prefix_norm
        if self.training and len(flat) < 2:
            # no batch statistics of one shape: its running statistics, as at evaluation
            return F.batch_norm(flat, bn.running_mean, bn.running_var, training=False, eps=bn.eps).view_as(prefix)
        return bn(flat).view_as(prefix)

    def _mask(self, t: int, device: torch.device) -> torch.Tensor:
        """(P+t, P+t) bool, True = may attend: the prefix sees itself, program tokens see the prefix and the past."""
        P = self.num_visual
        n = P + t
        allow = torch.ones(n, n, dtype=torch.bool, device=device).tril()
        allow[:, :P] = True
        allow[:P, P:] = False
        return allow

    def forward_prefix(self, prefix: torch.Tensor, tokens_in: torch.Tensor) -> torch.Tensor:
        """prefix (N, P, d), tokens_in (N, T) starting with BOS -> logits (N, T, V)."""
        P, T = prefix.shape[1], tokens_in.shape[1]
        emb = self.embed(tokens_in)                                 # (N, T, d)
        if self.bos_proj is not None:   # tokens_in[:, 0] is BOS
            emb = torch.cat([self._bos(prefix), emb[:, 1:]], 1)
        x = torch.cat([prefix, emb], dim=1) + self.pos[: P + T]
        mask = self._mask(T, x.device)
        for layer in self.layers:
            x, _ = layer(x, mask)
        return self.head(self.ln(x[:, P:]))

    def forward(self, shapes: torch.Tensor, tokens_in: torch.Tensor) -> torch.Tensor:
        return self.forward_prefix(self.encode(shapes), tokens_in)

    def teacher_forced(self, prefix: torch.Tensor, programs: torch.Tensor,
                       lengths: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(logits (N, L, V) float32, target (N, L), valid (N, L)) of programs (N, L) right-padded (any value
        past ``lengths`` (N,)) after the visual prefix (N, P, d), each token predicted from the true ones before it."""
        N, L = programs.shape
        valid = torch.arange(L, device=programs.device)[None, :] < lengths[:, None]
        target = torch.where(valid, programs, torch.zeros_like(programs))
        tokens_in = torch.cat([torch.full((N, 1), self.cfg.bos, device=programs.device, dtype=torch.long),
                               torch.where(valid, programs, torch.full_like(programs, self.cfg.pad))[:, :-1]], 1)
        # float32 logits: under bf16 autocast the cross-entropy still sums in float32 (a no-op in float32)
        return self.forward_prefix(prefix, tokens_in).float(), target, valid

    def token_nll(self, prefix: torch.Tensor, programs: torch.Tensor,
                  lengths: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Teacher-forced (nll, correct, valid), (N, L) each, of programs (N, L) right-padded (any value past
        ``lengths`` (N,)) after the visual prefix (N, P, d)."""
        logits, target, valid = self.teacher_forced(prefix, programs, lengths)
        N, L = programs.shape
        nll = F.cross_entropy(logits.reshape(N * L, -1), target.reshape(-1), reduction="none").view(N, L)
        return nll, logits.argmax(-1) == target, valid

    def loss(self, shapes: torch.Tensor, programs: torch.Tensor, lengths: torch.Tensor,
             prefix: torch.Tensor | None = None, soft: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean token cross-entropy and token accuracy of (shape, program) pairs.

        programs (N, L) long right-padded (any value past ``lengths``); lengths (N,). ``soft`` (V, V): the
        target distribution of each token (row), e.g. :func:`plad.domains.grammar.near_targets`; the loss is
        then the cross-entropy against ``soft[token]`` (None: against the token itself).
        """
        if prefix is None:
            prefix = self.encode(shapes)
        if soft is not None:
            logits, target, valid = self.teacher_forced(prefix, programs, lengths)
            nll = -(soft[target] * F.log_softmax(logits, -1)).sum(-1)            # (N, L)
            loss = (nll * valid).sum() / valid.sum()
            return loss, ((logits.argmax(-1) == target) & valid).sum().float() / valid.sum()
        nll, correct, valid = self.token_nll(prefix, programs, lengths)
        loss = (nll * valid).sum() / valid.sum()
        acc = (correct & valid).sum().float() / valid.sum()
        return loss, acc

    # ---- incremental decoding -------------------------------------------------------
    def start(self, prefix: torch.Tensor) -> tuple[torch.Tensor, list]:
        """Run the visual prefix and the BOS token: (logits (N, V) for the first token, caches)."""
        P = prefix.shape[1]
        x = torch.cat([prefix, self._bos(prefix)], dim=1) + self.pos[: P + 1]
        mask = self._mask(1, x.device)
        caches = []
        for layer in self.layers:
            x, (k, v) = layer(x, mask)
            # room for every position the length cap allows (visual tokens, BOS, max_len program tokens)
            caches.append(KVCache(k, v, self.pos.shape[0]))
        return self.head(self.ln(x[:, -1])), caches

    def step(self, tokens: torch.Tensor, caches: list, position: int) -> tuple[torch.Tensor, list]:
        """Feed one token per row ((N,) long) at program ``position`` (1-based after BOS) -> (logits, caches).

        The caches of :meth:`start` are extended in place (and returned).
        """
        x = self.embed(tokens)[:, None, :] + self.pos[self.num_visual + position]
        new = []
        for layer, kv in zip(self.layers, caches):
            x, kv = layer(x, None, kv)
            new.append(kv)
        return self.head(self.ln(x[:, -1])), new


class KVCache:
    """One layer's keys and values of the positions decoded so far, in preallocated buffers.

    Buffers (N, H, room, dh), the first ``n`` positions filled: a decoding step writes one position
    instead of concatenating the whole past again (torch.cat of the cache was ~10% of a greedy 3D CSG
    decode on CPU). The room grows by doubling up to ``capacity`` (the model's positions), so that short
    programs do not pay for buffers sized for the longest.
    """

    #: positions of room beyond those given, at first
    initial_room = 32

    def __init__(self, k: torch.Tensor, v: torch.Tensor, capacity: int):
        N, H, T, dh = k.shape
        self.capacity = capacity
        room = min(capacity, T + self.initial_room)
        self.k = k.new_empty(N, H, room, dh)
        self.v = v.new_empty(N, H, room, dh)
        self.k[:, :, :T] = k
        self.v[:, :, :T] = v
        self.n = T

    def append(self, k: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Add positions (N, H, t, dh) -> keys and values of all positions so far (views)."""
        t = k.shape[2]
        if self.n + t > self.capacity:
            raise ValueError(f"KV cache full: {self.n} + {t} positions > capacity {self.capacity}")
        if self.n + t > self.k.shape[2]:
            room = min(self.capacity, max(2 * self.k.shape[2], self.n + t))
            for name in ("k", "v"):
                old = getattr(self, name)
                grown = old.new_empty(*old.shape[:2], room, old.shape[3])
                grown[:, :, :self.n] = old[:, :, :self.n]
                setattr(self, name, grown)
        self.k[:, :, self.n:self.n + t] = k
        self.v[:, :, self.n:self.n + t] = v
        self.n += t
        return self.k[:, :, :self.n], self.v[:, :, :self.n]

    def select(self, index: torch.Tensor) -> KVCache:
        """The rows ``index`` (M,) long. With as many rows as before (a beam search step) they are gathered
        into this cache's own buffers, which is returned: its previous rows are gone. Otherwise a new cache.
        """
        if len(index) != len(self.k):
            k, v = self.k[:, :, :self.n].index_select(0, index), self.v[:, :, :self.n].index_select(0, index)
            return KVCache(k, v, self.capacity)
        # Only the rows whose source is another row are written: in a beam search most hypotheses extend
        # themselves, and copying every row twice (gather, then write back) made beam 5 slower than
        # concatenating. The sources are gathered before any row is overwritten.
        moved = torch.nonzero(index != torch.arange(len(index), device=index.device)).flatten()
        if len(moved):
            src = index[moved]
            k = self.k[:, :, :self.n].index_select(0, src)
            v = self.v[:, :, :self.n].index_select(0, src)
            self.k[:, :, :self.n].index_copy_(0, moved, k)
            self.v[:, :, :self.n].index_copy_(0, moved, v)
        return self


def reorder_caches(caches: list[KVCache], index: torch.Tensor) -> list[KVCache]:
    """Select rows of every layer's cache (:meth:`KVCache.select`, in place when the row count is kept):
    beam search keeps surviving hypotheses."""
    return [c.select(index) for c in caches]


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


__all__ = ["Architecture", "KVCache", "ModelConfig", "PLADNet", "count_parameters", "reorder_caches"]
