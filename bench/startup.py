"""Start-up time of the ``plad`` command against a bare Python start, measured in the same run.

Usage: ``python -m bench.startup [--repeats N] [--command "models"]``

Each timing is a fresh interpreter (this one's executable, this checkout first on the path):
ours runs ``plad --help`` (the CLI's ``main``, as the installed ``plad`` script does), the
baseline ``python -c "import argparse"``. The two alternate, N times each, and the best time
of each counts (the least disturbed by other work on the machine); the median is printed too.
The last line is ``ratio <ours/baseline>`` (time, lower is better; the target is at most 10).
"""
from __future__ import annotations

import argparse
import os
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def _time(cmd: list[str], env: dict[str, str]) -> float:
    start = time.perf_counter()
    subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--command", default="--help", help="the plad arguments timed (default: --help)")
    args = parser.parse_args(argv)
    path = [str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(path)}
    ours_cmd = [sys.executable, "-c", "import sys; from plad.serve.cli import main; sys.exit(main())",
                *shlex.split(args.command)]
    base_cmd = [sys.executable, "-c", "import argparse"]
    _time(ours_cmd, env), _time(base_cmd, env)   # warm the file cache
    ours, base = [], []
    for _ in range(args.repeats):
        ours.append(_time(ours_cmd, env))
        base.append(_time(base_cmd, env))
    print(f"plad {args.command}: best {min(ours) * 1000:.0f} ms, median {statistics.median(ours) * 1000:.0f} ms "
          f"({args.repeats} runs)")
    print(f"python -c 'import argparse': best {min(base) * 1000:.0f} ms, "
          f"median {statistics.median(base) * 1000:.0f} ms")
    print(f"load average {os.getloadavg()[0]:.1f}")
    print(f"ratio {min(ours) / min(base):.2f}")


if __name__ == "__main__":
    main()
