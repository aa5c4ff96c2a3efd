"""Stage ``prepare_3d``: the real 3D target shapes S*, from the PartNet ShapeAssembly programs.

Executes and voxelizes (32^3) every program of ``partnet_programs.tar.gz``
from the data directory, with the split rule of the datasets README (train:
the official train ids; the official val ids alternate val / test), and
writes ``<out_dir>/partnet_voxels.npz`` (bit-packed voxels, ids, categories;
format in :mod:`plad.domains.shapeassembly.dataset`) with a report
``partnet_voxels.json``. A program that fails to execute is listed there and
in ``partnet_failures.log`` with its id and reason, never silently dropped.
The same shapes are then written as ``<out_dir>/<domain>.npz`` for every 3D
domain configured (the layout of the ``prepare`` stage), so training and
evaluation read all domains alike.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plad.fsutil import atomic_write_text
from plad.stages import stage_main


@dataclass
class Prepare3DConfig:
    #: directory holding the datasets; null means $PLAD_DATA_DIR, else ./data/datasets
    data_dir: str | None = None
    #: 3D domains whose targets are these shapes
    domains: list[str] = field(default_factory=lambda: ["shapeassembly"])
    out_dir: str = "data/prepared"
    #: keep only the first N programs of each split (smoke runs); null: all
    limit: int | None = None


def find_source(data_dir: str | None) -> Path:
    from plad.data import DataError, resolve_data_dir
    from plad.domains.shapeassembly.dataset import FOLDER, SOURCE_NAME

    root = resolve_data_dir(data_dir)
    for path in (root / FOLDER / SOURCE_NAME, root / SOURCE_NAME):
        if path.is_file():
            return path
    raise DataError(root / FOLDER / SOURCE_NAME, "no such file: the PartNet ShapeAssembly programs are needed "
                                                 "for the 3D target shapes (see the datasets README)")


def prepare_3d(cfg: Prepare3DConfig) -> dict:
    import tarfile

    from plad.data import DataError
    from plad.domains import get_domain
    from plad.domains.shapeassembly.dataset import PREPARED_NAME, SPLITS, build_partnet_dataset, unpack
    from plad.stages.prepare import write_prepared

    source = find_source(cfg.data_dir)
    out = Path(cfg.out_dir)
    start = time.monotonic()
    try:
        report = build_partnet_dataset(source, out / PREPARED_NAME, limit=cfg.limit)
    except (tarfile.TarError, EOFError, OSError) as err:
        raise DataError(source, f"not a readable .tar.gz ({err.__class__.__name__}: {err})") from None
    report["seconds"] = round(time.monotonic() - start, 1)
    report["source"] = str(source)
    atomic_write_text(out / "partnet_voxels.json", json.dumps(report, indent=2) + "\n")
    atomic_write_text(out / "partnet_failures.log",
                      "".join(f"{f['program']}\t{f['reason']}\n" for f in report["failures"]))
    with np.load(out / PREPARED_NAME) as z:
        split = z["split"]
        splits = {s: unpack(z["voxels"][split == s]) for s in SPLITS}
    for name in cfg.domains:
        domain = get_domain(name)
        if tuple(domain.shape) != splits["train"].shape[1:]:
            raise ValueError(f"domain {name} works on {domain.shape}, the prepared 3D shapes are "
                             f"{splits['train'].shape[1:]}")
        write_prepared(name, tuple(domain.shape), splits, out, {"source": "partnet_voxels.npz"})
    return {k: report[k] for k in ("shapes", "listed", "seconds")} | {"failures": len(report["failures"])}


def main(argv: list[str] | None = None) -> int:
    return stage_main("prepare_3d", Prepare3DConfig, prepare_3d, argv, __doc__.splitlines()[0])

if __name__ == "__main__":
    sys.exit(main())
