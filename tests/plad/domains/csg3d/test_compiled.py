"""The compiled CPU path of the 3D CSG executor (plad.domains.csg3d.compiled) gives the tensor path's bits.

The stack machine on sampled, random grammar and pseudo-primitive programs is compared in test_csg3d.py
(``test_cpu_programs_run_one_at_a_time_to_the_same_bits``); here: every extent of both primitive kinds, the rows
it leaves to the batched path, and unpack.
"""
from __future__ import annotations

import importlib

import numpy as np
import pytest
import torch

from plad.domains import get_domain
from plad.domains.csg3d import compiled
from plad.domains.csg3d.executor import Executor, render_primitives, unpack

ex = importlib.import_module("plad.domains.csg3d.executor")
DOMAIN = get_domain("csg3d")
TABLE = DOMAIN.tokens


@pytest.fixture(autouse=True)
def always_compiled(monkeypatch):
    """Every call here compiled (the default waits until a process has earned it, plad.jit)."""
    monkeypatch.setattr(ex, "_COMPILED", True)


def test_numba_is_there():
    assert compiled.available()


@pytest.mark.parametrize("kind", ["cuboid", "ellipsoid"])
def test_every_extent_of_a_primitive_renders_the_tensor_paths_bits(kind):
    """All 31^3 extents, each at a random center (borders included), as one-primitive programs."""
    rng = np.random.default_rng(1 if kind == "cuboid" else 2)
    extents = np.stack(np.meshgrid(*[np.arange(1, 32)] * 3, indexing="ij"), -1).reshape(-1, 3)
    centers = rng.integers(1, 32, size=extents.shape)
    centers[:200] = rng.choice([1, 31], size=(200, 3))
    params = np.concatenate([centers, extents], 1)
    number = {int(t.params[0]): i for i, t in enumerate(TABLE.tokens) if t.kind not in ("primitive", "operator")}
    rows = [[TABLE.index(kind)] + [number[int(v)] for v in p] for p in params]
    words, flags = Executor(TABLE).run_packed(torch.tensor(rows))
    want = render_primitives(torch.from_numpy(params), torch.full((len(params),), kind == "ellipsoid"))
    assert torch.equal(words, want) and not flags.any()
    assert (words != 0).flatten(1).any(1).all()           # every primitive draws something


def test_a_parameter_that_is_no_number_leaves_the_row_to_the_batched_path(monkeypatch):
    ids = DOMAIN.parse("union cuboid 16 16 16 8 8 8 ellipsoid 10 10 10 6 6 6")
    odd = list(ids)
    odd[4] = TABLE.index("cuboid")                         # a primitive token where a parameter goes
    rows = torch.tensor([ids, odd])
    assert Executor(TABLE)._run_each(rows, False) is None
    assert torch.equal(Executor(TABLE).run_packed(rows)[0], Executor(TABLE, per_program=False).run_packed(rows)[0])
    beyond = torch.tensor([ids[:1] + [len(TABLE) + 7] + ids[2:]])   # a token beyond the tables
    T = {k: v.numpy() for k, v in ex._tables(torch.device("cpu")).items()}
    out, flags = np.empty((1, 1024), np.int32), np.zeros(1, bool)
    assert compiled.run_programs(beyond.numpy(), T["delta"], T["code"], T["value"], T["ell"], T["fixed"],
                                 T["interval"], T["column"], False, out, flags) == compiled.FALLBACK


def test_unpack_equals_the_byte_table_in_torch(monkeypatch):
    words = torch.randint(-2**31, 2**31 - 1, (5, 32, 32), generator=torch.Generator().manual_seed(0),
                          dtype=torch.int64).int()
    words[0] = 0
    words[1] = -1
    fast = unpack(words)
    monkeypatch.setattr(ex, "_COMPILED", False)
    slow = unpack(words)
    assert fast.dtype == torch.bool and fast.shape == (5, 32, 32, 32) and torch.equal(fast, slow)
    assert not fast[0].any() and fast[1].all()
    assert torch.equal(unpack(words[2:3].transpose(1, 2)), slow[2:3].transpose(1, 2))   # a strided view
