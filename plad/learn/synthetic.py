"""Synthetic (shape, program) pairs for training: the programs of the ``synthesize`` stage, read from their
file, and batches whose shapes are executed on the fly.

Used by pretraining (:mod:`plad.learn.pretrain`) and its diagnostics (:mod:`plad.learn.diagnostics`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from plad.config import ConfigError
from plad.data.batching import trim
from plad.device import to_device
from plad.domains.base import split_padding


def load_programs(path: Path) -> dict[str, torch.Tensor]:
    """``train``/``val`` token rows (N, L) int64, -1-padded, and their complexities where the file has them."""
    import zipfile

    from plad.data.files import DataError

    if not path.exists():
        raise ConfigError(f"{path}: synthetic programs not found; run the synthesize stage first")
    try:
        with np.load(path) as z:
            data = {k: torch.from_numpy(z[k].astype(np.int64))
                    for k in ("train", "val", "train_complexity", "val_complexity") if k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
        raise DataError(path, f"not a readable synthetic .npz ({type(err).__name__}: {err}); run the synthesize "
                              "stage again") from None
    if "train" not in data or "val" not in data:
        raise DataError(path, "not a synthetic programs file (no train/val arrays); run the synthesize stage again")
    return data



def make_batch(domain, programs: torch.Tensor, device: torch.device) -> tuple[torch.Tensor, ...]:
    """(shapes, programs, lengths) from -1-padded token rows: shapes are executed here, on ``device``; the
    programs are cut to the longest one (:func:`plad.data.batching.trim`) where the rows are (the synthetic
    file's: on the CPU, so that a GPU is not waited for to read the longest length), then moved."""
    programs, lengths = split_padding(programs)
    programs = trim(programs, lengths)
    programs, lengths = to_device(programs, device), to_device(lengths, device)
    return domain.execute(programs), programs, lengths

