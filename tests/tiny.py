"""Inputs of the fine-tuning tests: the prepared 2D CAD shapes and a tiny, randomly initialized model."""
from __future__ import annotations

from pathlib import Path

#: the tiny architecture of these tests (an untrained model: fast, and its numbers mean nothing)
ARCHITECTURE = {"d_model": 16, "n_layers": 1, "n_heads": 2, "dim_ff": 32, "enc_channels": (4, 4, 8, 8)}


def csg2d_inputs(root: Path, datasets_dir: Path) -> Path:
    """A project at layout root ``root`` (:mod:`plad.layout`) ready to fine-tune: the real 2D shapes prepared
    and, as the pretrained model, the tiny one (seed 0); ``root``."""
    import torch

    from plad.checkpoint import save_checkpoint
    from plad.domains import get_domain
    from plad.layout import Layout
    from plad.model import ModelConfig, PLADNet
    from plad.stages.prepare import PrepareConfig, prepare

    layout = Layout(root)
    prepare(PrepareConfig(data_dir=str(datasets_dir), domains=["csg2d"]), layout)
    domain = get_domain("csg2d")
    torch.manual_seed(0)
    model = PLADNet(ModelConfig(vocab_size=len(domain.tokens), max_len=domain.tokens.max_len,
                                input_shape=domain.shape, **ARCHITECTURE))
    save_checkpoint(layout.model("csg2d"), model, "csg2d", domain.tokens.names)
    return root
