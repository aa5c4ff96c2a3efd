"""The real target shapes as the ``prepare`` stage writes them: a domain's :class:`TargetSource` and the
prepared ``.npz`` files (:func:`write_prepared`, :func:`load_prepared`, :func:`load_split`).

Part of :mod:`plad.data.files` before (every name here is importable from there too); a prepared file
that is missing or damaged is a :class:`~plad.data.errors.DataError` naming it.
"""
from __future__ import annotations

import abc
import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plad.data.errors import DataError
from plad.fsutil import atomic_write, atomic_write_text, savez

# --------------------------------------------------------------------------- target sources
SPLITS = ("train", "val", "test")


@dataclass
class PreparedTargets:
    """What a :class:`TargetSource` hands the ``prepare`` stage."""

    #: split name -> bool (N, *shape), for every name of :data:`SPLITS`
    splits: dict[str, np.ndarray]
    #: recorded in the summary (``<domain>.json``) of every domain on this source
    provenance: dict = field(default_factory=dict)
    #: the stage's result for this source (counts, time, failures)
    report: dict = field(default_factory=dict)


class TargetSource(abc.ABC):
    """Where the real target shapes of one or more domains come from.

    A domain names its source (:attr:`plad.domains.base.Domain.targets`);
    domains on the same data share one source object, which the ``prepare``
    stage prepares once for all of them.
    """

    #: the source's name in params and results, e.g. ``"cad"``
    name: str
    #: files :meth:`prepare` writes into the prepared folder besides the domains' own (DVC outputs too)
    files: tuple[str, ...] = ()

    @abc.abstractmethod
    def load(self, split: str, data_dir: str | os.PathLike | None = None) -> np.ndarray:
        """The shapes of ``split`` (one of :data:`SPLITS`) from the data directory: bool (N, *shape)."""

    def prepare(self, data_dir: str | os.PathLike | None, out_dir: str | os.PathLike,
                limit: int | None = None) -> PreparedTargets:
        """Every split for the ``prepare`` stage; ``limit`` keeps the first N shapes of each.

        Default: :meth:`load` of each split. A source that builds its shapes
        (e.g. by executing programs) overrides this and may write its own
        files (reports, logs) into ``out_dir``.
        """
        return PreparedTargets({s: self.load(s, data_dir)[:limit] for s in SPLITS})


# --------------------------------------------------------------------------- prepared files
def write_prepared(name: str, shape: tuple[int, ...], splits: dict[str, np.ndarray], path: str | os.PathLike,
                   summary_path: str | os.PathLike, extra: dict | None = None) -> dict:
    """Write ``path`` (a ``.npz`` of bit-packed splits) and its JSON summary; returns the summary."""
    arrays = {s: np.packbits(x.reshape(len(x), -1), axis=1) for s, x in splits.items()}
    arrays["shape"] = np.asarray(shape)
    summary = {
        "domain": name,
        "shape": list(shape),
        **{f"{s}_count": int(len(x)) for s, x in splits.items()},
        **{f"{s}_occupancy": round(float(x.mean()), 6) if len(x) else 0.0 for s, x in splits.items()},
        **(extra or {}),
    }
    atomic_write(Path(path), lambda fh: savez(fh, **arrays))
    atomic_write_text(Path(summary_path), json.dumps(summary, indent=2) + "\n")
    return summary


def evenly_spaced_index(total: int, n: int | None) -> np.ndarray:
    """Indices (int64) of ``n`` items evenly spaced over ``total`` (all ``total`` if ``n`` is None or not smaller)."""
    if n is None or n >= total:
        return np.arange(total)
    # n < total: the points are more than 1 apart, so their rounding never repeats an index
    return np.linspace(0, total - 1, n).round().astype(np.int64)


def evenly_spaced(items: np.ndarray, n: int | None) -> np.ndarray:
    """``n`` items evenly spaced over ``items`` (all of them if ``n`` is None or not smaller).

    Prepared splits are ordered (PartNet: by category, chairs first), so a prefix would be one category.
    """
    if n is None or n >= len(items):
        return items
    return items[evenly_spaced_index(len(items), n)]


def load_prepared(path: str | os.PathLike, split: str) -> np.ndarray:
    """Read one split back from a prepared ``.npz`` (:func:`write_prepared`): bool (N, *shape).

    A missing, unreadable or incomplete file is a :class:`DataError` naming it (the prepare stage makes it).
    """
    if not Path(path).is_file():
        raise DataError(path, "no such prepared file; run the prepare stage (dvc repro prepare)")
    try:
        with np.load(path) as z:
            shape = tuple(int(v) for v in z["shape"])
            packed = z[split]
        return np.unpackbits(packed, axis=1, count=int(np.prod(shape))).astype(bool).reshape(-1, *shape)
    except KeyError as err:
        raise DataError(path, f"not a prepared file with split {split!r} (missing {err})") from None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
        raise DataError(path, f"not a readable prepared .npz ({type(err).__name__}: {err})") from None


def load_split(path: str | os.PathLike, split: str, limit: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(shapes, their indices in the split): a split of a prepared ``.npz``, or ``limit`` of its shapes evenly
    spaced over it (:func:`evenly_spaced_index`)."""
    shapes = load_prepared(path, split)
    index = evenly_spaced_index(len(shapes), limit)
    return (shapes if limit is None else shapes[index]), index
