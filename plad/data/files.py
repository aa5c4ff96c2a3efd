"""Real target shapes, whatever the dataset: where they live, verification, download, prepared files.

Each dataset is a module of :mod:`plad.data.datasets`; this module holds what they
share. A domain names its :class:`TargetSource`, the ``prepare`` stage writes
every source's splits once per domain as a prepared file
(:func:`write_prepared`), and training and evaluation read them back with
:func:`load_prepared`: those live in :mod:`plad.data.prepared`, and :class:`DataError`
in :mod:`plad.data.errors`; all are importable from here too.

Where the data directory is (:func:`resolve_data_dir`), in order:

1. an explicit argument (the CLI passes the params key ``data_dir`` here),
2. the environment variable ``PLAD_DATA_DIR``,
3. ``./data/datasets`` under the current working directory.

Datasets are described as data (:class:`DatasetSpec`) so that a new one is a
new record, not new code paths. Every file is checked against its published
sha256 before use: a half-downloaded or swapped file would otherwise train
and evaluate silently on the wrong shapes.

Every failure a user can fix (missing, truncated, damaged or wrong file) is a
:class:`DataError` whose message is one line naming the file, so the CLI can
print it without a traceback.
"""
from __future__ import annotations

import gzip
import hashlib
import http.client
import io
import logging
import os
import tempfile
import threading
import urllib.error
import urllib.request
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from plad.data.errors import DataError
from plad.data.prepared import (
    SPLITS,
    PreparedTargets,
    TargetSource,
    evenly_spaced,
    evenly_spaced_index,
    load_prepared,
    load_split,
    write_prepared,
)
from plad.fsutil import sha256_file

log = logging.getLogger(__name__)

DATA_DIR_ENV = "PLAD_DATA_DIR"
DEFAULT_DATA_SUBDIR = Path("data") / "datasets"

_CHUNK = 1 << 20
_GZIP_MAGIC = b"\x1f\x8b"


# --------------------------------------------------------------------------- specs
@dataclass(frozen=True)
class SplitSpec:
    """One split of a dataset: its name, where it is stored, and its exact shape."""

    name: str
    key: str
    shape: tuple[int, ...]


@dataclass(frozen=True)
class DatasetSpec:
    """Everything needed to find, verify and fetch one dataset file.

    Derive variants (a mirror URL, a test double) with ``dataclasses.replace``.
    """

    name: str
    #: paths relative to the data directory, tried in order; ``.gz`` ones are gzip of the file
    candidates: tuple[str, ...]
    #: sha256 of the (uncompressed) file
    sha256: str
    #: public home, used by download
    url: str
    #: where a download is placed, relative to the data directory
    download_to: str
    splits: tuple[SplitSpec, ...]
    #: numpy dtype name every split must have
    dtype: str = "bool"
    #: container format of the file (only ``hdf5`` so far)
    format: str = "hdf5"

    def split(self, name: str) -> SplitSpec:
        for s in self.splits:
            if s.name == name:
                return s
        allowed = ", ".join(repr(s.name) for s in self.splits)
        raise ValueError(f"unknown {self.name} split {name!r}; allowed: {allowed}")


# --------------------------------------------------------------------------- location
def resolve_data_dir(explicit: str | os.PathLike | None = None) -> Path:
    """The data directory: ``explicit``, else ``$PLAD_DATA_DIR``, else ``./data/datasets``.

    Existence is not checked here, so that callers can report a missing file
    with the list of names they looked for, or download into the directory.
    """
    if explicit is not None and str(explicit) != "":
        return Path(explicit).expanduser()
    env = os.environ.get(DATA_DIR_ENV, "")
    if env:
        return Path(env).expanduser()
    return Path.cwd() / DEFAULT_DATA_SUBDIR


def find_dataset_file(spec: DatasetSpec, data_dir: str | os.PathLike | None = None) -> Path | None:
    """The first existing candidate file of ``spec`` in the data directory, or ``None``."""
    root = resolve_data_dir(data_dir)
    for rel in spec.candidates:
        path = root / rel
        if path.is_file():
            return path
    return None


def _missing_error(spec: DatasetSpec, root: Path) -> DataError:
    looked = ", ".join(spec.candidates)
    # Absolute, because the default is relative to the working directory,
    # which is rarely obvious from a log.
    return DataError(
        root.absolute(),
        f"{spec.name} dataset not found (looked for {looked}); point the data directory at the "
        f"folder holding it with ${DATA_DIR_ENV} or the params key `data_dir`, or fetch it with "
        f"download=True / `plad data download`",
    )


# --------------------------------------------------------------------------- loading
# Keyed on the resolved path and dataset; the stamp (mtime, size, expected hash)
# invalidates an entry when the file is replaced, e.g. by a fresh download.
_Stamp = tuple[int, int, str]
_CACHE: dict[tuple[str, str], tuple[_Stamp, dict[str, np.ndarray]]] = {}
_CACHE_LOCK = threading.Lock()


def clear_cache() -> None:
    """Forget all loaded datasets (frees their memory; the next load re-reads and re-verifies)."""
    with _CACHE_LOCK:
        _CACHE.clear()


def load_dataset(spec: DatasetSpec, data_dir: str | os.PathLike | None = None,
                 split: str = "test", *, download: bool = False) -> np.ndarray:
    """One split of ``spec`` as a fresh array.

    Reads the first of ``spec.candidates`` found in the data directory
    (:func:`resolve_data_dir`), verifies its sha256 and caches all splits for
    the process, so loading the three splits reads the file once. With
    ``download=True`` a missing file is downloaded first; a present but
    damaged file is reported, not replaced.
    """
    split_spec = spec.split(split)  # ValueError before touching the disk
    root = resolve_data_dir(data_dir)
    path = find_dataset_file(spec, root)
    if path is None:
        if not download:
            raise _missing_error(spec, root)
        path = download_dataset(spec, root)
    arrays = _cached_arrays(spec, path)
    # A copy, because callers normalise/augment in place and the cached
    # original must stay the verified data; copying 40 MB is ~10 ms, far
    # cheaper than re-reading.
    return arrays[split_spec.name].copy()


def _cached_arrays(spec: DatasetSpec, path: Path) -> dict[str, np.ndarray]:
    resolved = path.resolve()
    try:
        st = resolved.stat()
    except OSError as e:
        raise DataError(path, f"cannot read: {e.strerror or e}") from e
    key = (str(resolved), spec.name)
    stamp: _Stamp = (st.st_mtime_ns, st.st_size, spec.sha256)
    # Holding the lock while reading keeps concurrent first loads (e.g. data
    # loader threads) from decompressing the same file several times.
    with _CACHE_LOCK:
        hit = _CACHE.get(key)
        if hit is not None and hit[0] == stamp:
            return hit[1]
        arrays = _read_verified(spec, path)
        _CACHE[key] = (stamp, arrays)
        return arrays


def _read_verified(spec: DatasetSpec, path: Path) -> dict[str, np.ndarray]:
    """Read, checksum and validate every split of the file at ``path``."""
    if spec.format != "hdf5":
        raise DataError(path, f"unsupported dataset format {spec.format!r}")
    log.info("loading %s dataset from %s", spec.name, path)
    if path.name.endswith(".gz"):
        # The whole file is small enough (~65 MB for CSGNet's CAD) to decompress into
        # memory; that avoids writing a decompressed copy into what may be a
        # read-only shared folder.
        data = _gunzip_verified(spec, path)
        return _read_hdf5(spec, path, data)
    _check_sha256(spec, path, checked_sha256(path), what="sha256")
    return _read_hdf5(spec, path, path)


def _gunzip_verified(spec: DatasetSpec, path: Path) -> io.BytesIO:
    try:
        with open(path, "rb") as raw:
            magic = raw.read(2)
            if magic != _GZIP_MAGIC:
                got = "an empty file" if not magic else f"starts with {magic!r}"
                raise DataError(path, f"not a gzip file ({got}); expected gzip of {spec.name}'s file")
            raw.seek(0)
            out = io.BytesIO()
            digest = hashlib.sha256()
            with gzip.GzipFile(fileobj=raw, mode="rb") as gz:
                while chunk := gz.read(_CHUNK):
                    digest.update(chunk)
                    out.write(chunk)
    except EOFError as e:
        raise DataError(path, f"truncated gzip file (incomplete download or copy?): {e}") from e
    except (gzip.BadGzipFile, zlib.error) as e:
        raise DataError(path, f"corrupt gzip data: {e}") from e
    except OSError as e:
        raise DataError(path, f"cannot read: {e.strerror or e}") from e
    _check_sha256(spec, path, digest.hexdigest(), what="sha256 of the decompressed data")
    out.seek(0)
    return out


def checked_sha256(path: Path) -> str:
    """:func:`plad.fsutil.sha256_file`, with a file that cannot be read as a one-line DataError."""
    try:
        return sha256_file(path)
    except OSError as e:
        raise DataError(path, f"cannot read: {e.strerror or e}") from e


def _check_sha256(spec: DatasetSpec, path: Path | str, got: str, *, what: str, hint: str = "") -> None:
    _sha256_matches(spec.name, spec.sha256, path, got, what=what, hint=hint)


def _sha256_matches(name: str, expected: str, path: Path | str, got: str, *, what: str, hint: str = "") -> None:
    if got != expected:
        raise DataError(
            path,
            f"{what} mismatch: expected {expected[:12]}..., got {got[:12]}... "
            f"(not {name}'s published file, or damaged{hint})",
        )


def verify_file(path: str | os.PathLike, sha256: str, name: str) -> Path:
    """``path`` as published: its bytes' sha256 is ``sha256``, else a :class:`DataError` as for the CAD file.

    A gzip file (``.gz``) is first checked to be gzip data at all, so an HTML page or an empty file is named
    as such rather than as a checksum mismatch.
    """
    path = Path(path)
    if path.name.endswith(".gz"):
        try:
            with open(path, "rb") as raw:
                magic = raw.read(2)
        except OSError as e:
            raise DataError(path, f"cannot read: {e.strerror or e}") from e
        if magic != _GZIP_MAGIC:
            got = "an empty file" if not magic else f"starts with {magic!r}"
            raise DataError(path, f"not a readable .tar.gz: not gzip data ({got}); expected {name}'s file")
    _sha256_matches(name, sha256, path, checked_sha256(path), what="sha256")
    return path


def _read_hdf5(spec: DatasetSpec, path: Path, source: Path | BinaryIO) -> dict[str, np.ndarray]:
    import h5py  # deferred: only data loading needs it, and it is slow to import

    try:
        f = h5py.File(source, "r")
    except OSError as e:
        raise DataError(path, f"not an HDF5 file (h5py: {e})") from e
    arrays: dict[str, np.ndarray] = {}
    try:
        with f:
            for s in spec.splits:
                if s.key not in f:
                    have = ", ".join(sorted(f.keys())) or "none"
                    raise DataError(path, f"missing HDF5 key {s.key!r} for split {s.name!r} (keys: {have})")
                ds = f[s.key]
                if not isinstance(ds, h5py.Dataset):
                    raise DataError(path, f"HDF5 key {s.key!r} is a group, expected a dataset")
                if tuple(ds.shape) != s.shape:
                    raise DataError(path, f"HDF5 key {s.key!r} has shape {tuple(ds.shape)}, expected {s.shape}")
                if ds.dtype != np.dtype(spec.dtype):
                    raise DataError(path, f"HDF5 key {s.key!r} has dtype {ds.dtype}, expected {spec.dtype}")
                arrays[s.name] = ds[...]
    except OSError as e:
        raise DataError(path, f"damaged HDF5 data (h5py: {e})") from e
    return arrays


# --------------------------------------------------------------------------- download
def download_dataset(spec: DatasetSpec, data_dir: str | os.PathLike | None = None, *,
                     url: str | None = None, timeout: float = 60.0) -> Path:
    """Download ``spec``'s file into the data directory and return its path.

    The bytes go to a temporary file beside the target and are hashed as they
    stream; only a verified file is renamed into place (atomically), so an
    interrupted or wrong download never leaves something that looks usable.
    An existing target is replaced only by a verified download.
    """
    url = url or spec.url
    target = resolve_data_dir(data_dir) / spec.download_to
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent)
    except OSError as e:
        raise DataError(target.parent, f"cannot create the download folder or file: {e.strerror or e}") from e
    tmp = Path(tmp_name)
    log.info("downloading %s dataset from %s to %s", spec.name, url, target)
    try:
        with os.fdopen(fd, "wb") as out:
            digest, size = _stream_to(url, out, target, timeout)
            out.flush()
            os.fsync(out.fileno())
        _check_sha256(spec, target, digest, what="downloaded sha256",
                      hint=f"; downloaded {size} bytes from {url}; nothing was saved")
        os.replace(tmp, target)
    except DataError:
        tmp.unlink(missing_ok=True)
        raise
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise DataError(target, f"cannot write the download: {e.strerror or e}") from e
    except BaseException:
        # KeyboardInterrupt included: a partial file must not survive.
        tmp.unlink(missing_ok=True)
        raise
    log.info("saved %s (%d bytes, sha256 verified)", target, size)
    return target


def _stream_to(url: str, out: BinaryIO, target: Path, timeout: float) -> tuple[str, int]:
    """Copy ``url`` into ``out``; returns (sha256 hex, byte count). Network failures are DataErrors."""
    digest = hashlib.sha256()
    size = 0
    # Network errors are told apart from local write errors (both OSError) by
    # where they happen: only reads from the response are wrapped here.
    request = urllib.request.Request(url, headers={"User-Agent": "plad-data/1"})
    try:
        response = urllib.request.urlopen(request, timeout=timeout)
    except (urllib.error.URLError, http.client.HTTPException, OSError, ValueError) as e:
        raise DataError(target, f"download from {url} failed: {_reason(e)}") from e
    with response:
        while True:
            try:
                chunk = response.read(_CHUNK)
            except (http.client.HTTPException, OSError) as e:
                raise DataError(target, f"download from {url} failed after {size} bytes: {_reason(e)}") from e
            if not chunk:
                break
            digest.update(chunk)
            out.write(chunk)
            size += len(chunk)
    return digest.hexdigest(), size


def _reason(e: BaseException) -> str:
    if isinstance(e, urllib.error.HTTPError):
        return f"HTTP {e.code} {e.reason}"
    if isinstance(e, urllib.error.URLError):
        return str(e.reason)
    return f"{type(e).__name__}: {e}"


__all__ = [
    "DATA_DIR_ENV",
    "SPLITS",
    "DataError",
    "DatasetSpec",
    "PreparedTargets",
    "SplitSpec",
    "TargetSource",
    "clear_cache",
    "download_dataset",
    "evenly_spaced",
    "evenly_spaced_index",
    "find_dataset_file",
    "load_dataset",
    "load_prepared",
    "load_split",
    "resolve_data_dir",
    "write_prepared",
]
