"""2D CSG: vocabulary, text form, executor (against the independent renderer), sampler."""
import re

import numpy as np
import pytest
import torch

from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.domains.csg2d.executor import pack, unpack
from plad.domains.csg2d.tokens import token_table
from plad.domains.grammar import ProgramError
from tests.conftest import require_shared
from tests.reference.csg2d_render import render

DOMAIN = get_domain("csg2d")


def reference_degenerate(program: str) -> bool:
    """Independent check of the sampler's rejection rule, step by step with numpy."""
    stack = []
    for m in re.finditer(r"([cst])\((\d+),(\d+),(\d+)\)|([+*\-])", program):
        if m.group(1):
            stack.append(render(f"{m.group(0)}$"))
            continue
        b, a = stack.pop(), stack.pop()
        op = m.group(5)
        out = a | b if op == "+" else a & b if op == "*" else a & ~b
        if np.array_equal(out, a) or np.array_equal(out, b):
            return True
        stack.append(out)
    (canvas,) = stack
    return not canvas.any() or canvas.all()


def test_vocabulary_contains_every_csgnet_token():
    lines = require_shared("datasets/csgnet_cad/terminals.txt").read_text().split()
    table = token_table()
    draws = [t for t in lines if t[0] in "cst"]
    assert len(draws) == 396
    missing = [t for t in draws if not table.has(t)]
    assert missing == []
    for op in "+*-$":
        assert table.has(op)
    assert len(table) == 424 + 4


def test_vocabulary_rule_keeps_primitives_inside_the_canvas():
    bitmaps = DOMAIN.executor.bitmaps
    for v, t in enumerate(token_table().tokens):
        if t.kind == "draw":
            assert bitmaps[v].any()


@pytest.mark.parametrize("text", [
    "c(32,24,16)s(40,40,12)+$", "t(32,32,20)$", "c(32,32,24)s(32,32,12)-$",
    "c(16,16,8)c(48,48,8)+s(32,32,20)*$", "s(24,24,16)t(40,40,16)+c(32,32,8)-$",
])
def test_executor_matches_reference_on_hand_programs(text):
    ids = DOMAIN.parse(text)
    assert DOMAIN.format(ids) == text
    got = DOMAIN.execute(torch.tensor([ids]))[0].numpy()
    assert np.array_equal(got, render(text))


def test_executor_matches_reference_on_1000_sampled_programs():
    programs = DOMAIN.sample(1000, np.random.default_rng(123))
    got = DOMAIN.execute(pad_programs(programs, pad=7)).numpy()  # padding after $ is ignored
    want = np.stack([render(DOMAIN.format(p)) for p in programs])
    bad = np.nonzero((got != want).reshape(len(programs), -1).any(axis=1))[0]
    assert bad.size == 0, [DOMAIN.format(programs[i]) for i in bad[:5]]


def test_10000_sampled_programs_are_valid_and_non_degenerate():
    programs = DOMAIN.sample(10000, np.random.default_rng(7))
    assert len(programs) == 10000
    lengths = np.bincount([len(p) // 2 for p in programs], minlength=8)  # k draws, k-1 ops, $
    assert lengths[0] == 0 and (lengths[1:] > 1000).all()  # 1 to 7 primitives, balanced
    for p in programs:
        DOMAIN.check(p)
    # independent recheck of the rejection rule on every program
    texts = [DOMAIN.format(p) for p in programs]
    flagged = [t for t in texts if reference_degenerate(t)]
    assert flagged == []


def test_sampler_is_seeded():
    a = DOMAIN.sample(50, np.random.default_rng(1))
    b = DOMAIN.sample(50, np.random.default_rng(1))
    assert a == b


def test_pack_unpack_round_trip():
    x = torch.rand(17, 64, 64) > 0.5
    assert torch.equal(unpack(pack(x)), x)
    assert pack(x).shape == (17, 64)


def test_parse_accepts_spaces_and_a_missing_stop():
    assert DOMAIN.parse(" c(32, 24, 16) s(40,40,12) + ") == DOMAIN.parse("c(32,24,16)s(40,40,12)+$")


@pytest.mark.parametrize("text, where", [
    ("c(32,24,16)x$", "token 1"),
    ("c(33,24,16)$", "c(33,24,16)"),
    ("c(8,8,32)$", "not in the vocabulary"),
    ("q(8,8,8)$", "unknown primitive"),
    ("c(a,8,8)$", "integers"),
    ("c(32,24,16)+$", "token 1 '+'"),
    ("c(32,24,16)c(32,24,16)$", "left unused"),
    ("c(32,24,16)$c(32,24,16)$", "already complete"),
])
def test_parse_errors_name_the_token(text, where):
    with pytest.raises(ProgramError) as err:
        DOMAIN.parse(text)
    assert where in str(err.value)


def test_fuzzed_program_texts_never_crash():
    rng = np.random.default_rng(0)
    alphabet = list("cstq(),+-*$ 0123456789x") + ["c(32,32,16)", "s(16,16,8)", "+", "$"]
    valid = 0
    for _ in range(3000):
        text = "".join(rng.choice(alphabet, size=rng.integers(0, 12)))
        try:
            ids = DOMAIN.parse(text)
        except ProgramError as err:
            assert str(err) and "\n" not in str(err)
            continue
        valid += 1
        assert DOMAIN.execute(torch.tensor([ids])).shape == (1, 64, 64)
    # random token sequences: valid ones execute, the others get a ProgramError
    names = token_table().names
    for _ in range(3000):
        seq = [names[i] for i in rng.integers(0, len(names), size=rng.integers(1, 16))]
        try:
            ids = DOMAIN.parse("".join(seq))
        except ProgramError:
            continue
        valid += 1
        assert np.array_equal(DOMAIN.execute(torch.tensor([ids]))[0].numpy(), render(DOMAIN.format(ids)))
    assert valid > 0


@pytest.mark.parametrize("check_degenerate", [False, True])
def test_cpu_programs_run_one_at_a_time_to_the_same_bits(check_degenerate, monkeypatch):
    """On the CPU programs run one at a time (a canvas as one Python integer): the same words and degenerate
    flags as the batched path, for sampled programs, random grammar programs and rewriting's extended executor
    (pseudo draws of the empty and the full canvas), in batches of 1 to 512 and all at once."""
    from plad.domains.csg2d.executor import Executor
    from tests.grammar import masked_rollouts

    programs = DOMAIN.sample(300, np.random.default_rng(3)) + masked_rollouts(DOMAIN, 200, seed=9)
    stop = DOMAIN.tokens.index("$")
    padded = pad_programs(programs, pad=stop)
    canvases = torch.zeros(2, 64, 64, dtype=torch.bool)
    canvases[1] = True
    draws = [v for v, t in enumerate(DOMAIN.tokens.tokens) if t.kind == "draw"]
    templates = padded[:150].clone()
    rng = np.random.default_rng(4)
    for r in range(len(templates)):
        for c in range(templates.shape[1]):
            if int(templates[r, c]) in draws and rng.random() < 0.3:
                templates[r, c] = len(DOMAIN.tokens) + int(rng.integers(2))
    calls = []
    monkeypatch.setattr(Executor, "_run_sorted",
                        lambda self, *a, _orig=Executor._run_sorted: calls.append(1) or _orig(self, *a))
    for plain, batch in ((Executor(), padded), (Executor().extended(canvases), templates)):
        batched = Executor(per_program=False)
        batched = batched if batch is padded else batched.extended(canvases)
        want_words, want_flags = batched.run_packed(batch, check_degenerate=check_degenerate)
        assert calls and bool(want_flags.any()) == check_degenerate
        calls.clear()
        for size in (1, 5, 64, 512, len(batch)):
            for start in range(0, len(batch), size):
                words, flags = plain.run_packed(batch[start:start + size], check_degenerate=check_degenerate)
                assert torch.equal(words, want_words[start:start + size])
                assert torch.equal(flags, want_flags[start:start + size])
        assert not calls                                 # every batch ran program by program


def test_a_malformed_row_runs_batched():
    from plad.domains.csg2d.executor import Executor

    ids = DOMAIN.parse("c(32,32,24)s(32,32,12)+$")
    stop = DOMAIN.tokens.index("$")
    for bad in (ids[:2] + [stop], ids[:1] + ids[2:3] + [stop], [ids[2], stop]):   # two canvases left; no operand
        row = torch.tensor([bad])
        assert Executor()._run_each(row, False) is None
        assert torch.equal(Executor().run_packed(row)[0], Executor(per_program=False).run_packed(row)[0])


def test_a_pickled_executor_rebuilds_its_integers():
    import pickle

    from plad.domains.csg2d.executor import Executor

    executor = Executor()
    programs = pad_programs(DOMAIN.sample(20, np.random.default_rng(5)), pad=DOMAIN.tokens.index("$"))
    want = executor.run_packed(programs)[0]
    copy = pickle.loads(pickle.dumps(executor))
    assert copy._each is None and executor._each is not None
    assert torch.equal(copy.run_packed(programs)[0], want)


def test_the_screen_scores_in_numpy_equal_the_torch_ones():
    """The rewrite space's screen (approximate Chamfer of packed canvases) in numpy on the CPU: the same scores as
    in torch, bit for bit, for program outputs, random canvases (every bit, the sign bit included), empty and
    full canvases, several targets and chunks."""
    from plad.domains.csg2d import rewrite as rw
    from plad.domains.csg2d.executor import pack

    space = DOMAIN.rewrite
    programs = DOMAIN.sample(40, np.random.default_rng(8))
    targets = DOMAIN.execute(pad_programs(programs[:5], pad=DOMAIN.tokens.index("$")))
    prepared = space.prepare_screen(targets)
    gen = torch.Generator().manual_seed(3)
    outputs = torch.cat([
        DOMAIN.executor.run_packed(pad_programs(programs, pad=DOMAIN.tokens.index("$")))[0],
        pack(torch.rand(30, 64, 64, generator=gen) > 0.5),
        torch.randint(-2**63, 2**63 - 1, (20, 64), generator=gen, dtype=torch.int64),
        torch.zeros(3, 64, dtype=torch.int64), torch.full((3, 64), -1, dtype=torch.int64)])
    owner = torch.randint(0, 5, (len(outputs),), generator=gen)
    saved = rw._SCREEN_CHUNK
    try:
        for chunk in (saved, 7):
            rw._SCREEN_CHUNK = chunk
            space.numpy_screen = True
            fast = space.screen_score(outputs, owner, prepared)
            space.numpy_screen = False
            slow = space.screen_score(outputs, owner, prepared)
            assert fast.dtype == slow.dtype == torch.float64 and torch.equal(fast, slow)
    finally:
        rw._SCREEN_CHUNK, space.numpy_screen = saved, True
