"""Wake-sleep: a generative model of programs trained on P_BEST (paper, Sec. 3.3 and supplement).

The generator is a VAE built from the recognition architecture: the CNN
encoder's visual prefix (P x d) is flattened, mapped by Linear -> ReLU to the
mean and log-variance of a ``latent``-dimensional code, and a Linear layer maps
the code back to a P x d prefix for the Transformer decoder. It is trained on
pairs (E(z), z) for the programs z in P_BEST, with loss = token cross-entropy
+ ``kl_weight`` * KL(q(c | E(z)) || N(0, I)); both terms are per program
(cross-entropy summed over its tokens), so weight 1 is the ELBO. Training
stops early when the training loss has not improved for ``patience`` epochs
(the loop is :class:`plad.learn.loop.Loop`, like every other trainer's).
The generator persists across rounds (it is fine-tuned every round, starting
from the recognition network the first time).

Sampling draws codes from N(0, I), decodes programs ancestrally under the
grammar mask, executes them, and keeps ``n`` unique programs whose execution
is not empty: the WS source pairs each with its execution.
"""
from __future__ import annotations

import copy
import logging
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from plad.device import FP32, Precision, to_device
from plad.domains.base import Domain, split_padding
from plad.fsutil import atomic_write
from plad.learn import distributed as dist
from plad.learn.loop import Limits, Loop, Objective, Unit
from plad.learn.pbest import PBest
from plad.model.checkpoint import CheckpointError
from plad.model.network import ModelConfig, PLADNet
from plad.model.sampling import ancestral_sample

log = logging.getLogger(__name__)


@dataclass
class WSConfig:
    latent: int = 128
    #: width of the Linear -> ReLU layer before the mean and log-variance
    hidden: int = 256
    kl_weight: float = 1.0
    lr: float = 1e-3
    batch_size: int = 100
    max_epochs: int = 100
    #: epochs without a training-loss improvement of more than ``min_delta`` before stopping
    patience: int = 10
    min_delta: float = 1e-4
    #: batches per epoch (None: one pass over P_BEST)
    steps_per_epoch: int | None = None
    #: programs decoded per sampling batch
    sample_batch: int = 500
    #: give up after this many sampling batches per requested program batch
    max_sample_factor: int = 20


class Generator(nn.Module):
    """VAE q(c | x) -> p(z | c) around a copy of the recognition network."""

    def __init__(self, net: PLADNet, latent: int, hidden: int):
        super().__init__()
        self.net = net
        p, d = net.num_visual, net.cfg.d_model
        self.prefix_shape = (p, d)
        self.to_hidden = nn.Linear(p * d, hidden)
        self.to_stats = nn.Linear(hidden, 2 * latent)      # mean and log-variance
        self.from_latent = nn.Linear(latent, p * d)
        self.latent = latent

    def decode_prefix(self, c: torch.Tensor) -> torch.Tensor:
        """Codes (N, latent) -> visual prefix (N, P, d)."""
        return self.from_latent(c).view(-1, *self.prefix_shape)

    def loss(self, shapes: torch.Tensor, programs: torch.Tensor, lengths: torch.Tensor,
             kl_weight: float) -> tuple[torch.Tensor, dict[str, float]]:
        h = F.relu(self.to_hidden(self.net.encode(shapes).flatten(1)))
        # float32 statistics: under bf16 autocast the KL term and the sampled code keep float32 (no-op in float32)
        mean, logvar = self.to_stats(h).float().chunk(2, dim=-1)
        c = mean + torch.randn_like(mean) * torch.exp(0.5 * logvar)
        ce, acc = self.net.loss(shapes, programs, lengths, prefix=self.decode_prefix(c))
        ce = ce * lengths.float().mean()                            # mean per token -> per program
        kl = (-0.5 * (1 + logvar - mean.pow(2) - logvar.exp()).sum(-1)).mean()
        return ce + kl_weight * kl, {"ce": float(ce.detach()), "kl": float(kl.detach()), "acc": float(acc)}

    @torch.no_grad()
    def sample(self, table, n: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        device = self.from_latent.weight.device
        c = torch.randn(n, self.latent, generator=generator, device=device)
        return ancestral_sample(self.net, table, self.decode_prefix(c), generator)


def new_generator(model: PLADNet, cfg: WSConfig) -> Generator:
    """A generator whose decoder and encoder start from (a copy of) the recognition network."""
    gen = Generator(copy.deepcopy(model), cfg.latent, cfg.hidden)
    return gen.to(next(model.parameters()).device)


def save_generator(path: str | Path, gen: Generator, cfg: WSConfig, round_: int) -> None:
    import io
    buf = io.BytesIO()
    torch.save({"model_config": gen.net.cfg.to_dict(), "ws": asdict(cfg), "round": round_,
                "state_dict": {k: v.detach().cpu() for k, v in gen.state_dict().items()}}, buf)
    atomic_write(path, lambda fh: fh.write(buf.getvalue()))


def load_generator(path: str | Path, device: torch.device) -> tuple[Generator, int]:
    try:   # tensors and plain data only: a generator file cannot run code when loaded
        payload = torch.load(Path(path), map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises many types for corrupt or unsafe files
        raise CheckpointError(f"{path}: not a readable generator checkpoint of tensors and plain data "
                              f"({err.__class__.__name__})") from None
    cfg = WSConfig(**payload["ws"])
    gen = Generator(PLADNet(ModelConfig(**payload["model_config"])), cfg.latent, cfg.hidden)
    gen.load_state_dict(payload["state_dict"])
    return gen.to(device), int(payload["round"])


#: the generator is selected on its training loss (there is no validation set of programs)
WS_LOSS = Objective("ws_loss", higher_is_better=False)


def train_generator(gen: Generator, pbest: PBest, cfg: WSConfig, seed: int,
                    max_seconds: float = math.inf, precision: Precision = FP32) -> dict[str, float]:
    """Fit the VAE on (execution, program) of every P_BEST entry; early stop on training loss.

    Not resumable by itself: a round saves the generator once it is trained,
    and a round killed before that trains it again from the same start.
    Under torchrun each rank trains on its own batches of P_BEST (every rank
    holds the same P_BEST) with the gradients averaged (DDP). ``precision``: the arithmetic of the forward
    passes (:mod:`plad.device`).
    """
    device = next(gen.parameters()).device
    idx_all = np.nonzero(pbest.has)[0]
    if len(idx_all) == 0:
        raise ValueError("P_BEST is empty: nothing to train the wake-sleep generator on")
    rng = np.random.default_rng(dist.rank_seed(seed))
    opt = torch.optim.Adam(gen.parameters(), lr=cfg.lr)
    loss_of = dist.data_parallel(gen, lambda g, *a: g.loss(*a))
    steps = cfg.steps_per_epoch or max(1, math.ceil(len(idx_all) / cfg.batch_size))
    best: dict[str, dict[str, torch.Tensor]] = {}
    gen.train()

    def epoch(unit: int, remaining) -> Unit:
        order = rng.permutation(np.resize(idx_all, steps * cfg.batch_size))
        total = 0.0
        for s in range(steps):
            idx = np.sort(order[s * cfg.batch_size:(s + 1) * cfg.batch_size])
            programs, lengths = split_padding(torch.from_numpy(pbest.programs[idx].astype(np.int64)))
            programs, lengths = to_device(programs, device), to_device(lengths, device)
            shapes = to_device(pbest.executions[idx], device)
            with precision.autocast():
                loss, _ = loss_of(shapes, programs, lengths, cfg.kl_weight)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(gen.parameters(), 1.0)
            opt.step()
            total += float(loss.detach())
        return Unit(dist.mean(total / steps))

    def keep_best(unit: int, value: float) -> None:   # in memory: see the docstring
        best["state"] = {k: v.detach().clone() for k, v in gen.state_dict().items()}

    def restore_best() -> None:
        if best:
            gen.load_state_dict(best["state"])

    loop = Loop("epoch", WS_LOSS, Limits(cfg.max_epochs, cfg.patience, cfg.min_delta, max_seconds))
    result = loop.run(epoch, keep_best=keep_best, restore_best=restore_best)
    gen.eval()
    # 1.0: the round's remaining budget stopped the generator before its epochs were done (a number, as every
    # column of the round's history, so that MLflow logs it)
    return {"ws_loss": result.best, "ws_epochs": result.units, "ws_stopped_by_time": float(result.stopped_by_time)}


def sample_dataset(gen: Generator, domain: Domain, n: int, cfg: WSConfig,
                   seed: int) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """``n`` unique programs with non-empty executions -> (programs (n, L) int16 -1 padded, executions, stats).

    Returns fewer than ``n`` only if ``max_sample_factor`` batches per ``n``
    programs did not find enough distinct ones (logged).
    """
    gen.eval()
    device = next(gen.parameters()).device
    g = torch.Generator(device=device).manual_seed(seed)
    L = domain.tokens.max_len
    seen: set[bytes] = set()
    programs, executions = [], []
    drawn, empty = 0, 0
    tries = cfg.max_sample_factor * max(1, math.ceil(n / cfg.sample_batch))
    for _ in range(tries):
        if len(seen) >= n:
            break
        tokens, lengths = gen.sample(domain.tokens, cfg.sample_batch, g)
        shapes = domain.execute(tokens)
        drawn += len(tokens)
        nonempty = shapes.flatten(1).any(1)
        empty += int((~nonempty).sum())
        rows = torch.where(torch.arange(L, device=device)[None] < lengths[:, None], tokens, -1)
        rows_np, shapes_np = rows.cpu().numpy().astype(np.int16), shapes.cpu().numpy()
        for i in np.nonzero(nonempty.cpu().numpy())[0]:
            key = rows_np[i].tobytes()
            if key in seen:
                continue
            seen.add(key)
            programs.append(rows_np[i])
            executions.append(shapes_np[i])
            if len(seen) >= n:
                break
    if len(programs) < n:
        log.warning("wake-sleep sampling found %d of %d unique non-empty programs", len(programs), n)
    stats = {"ws_unique": len(programs) / max(n, 1), "ws_empty_share": empty / max(drawn, 1)}
    shape = tuple(domain.shape)
    return (np.stack(programs) if programs else np.zeros((0, L), np.int16),
            np.stack(executions) if executions else np.zeros((0, *shape), bool), stats)


def ws_source(programs: np.ndarray, executions: np.ndarray, device: torch.device):
    """Wake-sleep: executions of sampled programs paired with those programs (exact labels)."""
    if len(programs) == 0:
        raise ValueError("the wake-sleep generator produced no usable programs")

    def draw(rng: np.random.Generator, n: int):
        idx = rng.choice(len(programs), size=n)
        p, lengths = split_padding(torch.from_numpy(programs[idx].astype(np.int64)))
        return to_device(executions[idx], device), to_device(p, device), to_device(lengths, device)
    return draw
