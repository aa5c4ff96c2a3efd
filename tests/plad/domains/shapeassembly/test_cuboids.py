"""token_cuboids with its prefix cache: bit-identical cuboids (and the same errors) as the original executor
(tests/reference/shapeassembly_v0.py, the frozen original), whatever programs ran before."""
import random

import numpy as np
import pytest

from plad.data.datasets.partnet.execute import BlockState, ExecutionError
from plad.domains import get_domain
from plad.domains.shapeassembly import cuboids
from tests.grammar import masked_rollouts
from tests.reference import shapeassembly_v0 as v0

DOMAIN = get_domain("shapeassembly")


def outcome(fn, ids):
    """The cuboids, or the error's type and message."""
    try:
        return fn(ids)
    except Exception as err:  # noqa: BLE001 - every failure must be the same one
        return type(err).__name__, str(err)


def assert_same(programs):
    for ids in programs:
        want, got = outcome(v0.token_cuboids, ids), outcome(cuboids.token_cuboids, ids)
        if isinstance(want, tuple) or isinstance(got, tuple):
            assert got == want, ids
        else:
            # bit for bit: the same float32 words (NaN included), shape and dtype
            assert got.dtype == want.dtype == np.float32 and got.shape == want.shape, ids
            assert np.array_equal(got.view(np.uint32), want.view(np.uint32)), ids


def variants(programs, rng: random.Random, n: int):
    """Programs as a search makes them: one argument token replaced by another of its kind, a part cut off,
    a part of one program appended to another's prefix."""
    table = DOMAIN.tokens
    by_kind = {}
    for i, t in enumerate(table.tokens):
        by_kind.setdefault(t.kind, []).append(i)
    out = []
    for _ in range(n):
        p = list(rng.choice(programs))
        k = rng.randrange(len(p))
        kind = table.tokens[p[k]].kind
        if kind in ("num", "face", "fpos", "axis", "snum", "cind"):
            p[k] = rng.choice(by_kind[kind])
        cut = [i for i, t in enumerate(p) if table.tokens[t].kind == "cuboid"]
        if len(cut) > 1 and rng.random() < 0.3:
            p = p[:rng.choice(cut[1:])] + [table.index("END")]
        out.append(p)
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_rollouts_and_their_variants_as_the_original(seed):
    cuboids.clear_cache()
    rng = random.Random(seed)
    programs = masked_rollouts(DOMAIN, 300, seed=seed)
    assert_same(programs)
    more = variants(programs, rng, 600)
    assert_same(more)
    rng.shuffle(more)
    assert_same(more)                      # now mostly from kept prefixes
    assert_same(programs)                  # every prefix kept: whole programs from the cache


def test_sampled_programs_as_the_original():
    cuboids.clear_cache()
    for programs in (DOMAIN.sample(30, np.random.default_rng(0)),
                     DOMAIN.samplers()["inside"](30, np.random.default_rng(1))):
        assert_same(programs)
        assert_same(programs[::-1])


def test_a_small_cache_drops_old_prefixes(monkeypatch):
    monkeypatch.setattr(cuboids, "PREFIX_CACHE", 50)
    cuboids.clear_cache()
    programs = masked_rollouts(DOMAIN, 100, seed=4)
    assert_same(programs + programs[::-1])
    assert len(cuboids._PREFIXES) == 50
    cuboids.clear_cache()


def test_malformed_token_sequences_fail_as_the_original():
    """Whatever is not a well-formed program runs from scratch, with the original's result or error."""
    cuboids.clear_cache()
    rng = random.Random(2)
    n = len(DOMAIN.tokens.tokens)
    programs = masked_rollouts(DOMAIN, 200, seed=6)
    junk = [[rng.randrange(-3, n + 2) for _ in range(rng.randrange(0, 25))] for _ in range(300)]
    spliced = [p[:k] + [rng.randrange(n)] + p[k:] for p in programs for k in [rng.randrange(len(p) + 1)]]
    assert_same(programs + junk + spliced)


def test_execution_errors_as_the_original(monkeypatch):
    """A part whose execution fails fails every program with that prefix, from the cache too."""
    def singular(*args):
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(BlockState, "_translate", singular)
    monkeypatch.setattr(v0.BlockState, "_translate", singular)
    cuboids.clear_cache()
    programs = masked_rollouts(DOMAIN, 300, seed=8)
    translate = DOMAIN.tokens.index("Translate")
    failing = [p for p in programs if translate in p]
    assert failing and len(failing) < len(programs)
    assert_same(programs)
    assert_same(variants(failing, random.Random(3), 300))
    with pytest.raises(ExecutionError):
        cuboids.token_cuboids(failing[0])
    cuboids.clear_cache()
