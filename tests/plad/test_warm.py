"""The opt-in warm stage runner (plad/warm.py): a command run through it behaves as ``python -m`` does."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import REPO_ROOT

PROBE = """\
import os, sys
print("torch preloaded" if "torch" in sys.modules else "cold", sys.argv[1:], os.getcwd(), os.environ.get("PROBE"))
print("stdin:", sys.stdin.read().strip())
print("to stderr", file=sys.stderr)
import atexit
atexit.register(lambda: print("atexit ran"))
sys.exit(int(os.environ.get("PROBE_CODE", "0")))
"""


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    folder = tmp_path_factory.mktemp("warm")
    (folder / "probe.py").write_text(PROBE)
    (folder / "sleeper.py").write_text("import os, time\nprint(os.getpid(), flush=True)\ntime.sleep(60)\n")
    (folder / "boom.py").write_text("raise ValueError('boom')\n")
    e = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "PLAD_WARM_DIR": str(folder / "sock"), "PLAD_WARM_IDLE": "20"}
    e.pop("PROBE", None)
    yield folder, e
    for sock in (folder / "sock").glob("*.sock"):   # end the server: it exits when its socket goes
        sock.unlink()


def warm(folder, env, *args, stdin="", extra=None):
    return subprocess.run([sys.executable, "-m", "plad.warm", "-m", *args], cwd=folder, input=stdin,
                          capture_output=True, text=True, env={**env, **(extra or {})}, timeout=120)


def test_a_command_runs_as_python_m_would_in_a_preloaded_process(env):
    folder, e = env
    out = warm(folder, e, "probe", "a", "b c", stdin="hello\n", extra={"PROBE": "x", "PROBE_CODE": "3"})
    assert out.returncode == 3
    assert out.stdout.splitlines() == [f"torch preloaded ['a', 'b c'] {folder} x", "stdin: hello", "atexit ran"]
    assert out.stderr == "to stderr\n"
    # the next request's environment replaces the previous one's (same server: the socket is reused)
    again = warm(folder, e, "probe", stdin="again")
    assert again.returncode == 0
    assert again.stdout.splitlines()[:2] == [f"torch preloaded [] {folder} None", "stdin: again"]
    assert len(list((folder / "sock").glob("*.sock"))) == 1


def test_an_uncaught_exception_prints_its_traceback_and_exits_1(env):
    folder, e = env
    out = warm(folder, e, "boom")
    assert out.returncode == 1
    assert out.stderr.strip().endswith("ValueError: boom")


def gone(pid: int, wait: float = 15.0) -> bool:
    deadline = time.monotonic() + wait
    while time.monotonic() < deadline:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
        except OSError:
            return True
        if state == "Z":   # dead, not yet reaped by its handler
            return True
        time.sleep(0.1)
    return False


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_to_the_client_reaches_the_stage_and_the_client_dies_of_it(env, sig):
    folder, e = env
    proc = subprocess.Popen([sys.executable, "-m", "plad.warm", "-m", "sleeper"], cwd=folder, env=e,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    stage = int(proc.stdout.readline())   # the stage runs, in a process of the server
    assert stage != proc.pid
    proc.send_signal(sig)
    assert proc.wait(timeout=30) == -sig
    assert gone(stage)


def test_a_killed_client_takes_its_stage_with_it(env):
    folder, e = env
    proc = subprocess.Popen([sys.executable, "-m", "plad.warm", "-m", "sleeper"], cwd=folder, env=e,
                            stdout=subprocess.PIPE, text=True)
    stage = int(proc.stdout.readline())
    proc.kill()
    proc.wait(timeout=30)
    assert gone(stage)


def test_the_server_exits_when_idle_and_logs_its_cpu(env):
    folder, e = env
    e = {**e, "PLAD_WARM_IDLE": "1"}   # another key: a server of its own
    assert warm(folder, e, "probe").returncode == 0
    socks = folder / "sock"
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and any(
            "exiting after" in p.read_text() for p in socks.glob("*.log")) is False:
        time.sleep(0.2)
    assert any("exiting after 1 requests; CPU user" in p.read_text() for p in socks.glob("*.log"))


def test_without_a_usable_socket_folder_the_command_runs_cold(env, tmp_path):
    folder, e = env
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("")
    out = warm(folder, e, "probe", stdin="x", extra={"PLAD_WARM_DIR": str(blocker / "sock")})
    assert out.returncode == 0
    assert out.stdout.startswith("cold ")
    assert "running probe cold" in out.stderr


def test_the_shim_routes_only_stage_modules(tmp_path):
    shim = tmp_path / "bin" / "python"
    subprocess.run([sys.executable, "-m", "plad.warm", "shim", str(shim.parent)], check=True,
                   env={**os.environ, "PYTHONPATH": str(REPO_ROOT)}, capture_output=True)
    text = shim.read_text()
    assert f'exec "{sys.executable}" -m plad.warm "$@"' in text
    out = subprocess.run([str(shim), "-c", "import sys; print(sys.executable)"], capture_output=True, text=True)
    assert out.stdout.strip() == sys.executable
