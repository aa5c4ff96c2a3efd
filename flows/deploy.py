"""Deploy the fine-tuning flow to a Prefect work pool, where workers on the training machines run it.

    python -m flows.deploy --pool plad [--name plad-pool] [--params params.yaml] [--profile smoke]
                           [--methods lest_st st] [--root DIR] [--cron "0 3 * * 0"] [--source /path/seen/by/workers]

``flows.finetune --serve`` runs the flow in the serving process; here a Prefect
server keeps the deployment and hands its runs to a work pool, whose process
workers start each run in a new process, on whichever machine they run::

    prefect server start --host 0.0.0.0                      # the orchestration machine; PREFECT_API_URL elsewhere
    python -m flows.deploy --pool plad --profile cpu          # creates the pool (type process) if needed
    prefect worker start --pool plad                          # on each training machine, any folder
    prefect deployment run plad-finetune/plad-pool -p profile=paper -p 'methods=["st", "rl"]'

The deployment's code is the repository folder ``--source`` (default: this
checkout) at the same path on the workers: its pull step only sets the working
directory, so nothing is cloned or downloaded, and the layout root
(:mod:`plad.layout`: the prepared data and pretrained model a run starts from,
its outputs under ``runs/flows/<run name>/``) is the repository unless
``--root`` names another folder the workers see. The deployment's default
parameters are ``--params`` (the params file, relative to the repository),
``--profile`` (the override file ``profiles/<profile>.yaml`` applied on top of
it, replacing the file's own ``profile`` key), ``--methods`` and ``--root``; a
run may override ``params_path``, ``profile``, ``methods``, ``root`` and
``run_name``. ``--env KEY=VALUE`` adds environment variables to every run (e.g.
``MLFLOW_TRACKING_URI`` of a shared tracking server).
"""
from __future__ import annotations

import argparse
from pathlib import Path
from uuid import UUID

REPO_ROOT = Path(__file__).resolve().parent.parent
ENTRYPOINT = "flows/finetune.py:finetune_flow"


def ensure_pool(pool: str) -> None:
    """Create the process work pool ``pool`` unless it exists."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.actions import WorkPoolCreate
    from prefect.exceptions import ObjectNotFound

    with get_client(sync_client=True) as client:
        try:
            client.read_work_pool(pool)
        except ObjectNotFound:
            client.create_work_pool(WorkPoolCreate(name=pool, type="process"))


def deploy(pool: str, name: str = "plad-pool", *, profile: str | None = None, params_path: str = "params.yaml",
           methods: list[str] | None = None, root: str | None = None, cron: str | None = None,
           source: str | Path = REPO_ROOT, env: dict[str, str] | None = None) -> UUID:
    """Register the deployment ``plad-finetune/<name>`` on work pool ``pool``; its id."""
    from flows.finetune import finetune_flow

    ensure_pool(pool)
    parameters: dict = {"params_path": params_path}
    if profile:
        parameters["profile"] = profile
    if methods:
        parameters["methods"] = list(methods)
    if root:
        parameters["root"] = str(root)
    flow = finetune_flow.from_source(source=str(Path(source).resolve()), entrypoint=ENTRYPOINT)
    return flow.deploy(name=name, work_pool_name=pool, parameters=parameters, cron=cron,
                       job_variables={"env": dict(env)} if env else None, build=False, push=False,
                       print_next_steps=False)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m flows.deploy", description=__doc__.splitlines()[0])
    parser.add_argument("--pool", required=True, help="work pool (created as a process pool if missing)")
    parser.add_argument("--name", default="plad-pool", help="deployment name (default: plad-pool)")
    parser.add_argument("--params", default="params.yaml", help="params file, relative to the repository")
    parser.add_argument("--profile", help="apply profiles/<PROFILE>.yaml on top of the params (smoke, cpu, paper)")
    parser.add_argument("--methods", nargs="*", help="finetune.methods keys (default: flows.methods, else all)")
    parser.add_argument("--root", help="layout root of the runs, as the workers see it (default: the repository)")
    parser.add_argument("--cron", help="schedule of the runs (default: none; trigger runs by hand)")
    parser.add_argument("--source", default=str(REPO_ROOT), help="the repository folder as the workers see it")
    parser.add_argument("--env", action="append", default=[], metavar="KEY=VALUE",
                        help="environment variable of every run (repeatable)")
    args = parser.parse_args(argv)
    bad = [e for e in args.env if "=" not in e]
    if bad:
        parser.error(f"--env {bad[0]!r}: expected KEY=VALUE")
    env = dict(e.split("=", 1) for e in args.env)
    deployment_id = deploy(args.pool, args.name, profile=args.profile, params_path=args.params,
                           methods=args.methods, root=args.root, cron=args.cron, source=args.source, env=env)
    print(f"deployment plad-finetune/{args.name} ({deployment_id}) on work pool {args.pool}")


if __name__ == "__main__":
    main()
