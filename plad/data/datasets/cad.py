"""CSGNet's 2D "CAD" dataset (Sharma et al. 2018): 64 x 64 binary drawings, the PLAD paper's 10K/3K/3K split.

One HDF5 file (``cad.h5``, or gzip of it ``cad.h5.gz``) with the three
splits, checked against its published sha256 before use (:mod:`plad.data.files`).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from plad.data.files import DatasetSpec, SplitSpec, TargetSource, download_dataset, load_dataset

#: where the file is looked for, its published hash and home, and its splits
CAD = DatasetSpec(
    name="CAD",
    candidates=("csgnet_cad/cad.h5", "csgnet_cad/cad.h5.gz", "cad.h5", "cad.h5.gz"),
    sha256="c1bc69bdc0f7a106ec1ac841932dcdac258497208758e92e1a94aaf39e61895d",
    # dl=1 makes Dropbox serve the file itself instead of a preview page.
    url="https://www.dropbox.com/s/d6vm7diqfp65kyi/cad.h5?dl=1",
    download_to="csgnet_cad/cad.h5",
    splits=(
        SplitSpec("train", "train_images", (10000, 64, 64)),
        SplitSpec("val", "val_images", (3000, 64, 64)),
        SplitSpec("test", "test_images", (3000, 64, 64)),
    ),
)


def load_cad(data_dir: str | os.PathLike | None = None, split: str = "test", *,
             download: bool = False) -> np.ndarray:
    """CSGNet CAD shapes of ``split`` (``train``/``val``/``test``): bool (N, 64, 64), True = inside.

    Reads ``cad.h5`` or ``cad.h5.gz`` (see :data:`CAD` for the names tried)
    from the data directory (:func:`plad.data.files.resolve_data_dir`), verifies its
    sha256 and caches all splits for the process (:func:`plad.data.files.load_dataset`).
    With ``download=True`` a missing file is downloaded first; a present but
    damaged file is reported, not replaced.
    """
    return load_dataset(CAD, data_dir, split, download=download)


def download_cad(data_dir: str | os.PathLike | None = None, url: str | None = None,
                 timeout: float = 60.0) -> Path:
    """Download CSGNet's ``cad.h5`` to ``<data_dir>/csgnet_cad/cad.h5`` (verified); returns the path.

    ``url`` defaults to the public Dropbox link (:data:`CAD`.url); ``timeout``
    is per socket operation, in seconds.
    """
    return download_dataset(CAD, data_dir, url=url, timeout=timeout)


def check(data_dir: str | os.PathLike | None = None) -> list[str]:
    """Lines for ``plad data check``: the file verified (sha256) and the size of every split."""
    from plad.data.files import find_dataset_file

    lines = []
    for split in CAD.splits:
        shapes = load_cad(data_dir, split.name)
        lines.append(f"{CAD.name} {split.name}: {len(shapes)} shapes {shapes.shape[1:]}")
    return [f"{CAD.name} {find_dataset_file(CAD, data_dir)}: sha256 {CAD.sha256} verified"] + lines


def checksums(data_dir: str | os.PathLike | None = None) -> dict[str, str]:
    """{the CAD file: the sha256 of its (uncompressed) contents}, verified by reading it."""
    from plad.data.files import find_dataset_file

    load_cad(data_dir, "test")   # verifies the sha256 (raises DataError otherwise)
    return {str(find_dataset_file(CAD, data_dir)): CAD.sha256}


class CADTargets(TargetSource):
    """The CAD shapes as they are published: the prepared splits are the verified file's."""

    name = "cad"

    def load(self, split: str, data_dir: str | os.PathLike | None = None) -> np.ndarray:
        return load_cad(data_dir, split)


#: the target source of domains whose real shapes are the CAD drawings
TARGETS = CADTargets()

__all__ = ["CAD", "TARGETS", "CADTargets", "check", "checksums", "download_cad", "load_cad"]
