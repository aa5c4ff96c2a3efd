"""The PartNet programs tarball itself: where it is, what it lists, and a check that needs neither torch nor execution.

``partnet_programs.tar.gz`` holds ``programs/{chair,table,storage}/<id>.txt`` and
``splits/<category>/{train,val}.txt`` (docs/conventions.md, "The data directory and
the real datasets"). :mod:`plad.data.datasets.partnet.dataset` executes and voxelizes
the programs; this module only reads the archive, so that ``plad data check``
stays fast and imports no torch.
"""
from __future__ import annotations

import os
import tarfile
from pathlib import Path

from plad.data.files import SPLITS, DataError, resolve_data_dir, verify_file

SOURCE_NAME = "partnet_programs.tar.gz"
#: sha256 of the published ``partnet_programs.tar.gz`` (the compressed file's bytes); checked before any use
SOURCE_SHA256 = "957ace4785ffd6e5dc345a1fae05e571ea1d9d82aa2b14c08deb57274b4daa71"
FOLDER = "shapeassembly_partnet"
CATEGORIES = ("chair", "table", "storage")


def read_source(tar_path: str | os.PathLike) -> tuple[dict[tuple[str, str], str], list[tuple[str, str, str]]]:
    """Programs {(category, id): text} and the split assignment [(split, category, id)] of the tarball.

    Split rule: train = the official train ids of all three categories; the official
    val ids, sorted by (category, numeric id), alternate val (even positions) / test (odd).
    """
    programs: dict[tuple[str, str], str] = {}
    official: dict[tuple[str, str], list[str]] = {}
    with tarfile.open(tar_path, "r:gz") as tar:
        for m in tar:
            if not m.isfile():
                continue
            parts = Path(m.name).parts
            if len(parts) == 3 and parts[0] == "programs" and parts[2].endswith(".txt"):
                programs[(parts[1], parts[2][:-4])] = tar.extractfile(m).read().decode()
            elif len(parts) == 3 and parts[0] == "splits" and parts[2] in ("train.txt", "val.txt"):
                ids = tar.extractfile(m).read().decode().split()
                official[(parts[1], parts[2][:-4])] = ids
    missing = [f"splits/{c}/{s}.txt" for c in CATEGORIES for s in ("train", "val") if (c, s) not in official]
    if missing:
        raise DataError(tar_path, f"missing split lists {', '.join(missing)}")

    def key(cat_id: tuple[str, str]):
        return CATEGORIES.index(cat_id[0]), int(cat_id[1]) if cat_id[1].isdigit() else cat_id[1]

    assignment = [("train", c, i) for c, i in sorted(((c, i) for c in CATEGORIES for i in official[(c, "train")]),
                                                     key=key)]
    val = sorted(((c, i) for c in CATEGORIES for i in official[(c, "val")]), key=key)
    assignment += [("val" if n % 2 == 0 else "test", c, i) for n, (c, i) in enumerate(val)]
    order = {s: k for k, s in enumerate(SPLITS)}
    assignment.sort(key=lambda r: (order[r[0]], key((r[1], r[2]))))
    return programs, assignment


def find_source(data_dir: str | os.PathLike | None) -> Path:
    """The programs tarball in the data directory (or its ``shapeassembly_partnet/`` folder), sha256-verified."""
    root = resolve_data_dir(data_dir)
    for path in (root / FOLDER / SOURCE_NAME, root / SOURCE_NAME):
        if path.is_file():
            return verify_file(path, SOURCE_SHA256, "PartNet")
    raise DataError(root / FOLDER / SOURCE_NAME, "no such file: the PartNet ShapeAssembly programs are needed "
                                                 "for the 3D target shapes (see the datasets README)")


def check(data_dir: str | os.PathLike | None = None) -> list[str]:
    """Lines for ``plad data check``: the tarball found, readable, its programs and split sizes.

    Raises :class:`DataError` (one line naming the file) when it is missing or unreadable, or
    when a split lists ids the archive holds no program for.
    """
    path = find_source(data_dir)
    try:
        programs, assignment = read_source(path)
    except (tarfile.TarError, EOFError, OSError, ValueError, UnicodeDecodeError) as err:
        raise DataError(path, f"not a readable PartNet programs archive ({err.__class__.__name__}: {err})") from None
    absent = [f"{c}/{i}" for _, c, i in assignment if (c, i) not in programs]
    if absent:
        raise DataError(path, f"{len(absent)} split ids without a program, e.g. {absent[0]}")
    per_cat = ", ".join(f"{sum(1 for c, _ in programs if c == cat)} {cat}" for cat in CATEGORIES)
    counts = {s: sum(1 for r in assignment if r[0] == s) for s in SPLITS}
    return [f"PartNet programs {path}: {len(programs)} programs ({per_cat}), sha256 {SOURCE_SHA256} verified",
            "PartNet " + ", ".join(f"{s}: {n} programs" for s, n in counts.items())
            + " (executed and voxelized at 32^3 by the prepare stage)"]


def checksums(data_dir: str | os.PathLike | None = None) -> dict[str, str]:
    """{the programs tarball: its sha256} (verified by :func:`find_source`)."""
    return {str(find_source(data_dir)): SOURCE_SHA256}
