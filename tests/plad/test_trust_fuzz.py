"""Fuzz (seeded loops, no extra dependency): program texts, params values and input files for every domain.

Whatever the input, a command answers 0, or one line on stderr with status 1 or 2 (plad.errors) and never a
traceback (an exception escaping ``main`` fails the test with its traceback); a refused params value leaves
the run directory and the MLflow store as they were. Budget: well under a minute.
"""
from __future__ import annotations

import random
import shutil
from pathlib import Path

import numpy as np
import pytest

from plad.domains import domain_names, get_domain
from plad.serve.cli import main
from tests.conftest import REPO_ROOT, require_shared

REPO = REPO_ROOT
SEED = 18
NASTY = ["-5", "0", "-0.5", ".nan", ".inf", "-.inf", "1e309", "csg4d", "[]", "{}", "null", "true", "'x'",
         "[1, -1]", "{a: 1}", "!!python/object/apply:os.system ['true']", "]", "{", "3", "2.5", "''",
         "99999999999999999999999", "[csg2d, csg4d]"]


def programs(domain: str) -> list[str]:
    """Valid program texts of a domain: a few executions of its own token sampler's programs, or a fixture."""
    if domain == "shapeassembly":
        path = require_shared("fixtures/shapeassembly_reference.npz")
        return [str(t) for t in np.load(path)["program_text"][:3]]
    return {"csg2d": ["c(32,32,16)s(40,40,12)-$", "t(20,30,10)c(40,40,8)+$"],
            "csg3d": ["union cuboid 12 10 16 10 8 12 ellipsoid 20 18 16 12 12 14"]}.get(domain) or []


def mutate(text: str, rng: random.Random) -> str:
    chars = list(text)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(6)
        i = rng.randrange(len(chars) + 1)
        if op == 0 and chars:
            del chars[min(i, len(chars) - 1)]
        elif op == 1:
            chars.insert(i, rng.choice("()$+-*,. \n\t{}=#0123456789abcxyz\x00é"))
        elif op == 2:
            chars[i:i] = list(rng.choice(["-1", "999999", "nan", "1e400", "-0", "  ", "$", "Cuboid(", "}"]))
        elif op == 3 and chars:
            j = rng.randrange(len(chars))
            chars = chars[:j] if rng.random() < 0.5 else chars[j:]
        elif op == 4:
            chars = chars * 2
        else:
            rng.shuffle(chars)
    return "".join(chars)


def assert_answer(status: int, err: str, allowed=(0, 2)) -> None:
    assert status in allowed, err
    assert "Traceback" not in err
    if status:
        lines = [line for line in err.splitlines() if line.startswith("plad: error:")]
        assert len(lines) == 1, err


@pytest.mark.parametrize("domain", domain_names())
def test_program_texts_never_traceback(domain, capsys):
    rng = random.Random(f"{SEED}-{domain}")
    bases = programs(domain) or ["x"]
    texts = [mutate(rng.choice(bases), rng) for _ in range(150)] + ["", " ", "\x00", "$" * 500, "(" * 2000]
    for text in texts:
        status = main(["execute", domain, "--", text])   # "--": a text starting with "-" is no option
        assert_answer(status, capsys.readouterr().err)


def _files(domain: str, folder: Path, rng: np.random.Generator) -> list[Path]:
    """Odd input files: arrays of every kind and shape, junk bytes under every supported suffix."""
    shape = tuple(get_domain(domain).shape)
    arrays = [np.full(shape, np.nan), np.full(shape, np.inf), np.zeros(shape), np.ones(shape),
              rng.random(shape) < 0.5, rng.integers(-3, 3, shape), np.zeros((0, *shape)), np.array(3.0),
              np.zeros((32, 32, 32), bool), np.zeros((64, 64), bool), rng.random((2, 2, *shape)) < 0.5,
              np.array(["a", "b"]), np.zeros(shape, np.complex64), rng.random((5, 7)) < 0.5]
    out = []
    for i, a in enumerate(arrays):
        out.append(folder / f"a{i}.npy")
        np.save(out[-1], a)
    for i, suffix in enumerate((".png", ".jpg", ".npy", ".obj", ".ply", ".off", ".stl", ".txt", "")):
        data = bytes(rng.integers(0, 256, int(rng.integers(0, 300)), dtype=np.uint8))
        out.append(folder / f"junk{i}{suffix}")
        out[-1].write_bytes(data)
    (folder / "empty.png").write_bytes(b"")
    (folder / "truncated.npy").write_bytes((folder / "a4.npy").read_bytes()[:90])
    (folder / "sub.npy").mkdir()
    return out + [folder / "empty.png", folder / "truncated.npy", folder / "sub.npy", folder / "missing.npy"]


@pytest.mark.parametrize("domain", domain_names())
def test_input_files_never_traceback(domain, tmp_path, capsys):
    from plad.data.inputs import read_inputs

    rng = np.random.default_rng(SEED)
    folder = tmp_path / "in"
    folder.mkdir()
    files = _files(domain, folder, rng)
    good = np.zeros(get_domain(domain).shape, bool)
    good[(slice(2, 9),) * good.ndim] = True
    np.save(tmp_path / "good.npy", good)
    for f in files:   # score (the same reader as refine and search) with the file on either side
        for args in (["--pred", str(f), "--target", str(tmp_path / "good.npy")],
                     ["--pred", str(tmp_path / "good.npy"), "--target", str(f)]):
            assert_answer(main(["score", domain, *args]), capsys.readouterr().err)
    # infer's edge: every file, and the folder, gives items (errors recorded), never an exception
    items = read_inputs([*map(str, files), str(folder)], tuple(get_domain(domain).shape))
    assert items and all((it.error is None) == (it.shape is not None) for it in items)
    assert all("\n" not in it.error for it in items if it.error)


def _snapshot(*roots: Path) -> dict[str, tuple[int, int]]:
    out = {}
    for root in roots:
        for p in sorted(root.rglob("*")):
            st = p.stat()
            out[str(p)] = (st.st_size, st.st_mtime_ns) if p.is_file() else (0, 0)
    return out


def _section_keys(raw: dict, prefix: str = "") -> list[str]:
    keys = []
    for k, v in raw.items():
        keys.append(prefix + k)
        if isinstance(v, dict) and v and k != "limit":
            keys += _section_keys(v, f"{prefix}{k}.")
    return keys


def test_params_values_never_traceback_and_a_refused_one_changes_nothing(tmp_path, monkeypatch, capsys):
    import importlib

    from plad.config import ConfigError, apply_overrides, build, load_params, lookup

    work = tmp_path / "work"
    work.mkdir()
    shutil.copy(REPO / "params.yaml", work / "params.yaml")
    shutil.copytree(REPO / "profiles", work / "profiles")
    store = tmp_path / "mlflow"
    store.mkdir()
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{store / 'mlflow.db'}")
    root = tmp_path / "root"
    root.mkdir()
    params = load_params(work / "params.yaml")
    rng = random.Random(SEED)
    stages = {"prepare": ["prepare"], "report": ["report"],
              **{s: [f"{s}.{d}" for d in params[s]] for s in ("synthesize", "pretrain", "evaluate", "finetune")}}
    refused = 0
    for _ in range(200):
        stage = rng.choice(sorted(stages))
        name = rng.choice(stages[stage])
        module = importlib.import_module(f"plad.stages.{stage}")
        key = rng.choice(_section_keys(lookup(params, name)) + ["no_such_key", "model.no_such"])
        item = f"{key}={rng.choice(NASTY)}"
        try:
            build(module.__dict__[_config_class(module)], apply_overrides(lookup(params, name), [item], name), name)
        except ConfigError:
            pass
        else:
            continue   # an accepted value would start a real run: not this test's business
        refused += 1
        before = _snapshot(root, store, work)
        status = module.main(["--params", str(work / "params.yaml"), "--section", name, "--set", item,
                              "--root", str(root)])
        err = capsys.readouterr().err
        assert status == 1 and "Traceback" not in err, (item, err)
        assert len(err.strip().splitlines()) == 1 and err.startswith(f"{stage}: error: "), (item, err)
        assert _snapshot(root, store, work) == before, item
    assert refused >= 80


def _config_class(module) -> str:
    """The config class the stage's ``main`` hands to ``stage_main`` (defined in the stage or imported)."""
    import inspect
    import re

    return re.search(r'stage_main\("\w+", (\w+),', inspect.getsource(module.main)).group(1)
