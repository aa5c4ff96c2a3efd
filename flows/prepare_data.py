"""Prefect flow: verify and pack the real target shapes (the DVC stage ``prepare``).

    python -m flows.prepare_data --params params.yaml

Use it to re-run data preparation when new shapes arrive, on a schedule or
by hand; it calls :func:`plad.stages.prepare.prepare`, the same function as
the DVC stage, once per target source (domains on the same source share one
task, so a source is built once).
"""
from __future__ import annotations

import argparse
import sys

from prefect import flow, task

from flows import one_line_errors
from plad.config import load_params, section
from plad.errors import run_guarded
from plad.layout import Layout
from plad.stages.prepare import PrepareConfig, prepare, prepare_sources


@task(retries=1, retry_delay_seconds=5)
def prepare_source(cfg: PrepareConfig, layout: Layout) -> dict[str, dict]:
    return prepare(cfg, layout)


@flow(name="plad-prepare-data")
def prepare_data(params_path: str = "params.yaml", root: str = ".") -> dict[str, dict]:
    """``root``: the layout root the prepared files are written under (:mod:`plad.layout`)."""
    cfg = section(load_params(params_path), "prepare", PrepareConfig)
    futures = [prepare_source.submit(part, Layout(root)) for part in prepare_sources(cfg)]
    out: dict[str, dict] = {"domains": {}, "sources": {}}
    for f in futures:
        for key, value in f.result().items():
            out[key].update(value)
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--root", default=".",
                        help="root folder of the artifacts (plad.layout; default: the working directory)")
    args = parser.parse_args()
    one_line_errors()

    def go() -> None:
        section(load_params(args.params), "prepare", PrepareConfig)   # a bad params file: before Prefect starts
        print(prepare_data(args.params, args.root))

    # the exit statuses of plad.errors: a params or data problem is one line and status 1
    sys.exit(run_guarded("flows.prepare_data", go))
