"""P_BEST: the best program found so far for every training shape.

Each entry holds the program's tokens, its execution and its metric value
against the training shape; a program is stored in its domain's canonical form
(``canonical``, :meth:`plad.domains.base.Domain.canonical`: the same execution,
so the same value). In "all-time" mode (the paper's default) an
entry only changes when a new program scores at least as well (ties go to
the new program, as in the reference code), so the mean metric never gets
worse; in "per-round" mode every round starts from scratch (the
supplement's ablation). Each entry also records whether a rewriter
(:mod:`plad.learn.pbest_search`) has refined it since it last changed. Saved atomically
(``.npz``) and reloaded on resume.
"""
from __future__ import annotations

import io
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from plad.fsutil import atomic_write, savez
from plad.metrics import Metric

MODES = ("all-time", "per-round")


@dataclass
class UpdateStats:
    mean: float          # mean metric over the shapes that have an entry
    improved: float      # share of shapes whose entry changed for a strictly better program
    filled: float        # share of shapes that have an entry


class PBest:
    """Best programs for ``n`` shapes of the given shape, judged by ``metric``."""

    def __init__(self, n: int, shape: tuple[int, ...], max_len: int, metric: Metric, mode: str = "all-time",
                 canonical: Callable[[Sequence[int]], list[int]] | None = None):
        if mode not in MODES:
            raise ValueError(f"P_BEST mode {mode!r}: expected one of {', '.join(MODES)}")
        self.metric = metric
        self.mode = mode
        #: rewrites an offered program into its canonical form before it is stored (None: stored as offered)
        self.canonical = canonical
        self.programs = np.full((n, max_len), -1, dtype=np.int16)    # -1 padded token ids
        self.values = np.full(n, np.nan)                              # NaN: no entry yet
        self.executions = np.zeros((n, *shape), dtype=bool)
        #: the entry was refined by a rewriter and has not changed since
        self.refined = np.zeros(n, dtype=bool)

    def __len__(self) -> int:
        return len(self.values)

    @property
    def has(self) -> np.ndarray:
        return ~np.isnan(self.values)

    def program(self, i: int) -> list[int]:
        row = self.programs[i]
        return row[row >= 0].tolist()

    def start_round(self) -> None:
        """Per-round mode forgets every entry at the start of a round."""
        if self.mode == "per-round":
            self.values[:] = np.nan
            self.programs[:] = -1
            self.executions[:] = False
            self.refined[:] = False

    def update(self, index: np.ndarray, programs: list[list[int]], values: np.ndarray,
               executions: np.ndarray, refined: bool = False) -> UpdateStats:
        """Offer new programs for shapes ``index``; keep each if at least as good as the entry.

        ``refined``: the programs come from a rewriter (the flag of each kept entry is set to it).
        """
        index = np.asarray(index)
        values = np.asarray(values, dtype=np.float64)
        old = self.values[index]
        new_t, old_t = torch.from_numpy(values), torch.from_numpy(np.nan_to_num(old, nan=self.metric.worst))
        strictly = self.metric.better(new_t, old_t).numpy()
        take = strictly | (values == old) | np.isnan(old)
        for j in np.nonzero(take)[0]:
            i = index[j]
            program = self.canonical(programs[j]) if self.canonical else programs[j]
            self.programs[i] = -1
            self.programs[i, : len(program)] = program
        self.values[index[take]] = values[take]
        self.executions[index[take]] = executions[take]
        self.refined[index[take]] = refined
        improved = (strictly & ~np.isnan(old)) | (np.isnan(old) & take)
        has = self.has
        return UpdateStats(mean=float(self.values[has].mean()) if has.any() else float("nan"),
                           improved=float(improved.sum() / max(len(index), 1)),
                           filled=float(has.mean()))

    # ---- persistence -------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> None:
        buf = io.BytesIO()
        savez(buf, programs=self.programs, values=self.values,
                            executions=np.packbits(self.executions.reshape(len(self), -1), axis=1),
                            shape=np.asarray(self.executions.shape[1:]), mode=np.asarray(self.mode),
                            refined=self.refined)
        atomic_write(path, lambda fh: fh.write(buf.getvalue()))

    @classmethod
    def load(cls, path: str | os.PathLike, metric: Metric,
             canonical: Callable[[Sequence[int]], list[int]] | None = None) -> PBest:
        with np.load(Path(path)) as z:
            shape = tuple(int(v) for v in z["shape"])
            out = cls(len(z["values"]), shape, z["programs"].shape[1], metric, str(z["mode"]), canonical)
            out.programs = z["programs"].copy()
            out.values = z["values"].copy()
            if "refined" in z.files:   # files of older versions have no flags: nothing refined
                out.refined = z["refined"].copy()
            n = int(np.prod(shape))
            out.executions = np.unpackbits(z["executions"], axis=1, count=n).astype(bool).reshape(-1, *shape)
        return out
