"""Filesystem helpers: atomic writes, so that a killed run never leaves half a file; inter-process locks."""
from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO


def atomic_write(path: str | os.PathLike, write: Callable[[BinaryIO], object], mode: int = 0o644) -> Path:
    """Call ``write(fh)`` on a temporary file beside ``path``, then rename it over ``path`` (permissions ``mode``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, mode)  # mkstemp creates 0600; outputs are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def sha256_file(path: str | os.PathLike) -> str:
    """The sha256 of a file's bytes, read in 1 MiB pieces (the one home of a file's hash)."""
    import hashlib

    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def atomic_write_text(path: str | os.PathLike, text: str, mode: int = 0o644) -> Path:
    return atomic_write(path, lambda fh: fh.write(text.encode()), mode)


@contextlib.contextmanager
def file_lock(path: str | os.PathLike, *, shared: bool = False, create: bool = True) -> Iterator[bool]:
    """Hold an ``flock`` on ``path`` (exclusive, or ``shared``) for the block, waiting for it; yields ``True``.

    The lock file is created when ``create`` (permissions 0666 less the umask, so that users sharing a
    folder share its locks) and is never removed (removing it would let two holders lock two files).
    Where it cannot be opened (a read-only folder without it, or ``create=False`` and none there) the
    block runs unlocked and ``False`` is yielded: the caller decides whether that is safe. flock
    excludes between processes and also between separately opened descriptors of one process (threads).
    """
    fd = None
    with contextlib.suppress(OSError):
        fd = os.open(path, (os.O_RDWR | os.O_CREAT) if create else os.O_RDONLY, 0o666)
    if fd is None:
        with contextlib.suppress(OSError):
            fd = os.open(path, os.O_RDONLY)       # flock needs no write access to the file
    if fd is None:
        yield False
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_SH if shared else fcntl.LOCK_EX)
        yield True
    finally:
        os.close(fd)                              # releases the lock
