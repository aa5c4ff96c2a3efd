"""The error of every dataset and prepared file a user can fix (:class:`DataError`), one line naming the file.

Its own module so that :mod:`plad.data.files` and :mod:`plad.data.prepared` both raise it; importable from
:mod:`plad.data.files` too.
"""
from __future__ import annotations

import os

from plad.errors import RunFailure


class DataError(RunFailure):
    """A dataset file is missing or unusable. ``str(err)`` is one line: ``<path>: <problem>`` (exit status 1)."""

    def __init__(self, path: str | os.PathLike, problem: str) -> None:
        self.path = path
        self.problem = _one_line(problem)
        # Collapsed to one line here, once, because messages embed text from
        # h5py/zlib/urllib that may contain newlines, and the CLI relies on
        # a single line.
        super().__init__(_one_line(f"{path}: {self.problem}"))

    def __reduce__(self) -> tuple[type[DataError], tuple[str | os.PathLike, str]]:
        # Keeps the error picklable across worker processes (the default
        # would call __init__ with the message alone).
        return (type(self), (self.path, self.problem))


def _one_line(text: str) -> str:
    return " ".join(str(text).split())
