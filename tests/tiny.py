"""Inputs of the fine-tuning tests: the prepared 2D CAD shapes and a tiny, randomly initialized model."""
from __future__ import annotations

from pathlib import Path

#: the tiny architecture of these tests (an untrained model: fast, and its numbers mean nothing)
ARCHITECTURE = {"d_model": 16, "n_layers": 1, "n_heads": 2, "dim_ff": 32, "enc_channels": (4, 4, 8, 8)}


def csg2d_inputs(root: Path, datasets_dir: Path) -> Path:
    """``root/prepared/csg2d.npz`` from the real data and ``root/sp.pt``, the tiny model (seed 0); ``root``."""
    import torch

    from plad.checkpoint import save_checkpoint
    from plad.domains import get_domain
    from plad.model import ModelConfig, PLADNet
    from plad.stages.prepare import PrepareConfig, prepare

    prepare(PrepareConfig(data_dir=str(datasets_dir), domains=["csg2d"], out_dir=str(root / "prepared")))
    domain = get_domain("csg2d")
    torch.manual_seed(0)
    model = PLADNet(ModelConfig(vocab_size=len(domain.tokens), max_len=domain.tokens.max_len,
                                input_shape=domain.shape, **ARCHITECTURE))
    save_checkpoint(root / "sp.pt", model, "csg2d", domain.tokens.names)
    return root
