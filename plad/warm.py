"""Opt-in warm runner for stage commands: ``python -m MODULE ARGS`` forked from a server that has torch
and MLflow imported already (a stage process otherwise spends about 3 s of CPU importing them).

Not used unless asked for: ``python -m plad.warm shim DIR`` writes ``DIR/python``, a shell script that
sends ``python -m plad.stages.<stage> ...`` here and runs anything else with the real interpreter; put
``DIR`` first on the ``PATH`` of ``dvc repro`` / ``dvc exp run`` (dvc.yaml's commands stay ``python -m
...``, so the stages, their deps and dvc.lock do not change)::

    python -m plad.warm shim .warm-bin
    PATH="$PWD/.warm-bin:$PATH" dvc exp run --temp -S profile=smoke

How it works. The client (``python -m plad.warm -m MODULE ARGS``) connects to a unix socket named by
a hash of the interpreter, ``sys.path`` and the environment variables read at import time
(:func:`server_key`), starting the server on first use. It sends its argv, working directory,
``sys.path``, environment and umask, and its stdin/stdout/stderr file descriptors (SCM_RIGHTS). The
server forks a handler per request, which forks the stage: the stage process takes over the
descriptors, the directory, the environment and ``sys.path``, drops any ``plad`` module the server
had imported (the project's code is always read fresh), and runs MODULE as ``__main__``
(:func:`runpy.run_module`) and then the ``atexit`` handlers, as ``python -m`` would. The handler
reports the stage's pid (the client forwards SIGINT/SIGTERM/SIGHUP to it) and its exit status, which
the client exits with (a signal death: the client kills itself with the same signal). A client that
goes away (killed) takes its stage with it. The server exits after ``$PLAD_WARM_IDLE`` seconds
(default 120) without a request. If the server cannot be reached or started, the client runs the
command cold (``exec python -m MODULE ARGS``) after a one-line warning.

What differs from a cold ``python -m``: MLflow's telemetry is off in the server (its thread would not
survive the fork), interpreter flags (``-X``, ``-u``, ...) of the client are not passed on, and the
modules of :data:`PRELOAD` are imported before the environment of the request is set (so the
variables they read on import are part of the server's key).
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import select
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: imported by the server before it forks (the bulk of a stage's start-up: torch, MLflow and what
#: starting an MLflow run imports: the SQLite store, the notebook and git context providers)
PRELOAD = ("torch", "mlflow", "mlflow.store.tracking.sqlalchemy_store", "IPython", "git")
#: environment variables that the preloaded modules may read on import: part of the server's key
KEY_PREFIXES = ("OMP_", "MKL_", "OPENBLAS_", "TORCH", "PYTORCH", "CUDA", "MLFLOW_", "PYTHON", "PLAD_WARM")
FORWARDED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
_HEADER = struct.Struct("!I")


# -- where the server listens -----------------------------------------------------------------------
def socket_dir() -> Path:
    """``$PLAD_WARM_DIR``, else a private folder of this user under the temporary directory."""
    folder = Path(os.environ.get("PLAD_WARM_DIR") or Path(tempfile.gettempdir()) / f"plad-warm-{os.getuid()}")
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    if folder.stat().st_uid != os.getuid():
        raise OSError(f"{folder}: not owned by this user")
    return folder


def server_key() -> str:
    """What a server's preloaded state depends on: the interpreter, sys.path, import-time environment."""
    env = {k: v for k, v in os.environ.items() if k.startswith(KEY_PREFIXES)}
    blob = json.dumps([sys.executable, sys.version, sys.path, sorted(env.items())])
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def socket_path() -> Path:
    return socket_dir() / f"{server_key()}.sock"


# -- framing ----------------------------------------------------------------------------------------
def _recv_exact(conn: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = conn.recv(n - len(data))
        if not chunk:
            raise ConnectionError("connection closed")
        data += chunk
    return data


def _send_request(conn: socket.socket, request: dict) -> None:
    body = json.dumps(request).encode()
    socket.send_fds(conn, [_HEADER.pack(len(body))], [0, 1, 2])
    conn.sendall(body)


def _recv_request(conn: socket.socket) -> tuple[dict, list[int]]:
    head, fds, _, _ = socket.recv_fds(conn, _HEADER.size, 3)
    if len(head) < _HEADER.size:
        head += _recv_exact(conn, _HEADER.size - len(head))
    if len(fds) != 3:
        for fd in fds:
            os.close(fd)
        raise ConnectionError(f"expected 3 file descriptors, got {len(fds)}")
    return json.loads(_recv_exact(conn, _HEADER.unpack(head)[0])), fds


# -- server -----------------------------------------------------------------------------------------
def serve(path: Path, idle: float) -> None:
    """Listen at ``path``, preload, then fork a handler per request; exit after ``idle`` quiet seconds."""
    os.environ["MLFLOW_DISABLE_TELEMETRY"] = "true"   # its thread would not survive the fork
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    tmp = path.with_name(f"{path.name}.{os.getpid()}")
    listener.bind(str(tmp))
    listener.listen(64)
    os.replace(tmp, path)          # clients see the socket only once it listens
    inode = path.stat().st_ino
    for name in PRELOAD:           # requests queue in the backlog meanwhile
        with contextlib.suppress(ImportError):
            __import__(name)
    listener.settimeout(1.0)
    handlers: set[int] = set()
    served = 0
    last = time.monotonic()
    while True:
        try:
            conn, _ = listener.accept()
        except TimeoutError:
            conn = None
        while handlers:            # reap finished handlers
            pid, _ = os.waitpid(-1, os.WNOHANG)
            if pid == 0:
                break
            handlers.discard(pid)
        if conn is None:
            try:
                ours = path.stat().st_ino == inode
            except OSError:
                ours = False
            if not ours or (not handlers and time.monotonic() - last > idle):
                if ours:
                    with contextlib.suppress(OSError):
                        path.unlink()
                _log_usage(served)
                return
            continue
        last = time.monotonic()
        served += 1
        conn.settimeout(None)
        try:
            request, fds = _recv_request(conn)
        except (OSError, ValueError):
            conn.close()
            continue
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        pid = os.fork()
        if pid == 0:
            listener.close()
            _handle(conn, request, fds)   # never returns
        handlers.add(pid)
        conn.close()
        for fd in fds:
            os.close(fd)


def _log_usage(served: int) -> None:
    """One line on the server's log: requests served and the CPU of the server and its stages."""
    import resource

    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    print(f"plad.warm: exiting after {served} requests; CPU user {me.ru_utime + kids.ru_utime:.2f} s "
          f"sys {me.ru_stime + kids.ru_stime:.2f} s (server {me.ru_utime + me.ru_stime:.2f} s)",
          file=sys.stderr, flush=True)


def _handle(conn: socket.socket, request: dict, fds: list[int]) -> None:
    """The handler process: fork the stage, report its pid and exit status; kill it if the client goes."""
    code = 1
    try:
        pid = os.fork()
        if pid == 0:
            conn.close()
            _run_stage(request, fds)      # never returns
        for fd in fds:
            os.close(fd)
        conn.sendall(b"P" + struct.pack("!q", pid))
        pidfd = os.pidfd_open(pid)
        while True:
            ready, _, _ = select.select([pidfd, conn], [], [])
            if pidfd in ready:
                break
            if not conn.recv(64):         # the client is gone: so is its stage
                os.kill(pid, signal.SIGTERM)
                deadline = time.monotonic() + 10
                while time.monotonic() < deadline and not select.select([pidfd], [], [], 0.5)[0]:
                    pass
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
                break
        _, status = os.waitpid(pid, 0)
        with contextlib.suppress(OSError):
            conn.sendall(b"X" + struct.pack("!i", os.waitstatus_to_exitcode(status)))
        code = 0
    finally:
        os._exit(code)


def _run_stage(request: dict, fds: list[int]) -> None:
    """The stage process: become the client's ``python -m MODULE ARGS`` and exit as it would."""
    import atexit
    import runpy
    import traceback

    code: int = 1
    try:
        for sig in FORWARDED:
            signal.signal(sig, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        for new, fd in enumerate(fds):
            os.dup2(fd, new)
            os.close(fd)
        sys.stdout.reconfigure(line_buffering=os.isatty(1))
        os.chdir(request["cwd"])
        os.umask(request["umask"])
        os.environ.clear()
        os.environ.update(request["env"])
        sys.path[:] = request["path"]
        sys.orig_argv = request["orig_argv"]
        for name in [m for m in sys.modules if m == "plad" or m.startswith("plad.")]:
            del sys.modules[name]     # the project's code as the client's sys.path has it, not the server's
        module, args = request["module"], request["args"]
        sys.argv = [module, *args]
        try:
            runpy.run_module(module, run_name="__main__", alter_sys=True)
            code = 0
        except SystemExit as exc:
            if exc.code is None:
                code = 0
            elif isinstance(exc.code, int):
                code = exc.code
            else:
                print(exc.code, file=sys.stderr)
                code = 1
        except KeyboardInterrupt:
            traceback.print_exc()
            code = -signal.SIGINT
        except BaseException:        # what the interpreter would print, and its exit status
            traceback.print_exc()
            code = 1
        atexit._run_exitfuncs()
    finally:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        if code < 0:                 # die of the signal, as python does on an uncaught KeyboardInterrupt
            _die_of(-code)
        os._exit(code & 0xFF)


def _die_of(sig: int) -> None:
    """End this process by signal ``sig`` with its default action (the forwarded ones reset first)."""
    for forwarded in FORWARDED:
        signal.signal(forwarded, signal.SIG_DFL)
    signal.signal(sig, signal.SIG_DFL)
    os.kill(os.getpid(), sig)


# -- client -----------------------------------------------------------------------------------------
def _connect(path: Path) -> socket.socket:
    conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        conn.connect(str(path))
    except OSError:
        conn.close()
        raise
    return conn


def connect_or_start(path: Path, wait: float = 30.0) -> socket.socket:
    """A connection to the server at ``path``, starting one (one at a time: a lock file) if none answers."""
    import fcntl

    with contextlib.suppress(OSError):
        return _connect(path)
    with open(path.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        with contextlib.suppress(OSError):
            return _connect(path)    # another client started it meanwhile
        with contextlib.suppress(FileNotFoundError):
            path.unlink()            # a stale socket of a dead server
        log = open(path.with_suffix(".log"), "ab")
        subprocess.Popen([sys.executable, "-m", "plad.warm", "serve", str(path)], stdin=subprocess.DEVNULL,
                         stdout=log, stderr=log, start_new_session=True, close_fds=True)
        log.close()
        deadline = time.monotonic() + wait
        while True:
            try:
                return _connect(path)
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.02)


def run(module: str, args: list[str]) -> int:
    """Run ``python -m module args`` in the warm server; its exit code (negative: killed by that signal)."""
    conn = connect_or_start(socket_path())
    umask = os.umask(0)
    os.umask(umask)
    _send_request(conn, {"module": module, "args": args, "cwd": os.getcwd(), "path": sys.path,
                         "env": dict(os.environ), "umask": umask,
                         "orig_argv": [sys.executable, "-m", module, *args]})
    stage = {"pid": None}

    def forward(sig, _frame):
        if stage["pid"] is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(stage["pid"], sig)

    for sig in FORWARDED:
        signal.signal(sig, forward)
    while True:
        try:
            kind = _recv_exact(conn, 1)
        except ConnectionError:
            print(f"plad.warm: lost the warm server while running {module}", file=sys.stderr)
            return 1
        if kind == b"P":
            stage["pid"] = struct.unpack("!q", _recv_exact(conn, 8))[0]
        elif kind == b"X":
            return struct.unpack("!i", _recv_exact(conn, 4))[0]
        else:
            print(f"plad.warm: unexpected reply {kind!r} from the warm server", file=sys.stderr)
            return 1


def write_shim(folder: Path) -> Path:
    """``folder/python``: ``python -m plad.stages.* ...`` through the warm runner, anything else unchanged."""
    from plad.fsutil import atomic_write_text

    real = sys.executable
    text = ("#!/bin/sh\n"
            "# written by `python -m plad.warm shim`: stage commands through the warm runner (plad/warm.py)\n"
            f'case "$1 $2" in\n  "-m plad.stages."*) exec "{real}" -m plad.warm "$@" ;;\nesac\n'
            f'exec "{real}" "$@"\n')
    return atomic_write_text(folder / "python", text, mode=0o755)


def main(argv: list[str]) -> int:
    if len(argv) >= 2 and argv[0] == "-m":
        module, args = argv[1], argv[2:]
        try:
            code = run(module, args)
        except OSError as err:   # no server: run cold, as the command would without the shim
            print(f"plad.warm: no warm server ({err}); running {module} cold", file=sys.stderr)
            os.execv(sys.executable, [sys.executable, "-m", module, *args])
        if code < 0:
            _die_of(-code)
        return code
    if len(argv) == 2 and argv[0] == "serve":
        serve(Path(argv[1]), float(os.environ.get("PLAD_WARM_IDLE", "120")))
        return 0
    if len(argv) == 2 and argv[0] == "shim":
        print(write_shim(Path(argv[1])))
        return 0
    print("usage: python -m plad.warm -m MODULE [ARGS...] | serve SOCKET | shim DIR", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
