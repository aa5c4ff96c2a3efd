"""Nothing lost, nothing silent when a write fails (issue 53, faults while writing): every output goes through
plad.fsutil.atomic_write, so a full disk (simulated: the file system refuses a write partway, at a random
point; or a real 2 MiB tmpfs where this process may mount one) leaves the old file as it was, no 0-byte or
truncated file and no temporary one, and the error is one line naming the path and the cause. Names at the
file system's limit still get a temporary file beside them; a killed writer's temporary file is removed later.
"""
from __future__ import annotations

import errno
import io
import os
import subprocess
import time
import zlib
from pathlib import Path

import numpy as np
import pytest

from plad import fsutil
from plad.errors import run_guarded
from plad.fsutil import WriteError, atomic_write, atomic_write_text


class _FullDisk(io.FileIO):
    """A file whose writes fail with ENOSPC once ``limit`` bytes are written (a disk that fills partway)."""

    limit = 0

    def write(self, data):
        if self.tell() + len(data) > self.limit:
            room = max(0, self.limit - self.tell())
            if room:
                super().write(bytes(data)[:room])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return super().write(data)


@pytest.fixture
def full_disk(monkeypatch):
    """``full_disk(limit)``: from now on, every atomic write fails with ENOSPC after ``limit`` bytes."""
    def fill(limit: int) -> None:
        _FullDisk.limit = limit
        monkeypatch.setattr(fsutil, "_open_temp", lambda fd: io.BufferedWriter(_FullDisk(fd, "wb")))
    return fill


def _listing(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def _writers():
    """(name, suffix, write(path)) of every kind of output the project writes for a user."""
    from plad.data.mesh import write_mesh
    from plad.data.pictures import save_comparison, save_npy, save_png
    from plad.domains import get_domain
    from plad.domains.base import save_grid

    grid = np.zeros((64, 64), bool)
    grid[10:40, 20:50] = True
    cube = np.zeros((32, 32, 32), bool)
    cube[8:20, 8:20, 8:20] = True
    csg2d, csg3d = get_domain("csg2d"), get_domain("csg3d")
    return [
        ("text", ".txt", lambda p: atomic_write_text(p, "x" * 5000)),
        ("grid png", ".png", lambda p: save_grid(grid, p)),
        ("grid npy", ".npy", lambda p: save_grid(grid, p)),
        ("png", ".png", lambda p: save_png(np.zeros((50, 50, 3), np.uint8), p)),
        ("npy", ".npy", lambda p: save_npy(np.arange(2000), p)),
        ("comparison", ".png", lambda p: save_comparison([("a", grid), ("b", ~grid)], p, title="t")),
        ("ply", ".ply", lambda p: write_mesh(*_box(), p)),
        ("obj", ".obj", lambda p: write_mesh(*_box(), p)),
        ("svg", ".svg", lambda p: csg2d.write_export(csg2d.parse("c(32,32,16)$"), "svg", p)),
        ("scad", ".scad", lambda p: csg3d.write_export(csg3d.parse("cuboid 16 16 16 8 8 8"), "scad", p)),
        ("3d views", ".png", lambda p: csg3d.execute_text("cuboid 16 16 16 8 8 8", p)),
        ("3d mesh", ".ply", lambda p: csg3d.execute_text("cuboid 16 16 16 8 8 8", p)),
    ]


def _box():
    from plad.domains.csg3d.export import mesh_arrays

    cube = np.zeros((32, 32, 32), bool)
    cube[8:20, 8:20, 8:20] = True
    return mesh_arrays(cube)


@pytest.mark.parametrize("name, suffix, write", _writers(), ids=[w[0] for w in _writers()])
def test_a_full_disk_at_any_point_keeps_the_old_file_and_leaves_nothing_else(tmp_path, full_disk, name, suffix,
                                                                            write):
    target = tmp_path / f"out{suffix}"
    write(target)                                    # the old file, written on a disk with room
    old = _listing(tmp_path)
    assert target.stat().st_size > 0
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    for limit in [0, 1, *rng.integers(2, max(3, target.stat().st_size), 4).tolist()]:
        full_disk(int(limit))
        with pytest.raises(OSError) as err:
            write(target)
        assert isinstance(err.value, WriteError) and err.value.errno == errno.ENOSPC
        line = str(err.value)
        assert line == f"cannot write {target}: No space left on device" and "\n" not in line
        assert _listing(tmp_path) == old, (name, limit)   # the old file as it was; no temporary, no 0-byte file


def test_a_failing_writer_and_unwritable_places_are_one_line_and_leave_nothing(tmp_path):
    target = tmp_path / "a.txt"
    atomic_write_text(target, "old")

    def broken(fh):
        fh.write(b"half")
        raise ValueError("the writer's own bug")
    with pytest.raises(ValueError):                  # not an OSError: raised as it is, the old file kept
        atomic_write(target, broken)
    assert _listing(tmp_path) == {"a.txt": b"old"}
    (tmp_path / "file").write_text("x")
    for place, cause in [(tmp_path / "file" / "x.txt", "its folder is a file"),
                         (tmp_path / ("n" * 256), "File name too long")]:
        with pytest.raises(WriteError) as err:
            atomic_write_text(place, "x")
        assert str(err.value) == f"cannot write {place}: {cause}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "file"]


def test_a_name_at_the_limit_gets_its_temporary_file_beside_it_and_text_keeps_undecodable_names(tmp_path):
    longest = tmp_path / ("é" * 127)                # 254 bytes in UTF-8: the prefix is cut on a character
    atomic_write_text(longest, "ok")
    assert longest.read_text() == "ok" and len(list(tmp_path.iterdir())) == 1
    name = os.fsdecode(b"bad_\xff\xfe.png")
    atomic_write_text(tmp_path / "names.txt", name + "\n")
    assert (tmp_path / "names.txt").read_bytes() == b"bad_\xff\xfe.png\n"   # the name's own bytes


def test_a_killed_writers_temporary_file_is_removed_by_the_next_write_once_stale(tmp_path):
    target = tmp_path / "x.json"
    atomic_write_text(target, "{}")                  # a file written again: a killed writer may have left one
    stale, fresh = tmp_path / ".x.json.abcd1234.tmp", tmp_path / ".x.json.efgh5678.tmp"
    for path in (stale, fresh):
        path.write_bytes(b"half a file")
    old = time.time() - fsutil.STALE_SECONDS - 60
    os.utime(stale, (old, old))
    atomic_write_text(target, "{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == [fresh.name, "x.json"]   # a live writer's is kept


def test_an_environment_oserror_is_one_line_and_a_bug_keeps_its_traceback(capsys):
    def full():
        raise OSError(errno.ENOSPC, "No space left on device", "/runs/x/last.pt")
    assert run_guarded("stage", full) == 1
    assert capsys.readouterr().err == "stage: error: cannot use /runs/x/last.pt: No space left on device\n"

    def bug():
        raise OSError(errno.EBADF, "Bad file descriptor")
    with pytest.raises(OSError):
        run_guarded("stage", bug)


def test_execute_and_refine_on_a_full_disk(tmp_path, full_disk, capsys):
    from plad.serve.cli import main

    png, ply = tmp_path / "old.png", tmp_path / "old.ply"
    assert main(["execute", "csg2d", "c(32,32,16)$", "-o", str(png)]) == 0
    assert main(["execute", "csg3d", "cuboid 16 16 16 4 4 4", "-o", str(ply)]) == 0
    target = tmp_path / "target.npy"
    grid = np.zeros((64, 64), bool)
    grid[16:48, 16:48] = True
    np.save(target, grid)
    old = _listing(tmp_path)
    capsys.readouterr()
    full_disk(100)
    assert main(["execute", "csg2d", "s(32,32,16)$", "-o", str(png)]) == 2
    assert main(["execute", "csg3d", "union cuboid 16 16 22 26 26 4 ellipsoid 24 24 11 8 8 18", "-o", str(ply)]) == 2
    assert main(["execute", "csg3d", "cuboid 16 16 16 4 4 4", "-o", str(tmp_path / "new.obj")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [f"plad: error: {p}: cannot write (No space left on device)"
                   for p in (png, ply, tmp_path / "new.obj")]
    assert _listing(tmp_path) == old                 # old files intact, no 0-byte new file
    full_disk(0)
    assert main(["refine", "csg2d", "c(32,32,16)$", "--target", str(target), "--effort", "fast",
                 "-o", str(tmp_path / "refined.txt")]) == 2
    out, err = capsys.readouterr()
    assert out.splitlines()[0].endswith("$") and "->" in out          # the refined program is printed first
    assert err.strip().splitlines()[-1] == f"plad: error: {tmp_path / 'refined.txt'}: cannot write (No space " \
                                           "left on device)"
    assert _listing(tmp_path) == old


def _can_mount_tmpfs(folder: Path) -> bool:
    if os.geteuid() != 0:
        return False
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(folder)], capture_output=True)
    return res.returncode == 0


def test_on_a_real_full_tmpfs_the_old_mesh_survives(tmp_path, capsys):
    """Reproduction 2 of issue 53 on a real file system, where this process may mount a tmpfs (root)."""
    from plad.serve.cli import main

    disk = tmp_path / "T"
    disk.mkdir()
    if not _can_mount_tmpfs(disk):
        pytest.skip("cannot mount a tmpfs here (not root, or no mount permission); the simulated full disk "
                    "tests cover the same")
    try:
        old = disk / "old.ply"
        assert main(["execute", "csg3d", "cuboid 16 16 16 4 4 4", "-o", str(old)]) == 0
        before = old.read_bytes()
        free = os.statvfs(disk).f_bavail * os.statvfs(disk).f_frsize
        (disk / "filler").write_bytes(b"\0" * free)
        capsys.readouterr()
        assert main(["execute", "csg3d", "union cuboid 16 16 22 26 26 4 union cuboid 8 8 11 4 4 18 ellipsoid 24 24 "
                     "11 8 8 18", "-o", str(old)]) == 2
        assert capsys.readouterr().err == f"plad: error: {old}: cannot write (No space left on device)\n"
        assert old.read_bytes() == before and sorted(p.name for p in disk.iterdir()) == ["filler", "old.ply"]
    finally:
        subprocess.run(["umount", str(disk)], capture_output=True)
