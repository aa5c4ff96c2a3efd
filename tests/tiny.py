"""The tiny, randomly initialized model of the tests, and the prepared 2D CAD project built around it.

One home for the factory the test files used to copy: :func:`tiny_model` / :func:`tiny_checkpoint`
(also the ``tiny_model`` / ``tiny_checkpoint`` fixtures of ``tests/conftest.py``).
"""
from __future__ import annotations

from pathlib import Path

#: the tiny architecture of the tests (an untrained model: fast, and its numbers mean nothing);
#: dropout as :class:`plad.model.network.Architecture`'s default
ARCHITECTURE = {"d_model": 32, "n_layers": 1, "n_heads": 2, "dim_ff": 64, "enc_channels": (4, 8, 8, 16)}


def tiny_config(domain: str = "csg2d", **overrides):
    """The :class:`plad.model.network.ModelConfig` of the tiny network for ``domain``; ``overrides`` replace its
    knobs."""
    from plad.domains import get_domain
    from plad.model.network import ModelConfig

    spec = get_domain(domain)
    base = dict(vocab_size=len(spec.tokens), max_len=spec.tokens.max_len, input_shape=spec.shape, **ARCHITECTURE)
    return ModelConfig(**{**base, **overrides})


def tiny_model(domain: str = "csg2d", seed: int = 0, **overrides):
    """A tiny :class:`plad.model.network.PLADNet` for ``domain``, initialized from torch seed ``seed`` (training
    mode)."""
    import torch

    from plad.model.network import PLADNet

    config = tiny_config(domain, **overrides)
    torch.manual_seed(seed)
    return PLADNet(config)


def tiny_checkpoint(path: Path, domain: str = "csg2d", seed: int = 0, **overrides) -> Path:
    """The tiny model (as :func:`tiny_model`) saved as a checkpoint at ``path``; ``path``."""
    from plad.domains import get_domain
    from plad.model.checkpoint import save_checkpoint

    return save_checkpoint(path, tiny_model(domain, seed, **overrides), domain, get_domain(domain).tokens.names)


def tiny_pretrain_params(path: Path) -> None:
    """A params file at ``path`` that pretrains the tiny architecture on 2D CSG in seconds (2 epochs of 4
    steps, batch 8, one thread, on the CPU)."""
    import json

    model = {**ARCHITECTURE, "dropout": 0.1, "enc_channels": list(ARCHITECTURE["enc_channels"])}
    block = {"device": "cpu", "threads": 1, "seed": 0, "val_metric_shapes": 8, "max_minutes": None, "model": model,
             "train": {"batch_size": 8, "lr": 0.001, "steps_per_epoch": 4, "max_epochs": 2, "patience": 5,
                       "min_delta": 0.001, "lr_patience": 0, "lr_factor": 0.5, "grad_clip": 1.0}}
    path.write_text(json.dumps({"pretrain": {"base": block, "csg2d": {}}}))


def csg2d_inputs(root: Path, datasets_dir: Path) -> Path:
    """A project at layout root ``root`` (:mod:`plad.layout`) ready to fine-tune: the real 2D shapes prepared
    and, as the pretrained model, the tiny one (seed 0); ``root``."""
    from plad.layout import Layout
    from plad.stages.prepare import PrepareConfig, prepare

    layout = Layout(root)
    prepare(PrepareConfig(data_dir=str(datasets_dir), domains=["csg2d"]), layout)
    tiny_checkpoint(layout.model("csg2d"), "csg2d")
    return root


def tiny_pretrain_config(epochs: int, **kw):
    """A :class:`plad.learn.pretrain.PretrainConfig` of the tiny architecture on 2D CSG: ``epochs`` epochs of 4
    steps of batch 8, one thread, on the CPU (``kw``: more keys)."""
    from plad.learn.curriculum import CurriculumConfig
    from plad.learn.pretrain import PretrainConfig
    from plad.learn.train import TrainConfig
    from plad.model.network import Architecture

    return PretrainConfig(domain="csg2d", device="cpu", threads=1, val_metric_shapes=4, gap_programs=4,
                          model=Architecture(**ARCHITECTURE), curriculum=CurriculumConfig(),
                          train=TrainConfig(batch_size=8, steps_per_epoch=4, max_epochs=epochs, patience=100), **kw)


def tiny_pretrained_root(root: Path) -> Path:
    """``root`` as a layout root with 200 synthetic 2D programs and a one-epoch tiny pretraining."""
    from plad.layout import Layout
    from plad.learn.pretrain import pretrain
    from plad.stages.synthesize import SynthesizeConfig, synthesize

    synthesize(SynthesizeConfig(domain="csg2d", train_programs=200, val_programs=20), Layout(root))
    pretrain(tiny_pretrain_config(1), Layout(root))
    return root
