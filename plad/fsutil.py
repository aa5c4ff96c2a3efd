"""Filesystem helpers: the one writer of every file the project writes, and inter-process locks.

:func:`atomic_write` is how every output is written (``plad execute -o``, ``plad infer``'s files, exports,
pictures, checkpoints, the stages' files): a temporary file beside the target, written, flushed and
``fsync``'d, then renamed over the target (and the folder ``fsync``'d). A killed process or a full disk
therefore never leaves half a file, a 0-byte file or a damaged one where the old one was: the old file
stays until the new one is complete. Any failure is a :class:`WriteError`, one line naming the path and
the cause (``cannot write x.png: No space left on device``), and the temporary file is removed. A writer
that cannot write into an open file makes its bytes in memory first (meshes: :mod:`plad.data.mesh`;
figures: :func:`plad.data.pictures.save_figure`), so that nothing writes past this function.
"""
from __future__ import annotations

import contextlib
import errno as _errno
import fcntl
import os
import tempfile
import time
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO

from plad.errors import RunFailure, one_line

#: the longest file name most file systems take (bytes); a temporary name is kept within it
NAME_MAX = 255
#: a writer's temporary file older than this (seconds) is a killed writer's and is removed by the next write
STALE_SECONDS = 3600
#: the most folder entries looked at for such files per write (a write's cost stays bounded in a large folder)
STALE_SCAN = 4096


class WriteError(RunFailure, OSError):
    """A file cannot be written: one line naming the path and the cause (exit status 1; the command line
    reports an output path of the user's with status 2). An ``OSError`` too, with the cause's ``errno``."""

    def __init__(self, path: str | os.PathLike, cause: BaseException | str):
        self.path = Path(path)
        self.cause = cause_of(cause)
        code = getattr(cause, "errno", None) if isinstance(cause, BaseException) else None
        super().__init__(code if code is not None else _errno.EIO, self.cause, str(path))

    def __str__(self) -> str:
        # a name with a newline or another unprintable character is shown quoted (as plad.data.inputs.quote)
        name = str(self.path)
        return f"cannot write {name if name.isprintable() else repr(name)}: {self.cause}"


def cause_of(err: BaseException | str) -> str:
    """The cause of an error in a few words: an ``OSError``'s ``strerror`` (``No space left on device``),
    else its one-line text, else its class."""
    if isinstance(err, str):
        return one_line(err)
    if isinstance(err, WriteError):
        return err.cause
    if isinstance(err, OSError) and err.strerror:
        return err.strerror
    return one_line(err) or err.__class__.__name__


def _temp_prefix(name: str) -> str:
    """``.<name>.``, cut so that the temporary name (prefix, 8 random characters, ``.tmp``) fits
    :data:`NAME_MAX` bytes: a target whose name is at the limit still gets a temporary file beside it."""
    raw = os.fsencode(name)
    room = NAME_MAX - 2 - 8 - 4 - 2
    if len(raw) > room:
        raw = raw[:room]
        while raw:   # never cut a character in half
            try:
                raw.decode("utf-8")
                break
            except UnicodeDecodeError:
                raw = raw[:-1]
    return "." + os.fsdecode(raw) + "."


def _remove_stale(folder: Path, prefix: str) -> None:
    """Remove the temporary files of this target left by a writer killed more than :data:`STALE_SECONDS`
    ago (a writer alive now has a younger one), among the first :data:`STALE_SCAN` entries of the folder."""
    now = time.time()
    with contextlib.suppress(OSError), os.scandir(folder) as entries:
        for n, entry in enumerate(entries):
            if n >= STALE_SCAN:
                break
            if entry.name.startswith(prefix) and entry.name.endswith(".tmp") and len(entry.name) == \
                    len(prefix) + 8 + 4:
                with contextlib.suppress(OSError):
                    if now - entry.stat(follow_symlinks=False).st_mtime > STALE_SECONDS:
                        os.unlink(entry.path)


def _fsync_folder(folder: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _open_temp(fd: int) -> BinaryIO:
    """The temporary file's descriptor as a binary file (one place, which the tests replace by a disk that
    fills)."""
    return os.fdopen(fd, "wb")


def atomic_write(path: str | os.PathLike, write: Callable[[BinaryIO], object], mode: int = 0o644) -> Path:
    """Call ``write(fh)`` on a temporary file beside ``path``, fsync it, then rename it over ``path``
    (permissions ``mode``). Any failure (a full disk, a read-only folder, a name too long, an error of
    ``write`` itself) leaves ``path`` as it was and no temporary file; an ``OSError`` (or a ``ValueError``
    of the file system's encoding) is raised as a :class:`WriteError` naming ``path``."""
    path = Path(path)
    tmp = None
    replaces = False
    try:
        replaces = path.exists()   # a file written again is where a killed writer may have left a temporary one
        if path.parent.exists() and not path.parent.is_dir():
            raise OSError(_errno.ENOTDIR, "its folder is a file")
        path.parent.mkdir(parents=True, exist_ok=True)
        prefix = _temp_prefix(path.name)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=prefix, suffix=".tmp")
        with _open_temp(fd) as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, mode)  # mkstemp creates 0600; outputs are meant to be shared
        os.replace(tmp, path)
        tmp = None
    except (OSError, UnicodeError) as err:
        raise (err if isinstance(err, WriteError) and err.path == path else WriteError(path, err)) from None
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
    _fsync_folder(path.parent)
    if replaces:
        _remove_stale(path.parent, prefix)
    return path


def atomic_write_bytes(path: str | os.PathLike, data: bytes, mode: int = 0o644) -> Path:
    """``data`` as the file ``path``, by :func:`atomic_write`."""
    return atomic_write(path, lambda fh: fh.write(data), mode)


def atomic_write_text(path: str | os.PathLike, text: str, mode: int = 0o644) -> Path:
    """``text`` as UTF-8 by :func:`atomic_write`. Text naming the user's files may hold the undecodable
    bytes of a file name (Python's surrogate escapes, as ``os.fsdecode`` gives them): they are written
    back as those bytes, as the file system spells the name, never an error."""
    return atomic_write(path, lambda fh: fh.write(text.encode("utf-8", "surrogateescape")), mode)


#: the time stamp of every member of the archives :func:`savez` writes (the zip format's earliest)
_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


def savez(file: BinaryIO, **arrays) -> None:
    """``numpy.savez_compressed`` with the same bytes for the same arrays under every numpy the project allows:
    numpy 1.x stamped each member with the time of writing, so a rebuilt output (a prepared dataset, labels)
    differed from the one DVC recorded and every stage after it counted as changed (numpy 2.4 writes these very
    bytes). Read back with ``numpy.load`` as before."""
    import numpy as np

    with zipfile.ZipFile(file, mode="w", compression=zipfile.ZIP_DEFLATED, allowZip64=True) as zf:
        for name, value in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_EPOCH)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o600 << 16
            with zf.open(info, "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=True)   # as numpy.savez


def sha256_file(path: str | os.PathLike) -> str:
    """The sha256 of a file's bytes, read in 1 MiB pieces (the one home of a file's hash)."""
    import hashlib

    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


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
