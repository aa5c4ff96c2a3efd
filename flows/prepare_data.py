"""Prefect flow: verify and pack the real target shapes (the DVC stage ``prepare``).

    python -m flows.prepare_data --params params.yaml

Use it to re-run data preparation when new shapes arrive, on a schedule or
by hand; it calls :func:`plad.stages.prepare.prepare`, the same function as
the DVC stage.
"""
from __future__ import annotations

import argparse

from prefect import flow, task

from plad.config import load_params, section
from plad.stages.prepare import PrepareConfig, prepare


@task(retries=1, retry_delay_seconds=5)
def prepare_domain(cfg: PrepareConfig, domain: str) -> dict:
    single = PrepareConfig(data_dir=cfg.data_dir, domains=[domain], out_dir=cfg.out_dir)
    return prepare(single)[domain]


@flow(name="plad-prepare-data")
def prepare_data(params_path: str = "params.yaml") -> dict[str, dict]:
    cfg = section(load_params(params_path), "prepare", PrepareConfig, source=params_path)
    futures = {d: prepare_domain.submit(cfg, d) for d in cfg.domains}
    return {d: f.result() for d, f in futures.items()}


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    print(prepare_data(parser.parse_args().params))
