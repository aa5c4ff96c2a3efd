"""The PartNet target shapes: PartNet-derived ShapeAssembly programs, executed and voxelized at 32^3.

Source: ``partnet_programs.tar.gz`` (``programs/{chair,table,storage}/<id>.txt``
and ``splits/<category>/{train,val}.txt``; see docs/conventions.md, "The data directory and the real datasets").
Split rule: train = the official train ids of all three
categories; the official val ids, sorted by (category, numeric id),
alternate val (even positions) / test (odd positions).

Prepared file format (``partnet_voxels.npz``, written by
:func:`build_partnet_dataset`, read by :func:`load_split`), one record per
successfully executed program, ordered by split (train, val, test), then
category, then numeric id:

* ``voxels``: uint8 (N, 4096), ``np.packbits`` of each (32, 32, 32) bool grid
  indexed [x, y, z] and flattened in C order (default big bit order);
  unpack with ``np.unpackbits(v, axis=1).reshape(-1, 32, 32, 32).astype(bool)``;
* ``ids``: str (N,) program ids; ``categories``: str (N,) chair/table/storage;
  ``split``: str (N,) train/val/test;
* ``norm_center`` float64 (N, 3), ``norm_scale`` float64 (N,): the tight-bounds
  normalization applied before voxelizing (docs/shapeassembly.md);
* ``n_cuboids`` int64 (N,);
* ``format_version`` int (1) and ``voxel_convention`` str.

Voxels follow docs/shapeassembly.md, "Voxelizing a real shape" (see :mod:`plad.data.datasets.partnet.voxels`).

:data:`TARGETS` is the target source of the 3D domains: the ``prepare``
stage builds the file once (:meth:`PartNetTargets.prepare`), with a report
``partnet_voxels.json`` and ``partnet_failures.log`` beside it.
"""
from __future__ import annotations

import json
import logging
import os
import tarfile
import time
from pathlib import Path

import numpy as np

from plad.data.datasets.partnet.execute import run_text
from plad.data.datasets.partnet.source import CATEGORIES, FOLDER, SOURCE_NAME, SOURCE_SHA256, find_source, read_source
from plad.data.datasets.partnet.voxels import RES, normalization, voxelize
from plad.data.files import SPLITS, DataError, PreparedTargets, TargetSource, resolve_data_dir, verify_file
from plad.domains.grammar import ProgramError
from plad.fsutil import atomic_write, atomic_write_text, savez

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
PREPARED_NAME = "partnet_voxels.npz"
REPORT_NAME = "partnet_voxels.json"
FAILURES_NAME = "partnet_failures.log"
CONVENTION = ("tight AABB of all cuboid corners; p_norm = (p - center) / scale; voxel (i,j,k) center "
              "((i+.5)/32-.5, (j+.5)/32-.5, (k+.5)/32-.5) indexed [x,y,z]; occupied iff "
              "|(c-p).u_a| <= max(|d_a|/2, 0.55/32) + 1e-6 for a = x, y, z for some cuboid")


def execute_records(programs: dict[tuple[str, str], str], assignment: list[tuple[str, str, str]]):
    """Execute and voxelize; returns (arrays dict, failures [(category/id, reason)])."""
    rows, failures = [], []
    for split, cat, pid in assignment:
        text = programs.get((cat, pid))
        if text is None:
            failures.append((f"{cat}/{pid}", "listed in the splits but no program file"))
            continue
        try:
            cub = run_text(text)
            if len(cub) == 0:
                raise ProgramError("the program has no leaf cuboids")
            if not np.isfinite(cub).all():
                raise ProgramError("execution produced non-finite cuboids")
        except ProgramError as err:
            failures.append((f"{cat}/{pid}", str(err)))
            continue
        center, scale = normalization(cub)
        rows.append((split, cat, pid, voxelize(cub), center, scale, len(cub)))
    arrays = {
        "voxels": np.packbits(np.stack([r[3] for r in rows]).reshape(len(rows), -1), axis=1) if rows
        else np.zeros((0, RES ** 3 // 8), np.uint8),
        "ids": np.array([r[2] for r in rows], dtype=str),
        "categories": np.array([r[1] for r in rows], dtype=str),
        "split": np.array([r[0] for r in rows], dtype=str),
        "norm_center": np.array([r[4] for r in rows], dtype=np.float64).reshape(-1, 3),
        "norm_scale": np.array([r[5] for r in rows], dtype=np.float64),
        "n_cuboids": np.array([r[6] for r in rows], dtype=np.int64),
        "format_version": np.array(FORMAT_VERSION),
        "voxel_convention": np.array(CONVENTION),
    }
    return arrays, failures


def build_partnet_dataset(tar_path: str | os.PathLike, out_path: str | os.PathLike,
                          limit: int | None = None) -> dict:
    """Execute and voxelize every program of the tarball's splits; write the prepared .npz.

    ``limit`` keeps only the first ``limit`` programs of each split (for tests).
    Returns a report: counts per split and category, and ``failures``, a list of
    {"program": "category/id", "reason": ...} (also logged as warnings).
    """
    programs, assignment = read_source(tar_path)
    if limit is not None:
        seen: dict[str, int] = {}
        kept = []
        for r in assignment:
            if seen.get(r[0], 0) < limit:
                seen[r[0]] = seen.get(r[0], 0) + 1
                kept.append(r)
        assignment = kept
    arrays, failures = execute_records(programs, assignment)
    out_path = Path(out_path)
    atomic_write(out_path, lambda fh: savez(fh, **arrays))
    for name, reason in failures:
        log.warning("PartNet dataset: %s failed: %s", name, reason)
    counts = {s: {c: int(((arrays["split"] == s) & (arrays["categories"] == c)).sum()) for c in CATEGORIES}
              for s in SPLITS}
    listed = {s: sum(1 for r in assignment if r[0] == s) for s in SPLITS}
    return {"out_path": str(out_path), "shapes": int(len(arrays["ids"])), "listed": listed, "counts": counts,
            "failures": [{"program": n, "reason": r} for n, r in failures]}


def unpack(voxels: np.ndarray) -> np.ndarray:
    """Bit-packed (N, 4096) uint8 -> bool (N, 32, 32, 32)."""
    return np.unpackbits(voxels, axis=1).reshape(-1, RES, RES, RES).astype(bool)


_SPLIT_CACHE: dict[tuple[str, str], np.ndarray] = {}


def load_split(split: str, data_dir: str | os.PathLike | None = None) -> np.ndarray:
    """Target shapes of a split: bool (N, 32, 32, 32).

    Reads the prepared ``partnet_voxels.npz`` (in the data directory or its
    ``shapeassembly_partnet/`` folder); where only the source tarball is there,
    executes that split's programs directly (a few seconds for val/test,
    about 20 s for train) and caches the result for the process.
    """
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; expected one of {', '.join(SPLITS)}")
    root = resolve_data_dir(data_dir)
    for rel in (PREPARED_NAME, f"{FOLDER}/{PREPARED_NAME}"):
        path = root / rel
        if path.is_file():
            try:
                with np.load(path, allow_pickle=False) as z:
                    if int(z["format_version"]) != FORMAT_VERSION:
                        raise DataError(path, f"format_version {int(z['format_version'])}, expected {FORMAT_VERSION}")
                    rows = z["split"] == split
                    return unpack(z["voxels"][rows])
            except (OSError, KeyError, ValueError) as err:
                raise DataError(path, f"not a readable prepared PartNet dataset ({err})") from None
    for rel in (SOURCE_NAME, f"{FOLDER}/{SOURCE_NAME}"):
        path = root / rel
        if path.is_file():
            key = (str(path.resolve()), split)
            if key not in _SPLIT_CACHE:
                log.info("no prepared %s; executing the %s programs of %s", PREPARED_NAME, split, path)
                verify_file(path, SOURCE_SHA256, "PartNet")
                try:
                    programs, assignment = read_source(path)
                except (tarfile.TarError, EOFError, OSError) as err:
                    raise DataError(path, f"not a readable .tar.gz ({err.__class__.__name__}: {err})") from None
                arrays, failures = execute_records(programs, [r for r in assignment if r[0] == split])
                for name, reason in failures:
                    log.warning("PartNet dataset: %s failed: %s", name, reason)
                _SPLIT_CACHE[key] = unpack(arrays["voxels"])
            return _SPLIT_CACHE[key]
    raise DataError(root.absolute(), f"PartNet target shapes not found (looked for {PREPARED_NAME} and "
                                     f"{SOURCE_NAME}, also under {FOLDER}/); the prepared file is built by the "
                                     f"prepare stage (build_partnet_dataset), or point the data directory at "
                                     f"the folder holding {SOURCE_NAME}")



class PartNetTargets(TargetSource):
    """The PartNet shapes: read from the prepared file, or built from the programs by the ``prepare`` stage."""

    name = "partnet"
    files = (PREPARED_NAME, REPORT_NAME, FAILURES_NAME)

    def load(self, split: str, data_dir: str | os.PathLike | None = None) -> np.ndarray:
        return load_split(split, data_dir)

    def prepare(self, data_dir: str | os.PathLike | None, out_dir: str | os.PathLike,
                limit: int | None = None) -> PreparedTargets:
        """Execute and voxelize every program (``limit``: the first N of each split).

        Writes ``<out_dir>/partnet_voxels.npz``, its report ``partnet_voxels.json``
        and ``partnet_failures.log``: a program that fails to execute is listed
        there with its id and reason, never silently dropped.
        """
        source = find_source(data_dir)
        out = Path(out_dir)
        start = time.monotonic()
        try:
            report = build_partnet_dataset(source, out / PREPARED_NAME, limit=limit)
        except (tarfile.TarError, EOFError, OSError) as err:
            raise DataError(source, f"not a readable .tar.gz ({err.__class__.__name__}: {err})") from None
        report["seconds"] = round(time.monotonic() - start, 1)
        # provenance without machine paths: the file's name and its verified sha256
        report["source"] = {"file": source.name, "sha256": SOURCE_SHA256}
        atomic_write_text(out / REPORT_NAME, json.dumps(report, indent=2) + "\n")
        atomic_write_text(out / FAILURES_NAME, "".join(f"{f['program']}\t{f['reason']}\n" for f in report["failures"]))
        with np.load(out / PREPARED_NAME) as z:
            split = z["split"]
            splits = {s: unpack(z["voxels"][split == s]) for s in SPLITS}
        return PreparedTargets(splits, provenance={"source": PREPARED_NAME},
                               report={k: report[k] for k in ("shapes", "listed", "seconds")}
                               | {"failures": len(report["failures"])})


#: the target source of the domains whose real shapes are the PartNet shapes
TARGETS = PartNetTargets()
