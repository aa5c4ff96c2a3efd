"""One rank of the distributed tests, started by torchrun: runs stages' ``main`` and records for the test
the weights after every optimizer step and what this process wrote.

    torchrun ... -m tests.distributed_worker RECORD_DIR STAGE [stage arguments] [:: STAGE [arguments] ...]

(as a module: run as a script, its folder ``tests/`` would come first on ``sys.path`` and ``tests/plad/``
would shadow the package ``plad``).

Runs the stage commands one after the other (one launch costs seconds of
imports) and writes ``RECORD_DIR/rank<RANK>.json``, a list with one record
per command: ``steps`` (a digest of the stepped parameters after each
optimizer step), ``writes`` (files under ``$PLAD_TEST_WATCH`` opened for
writing, renamed onto or removed) and ``sqlite`` (databases this process
connected to: MLflow's store).
"""
from __future__ import annotations

import hashlib
import importlib
import json
import os
import sys
from pathlib import Path

import torch
from torch.optim.optimizer import register_optimizer_step_post_hook

WATCH = os.environ["PLAD_TEST_WATCH"]
records: list[dict[str, list[str]]] = []
record: dict[str, list[str]] = {}


def _under_watch(path) -> str | None:
    if isinstance(path, bytes):
        path = path.decode(errors="replace")
    if isinstance(path, (str, os.PathLike)):
        path = os.path.abspath(path)
        return path if path.startswith(WATCH) else None
    return None


def audit(event: str, args: tuple) -> None:
    if event == "open":
        path, mode, flags = args
        writing = any(c in mode for c in "wax+") if isinstance(mode, str) else \
            bool(flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT))
        if writing and (p := _under_watch(path)):
            record["writes"].append(p)
    elif event in ("os.rename", "os.remove", "shutil.rmtree"):
        target = args[1] if event == "os.rename" else args[0]
        if p := _under_watch(target):
            record["writes"].append(p)
    elif event == "sqlite3.connect":
        record["sqlite"].append(str(args[0]))


def after_step(optimizer, args, kwargs) -> None:
    h = hashlib.sha256()
    for group in optimizer.param_groups:
        for p in group["params"]:
            h.update(p.detach().cpu().numpy().tobytes())
    record["steps"].append(h.hexdigest())


def main() -> int:
    out, *rest = sys.argv[1:]
    torch.set_num_threads(1)
    sys.addaudithook(audit)
    register_optimizer_step_post_hook(after_step)
    commands = " ".join(rest).split(" :: ")
    for command in commands:
        stage, *stage_args = command.split()
        record.clear()
        record.update(steps=[], writes=[], sqlite=[])
        status = importlib.import_module(f"plad.stages.{stage}").main(stage_args)
        records.append(dict(record))
        if status:
            return status
    Path(out, f"rank{os.environ['RANK']}.json").write_text(json.dumps(records))
    return 0


if __name__ == "__main__":
    sys.exit(main())
