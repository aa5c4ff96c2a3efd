"""The wheel holds what the code loads (issue 54): built from a clean copy of the tree, installed into a fresh
virtual environment that cannot see the editable install, it lists all six shipped networks (`plad models`)
and infers in every domain (`plad infer --no-refine`), run from a folder outside the repository.

The virtual environment has no site packages of its own but the wheel; the dependencies already installed
here reach it through a ``.pth`` file naming this interpreter's site-packages folders. A folder named in a
``.pth`` file is only added to ``sys.path``: the ``.pth`` files inside it (the editable install's finder among
them) are not run, so ``import plad`` can only find the installed wheel (asserted). Nothing is downloaded
(``pip --no-index``, ``--no-build-isolation``: the build uses the setuptools installed here)."""
from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from tests.conftest import REPO_ROOT, under_ci

pytestmark = pytest.mark.integration

DOMAINS = ("csg2d", "csg3d", "shapeassembly")
#: one example input per domain (examples/README.md)
EXAMPLES = {"csg2d": "examples/csg2d/bracket.png", "csg3d": "examples/csg3d/stool.npy",
            "shapeassembly": "examples/shapeassembly/chair.npy"}


def _skip_or_fail(message: str):
    if under_ci():
        pytest.fail(f"CI=true and {message}")
    pytest.skip(message)


def clean_tree(dest: Path) -> Path:
    """The files a clean clone of this checkout would have (tracked, and untracked but not ignored: what the
    next commit holds), copied to ``dest``: no build/, no *.egg-info, no run outputs."""
    try:
        listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                                cwd=REPO_ROOT, capture_output=True, check=True, timeout=60).stdout
    except (OSError, subprocess.SubprocessError) as err:
        _skip_or_fail(f"the checkout's files cannot be listed with git ({err})")
    for name in sorted(set(listed.decode().split("\0")) - {""}):
        source = REPO_ROOT / name
        if source.is_file():   # a tracked file deleted in the working tree is not in the next commit
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, dest / name)
    return dest


def clean_env(**extra: str) -> dict[str, str]:
    """This environment without what would point Python or PLAD at the checkout or its stores."""
    drop = {"PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP", "PLAD_SHIPPED_DIR", "MLFLOW_TRACKING_URI", "VIRTUAL_ENV"}
    env = {k: v for k, v in os.environ.items() if k not in drop and not k.startswith("PIP_")}
    # no user site-packages either: its .pth files would run (an editable install may live there)
    env.update(PYTHONNOUSERSITE="1", PIP_DISABLE_PIP_VERSION_CHECK="1", PIP_NO_INPUT="1", OMP_NUM_THREADS="1",
               **extra)
    return env


def run(cmd: list[str], cwd: Path, timeout: float, **env: str) -> subprocess.CompletedProcess:
    res = subprocess.run([str(c) for c in cmd], cwd=cwd, env=clean_env(**env), capture_output=True, text=True,
                         timeout=timeout)
    assert res.returncode == 0, f"{' '.join(map(str, cmd))}: exit status {res.returncode}\n{res.stdout}\n{res.stderr}"
    return res


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> dict[str, Path]:
    """The wheel built from a clean copy of the tree, and a virtual environment with it installed."""
    if importlib.util.find_spec("setuptools") is None:   # the build backend, used without build isolation
        _skip_or_fail("setuptools is not installed here: the wheel cannot be built offline")
    base = tmp_path_factory.mktemp("wheel")
    src = clean_tree(base / "src")
    dist = base / "dist"
    run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-w", dist, src],
        cwd=base, timeout=300)
    (wheel,) = dist.glob("plad-*.whl")
    venv = base / "venv"
    run([sys.executable, "-m", "venv", "--without-pip", venv], cwd=base, timeout=120)
    python = venv / "bin" / "python"
    site = Path(run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], cwd=base,
                    timeout=60).stdout.strip())
    # the dependencies installed here, by folder only (their .pth files are not run: see the module docstring)
    deps = [p for p in dict.fromkeys(sys.path) if p.endswith(("site-packages", "dist-packages")) and Path(p).is_dir()]
    (site / "plad_test_dependencies.pth").write_text("".join(f"{p}\n" for p in deps))
    # --ignore-installed: the editable plad of the folders above is neither taken for this one nor uninstalled
    run([python, "-m", "pip", "install", "--no-deps", "--no-index", "--ignore-installed", wheel], cwd=base,
        timeout=300)
    elsewhere = base / "elsewhere"   # the commands' working folder: outside the repository and the copy
    elsewhere.mkdir()
    return {"src": src, "wheel": wheel, "venv": venv, "site": site, "cwd": elsewhere}


def test_the_wheel_holds_every_data_file_of_the_package(installed):
    """Every file under plad/ of a clean clone that is not Python (the shipped networks and their sidecars and
    index, a domain's grafting library, ...) is in the wheel; only the lock files, made on demand, and the
    kept search-seeded and taught networks the teach@ stages of a clone start from (no inference reads them) are
    not."""
    src = installed["src"]
    clone_only = {"search_seeded.json", "search_seeded.pt", "taught.json", "taught.pt"}
    wanted = {p.relative_to(src).as_posix() for p in (src / "plad").rglob("*")
              if p.is_file() and p.suffix not in (".py", ".pyc", ".lock") and "__pycache__" not in p.parts
              and p.name not in clone_only}
    for kept in ("search_seeded.pt", "taught.pt"):
        assert {f"plad/shipped/{d}/{kept}" for d in DOMAINS} <= \
            {p.relative_to(src).as_posix() for p in (src / "plad").rglob(kept)}
    with zipfile.ZipFile(installed["wheel"]) as whl:
        packed = set(whl.namelist())
    assert {"plad/shipped/pretrained.json", "plad/domains/csg2d/graft_library.npz"} <= wanted
    assert {f"plad/shipped/{d}/{f}" for d in DOMAINS for f in ("model.pt", "model.json", "pretrained.pt")} <= wanted
    assert sorted(wanted - packed) == []
    assert [n for n in packed if n.startswith("plad/tools/")] == []   # the maintainers' tools stay in the checkout


def test_the_installed_package_lists_six_networks_and_infers_in_every_domain(installed):
    venv, site, cwd = installed["venv"], installed["site"], installed["cwd"]
    where = run([venv / "bin" / "python", "-c", "import plad; print(plad.__file__)"], cwd=cwd, timeout=60)
    assert Path(where.stdout.strip()).is_relative_to(site), f"plad imported from {where.stdout}, not the wheel"

    listed = run([venv / "bin" / "plad", "models"], cwd=cwd, timeout=120)
    rows = [line.split() for line in listed.stdout.splitlines()[1:]]
    found = {(r[0], r[1]): r[-1].lstrip("*") for r in rows if len(r) > 2 and r[1] in ("shipped", "pretrained")}
    assert sorted(found) == sorted((d, kind) for d in DOMAINS for kind in ("shipped", "pretrained")), listed.stdout
    assert all(Path(path).is_relative_to(site / "plad" / "shipped") for path in found.values()), listed.stdout
    assert "registered" not in listed.stdout
    for d in DOMAINS:
        assert f"plad infer {d} uses {site / 'plad' / 'shipped' / d / 'model.pt'}: the shipped model" in listed.stdout

    for d in DOMAINS:
        out = installed["cwd"].parent / "inferred" / d
        res = run([venv / "bin" / "plad", "infer", d, installed["src"] / EXAMPLES[d], "--no-refine", "--out", out],
                  cwd=cwd, timeout=300)
        method = json.loads((installed["src"] / "plad" / "shipped" / d / "model.json").read_text())["method"]
        assert f"model: shipped {d} model ({method}" in res.stderr and str(site) in res.stderr, res.stderr
        assert "1 of 1 shapes inferred" in res.stderr, res.stderr
        (run_dir,) = out.iterdir()
        assert (run_dir / "results.csv").is_file()
    assert list(cwd.iterdir()) == []   # nothing written where the commands ran
