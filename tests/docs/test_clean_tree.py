"""The documented commands leave a clean tree (issue 54): what the README's Quick start writes in the
repository's folder (`plad infer --out inferred`, `plad execute ... -o gear.png`) and what the documented flow
writes (`python -m flows.finetune --profile smoke --run-name try`: runs/flows/try/) is ignored by git. The paths
are read from the docs and the layout, and checked with `git check-ignore` (nothing is run)."""
from __future__ import annotations

import re
import shutil
import subprocess

import pytest

from plad.layout import Layout
from tests.conftest import REPO_ROOT as REPO


def quick_start_outputs() -> list[str]:
    """The files and folders the Quick start's commands write (their --out and -o), relative to the root."""
    readme = (REPO / "README.md").read_text()
    start = readme.index("\n## Quick start\n")
    block = re.search(r"^```bash\n(.*?)^```", readme[start:], re.M | re.S).group(1)
    commands = [line.split("#")[0] for line in block.splitlines() if line.startswith("plad ")]
    outs = [m.group(1) for c in commands for m in re.finditer(r"(?:--out|-o)\s+(\S+)", c)]
    assert "gear.png" in outs and "inferred" in outs, commands
    return sorted(set(outs))


def flow_outputs() -> list[str]:
    """What docs/pipeline.md's `--run-name try` flow writes: its run's layout root (plad.layout)."""
    assert "python -m flows.finetune --profile smoke --run-name try" in (REPO / "docs" / "pipeline.md").read_text()
    return [Layout(REPO).flow_run("try").root.relative_to(REPO).as_posix()]


def test_what_the_documented_commands_write_is_ignored():
    if shutil.which("git") is None or not (REPO / ".git").exists():
        pytest.skip("not a git checkout")
    # as the commands write them: a file (-o), a run's folder under --out, the flow run's layout
    paths = [out if "." in out else f"{out}/20260101-000000-1/results.csv" for out in quick_start_outputs()]
    paths += [f"{root}/{inside}" for root in flow_outputs()
              for inside in ("runs/finetune/csg2d/lest_st/best.pt", "results/eval/lest_st/csg2d/metrics.json")]
    res = subprocess.run(["git", "check-ignore", "--no-index", "--verbose", "--non-matching", *paths], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    not_ignored = [line.split("\t", 1)[1] for line in res.stdout.splitlines() if line.startswith("::")]
    assert not_ignored == [] and res.returncode == 0, res.stdout + res.stderr
    # and no more: the README's tracked picture and the example named like the Quick start's output stay tracked
    kept = subprocess.run(["git", "check-ignore", "--no-index", "results/infer/bracket_refined/bracket.png",
                           "examples/csg2d/gear.png"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert kept.returncode == 1 and kept.stdout == "", kept.stdout
