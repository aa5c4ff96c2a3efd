"""plad.fsutil.file_lock: exclusive and shared flock between holders (threads here: flock excludes
separately opened descriptors as it excludes processes), and the unlocked fallback."""
from __future__ import annotations

import threading

from plad.fsutil import file_lock


def holder(path, shared: bool, events: list[str], name: str) -> threading.Thread:
    def hold() -> None:
        with file_lock(path, shared=shared) as held:
            events.append(f"{name} {held}")
    thread = threading.Thread(target=hold)
    thread.start()
    return thread


def test_an_exclusive_lock_waits_for_the_holder_and_shared_ones_do_not_wait_for_each_other(tmp_path):
    lock = tmp_path / "x.lock"
    events: list[str] = []
    with file_lock(lock) as held:
        assert held and lock.is_file()
        waiting = [holder(lock, False, events, "exclusive"), holder(lock, True, events, "shared")]
        for thread in waiting:
            thread.join(0.5)
        assert events == [] and all(t.is_alive() for t in waiting)
    for thread in waiting:
        thread.join(10)
    assert sorted(events) == ["exclusive True", "shared True"]

    events.clear()
    with file_lock(lock, shared=True):
        other = holder(lock, True, events, "shared")
        other.join(10)
        assert events == ["shared True"]   # taken while this shared lock is held
        blocked = holder(lock, False, events, "exclusive")
        blocked.join(0.5)
        assert blocked.is_alive()
    blocked.join(10)
    assert events == ["shared True", "exclusive True"]


def test_without_a_lock_file_to_open_the_block_runs_unlocked(tmp_path):
    with file_lock(tmp_path / "absent.lock", shared=True, create=False) as held:
        assert held is False
    assert list(tmp_path.iterdir()) == []
    with file_lock(tmp_path / "no" / "such" / "folder.lock") as held:
        assert held is False


def test_savez_writes_the_same_bytes_whatever_the_clock(monkeypatch):
    """A rebuilt output must have the bytes DVC recorded, whatever the clock and the numpy version (numpy 1.x
    stamped each member with the time of writing); numpy.load reads it back."""
    import io
    import time

    import numpy as np

    from plad.fsutil import savez

    arrays = {"train": np.packbits(np.eye(9, dtype=bool), axis=1), "shape": np.asarray([3, 3]),
              "name": np.asarray("csg2d")}

    def written(write, clock):
        monkeypatch.setattr(time, "time", lambda: clock)
        buf = io.BytesIO()
        write(buf, **arrays)
        return buf.getvalue()

    assert written(savez, 1.0e9) == written(savez, 1.7e9)
    with np.load(io.BytesIO(written(savez, 1.0e9))) as z:
        assert sorted(z.files) == ["name", "shape", "train"]
        assert all(np.array_equal(z[k], v) for k, v in arrays.items())
