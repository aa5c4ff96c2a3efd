"""csg3d domain: vocabulary, text form and its errors, and the executor against the numpy reference."""
import numpy as np
import pytest
import torch

from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.domains.csg3d.executor import Executor, pack, render_primitives, unpack
from plad.domains.grammar import ProgramError
from tests.grammar import masked_rollouts
from tests.reference.csg3d_render import render

DOMAIN = get_domain("csg3d")
TABLE = DOMAIN.tokens


def run(text: str) -> np.ndarray:
    return DOMAIN.execute(torch.tensor([DOMAIN.parse(text)]))[0].numpy()


# ---- vocabulary and grammar ------------------------------------------------------------
def test_vocabulary_layout_and_cap():
    assert TABLE.names == ["cuboid", "ellipsoid", "union", "inter", "diff"] + [str(i) for i in range(1, 32)]
    assert TABLE.max_len == 100
    # a shape costs at least 7 tokens (a primitive and its 6 parameters), a parameter 1
    assert TABLE.symbol_cost == {"shape": 7, "num": 1}


def test_mask_after_a_primitive_allows_only_parameters():
    state = TABLE.initial_state(1)
    for name in ["union", "cuboid", "16"]:
        state = TABLE.advance(state, torch.tensor([TABLE.index(name)]))
    allowed = {TABLE.tokens[i].name for i in torch.nonzero(TABLE.mask(state)[0]).flatten().tolist()}
    assert allowed == {str(i) for i in range(1, 32)}


def test_mask_keeps_the_program_within_the_cap():
    # 11 operators and 12 primitives take 11 + 12 * 7 = 95 tokens; a 12th operator would need
    # 12 + 13 * 7 = 103, so after 10 unions an 11th is allowed and after 11 a 12th is not
    state = TABLE.initial_state(1)
    union = torch.tensor([TABLE.index("union")])
    for _ in range(10):
        state = TABLE.advance(state, union)
    assert TABLE.mask(state)[0, TABLE.index("union")]
    state = TABLE.advance(state, union)
    mask = TABLE.mask(state)[0]
    assert not mask[TABLE.index("union")] and mask[TABLE.index("cuboid")] and mask[TABLE.index("ellipsoid")]


# ---- text form -------------------------------------------------------------------------
def test_text_round_trip_and_aliases():
    text = ("diff union cuboid 16 16 16 20 20 20 ellipsoid 8 9 10 3 4 5 "
            "inter cuboid 1 2 3 4 5 6 ellipsoid 31 31 31 31 31 31")
    ids = DOMAIN.parse(text)
    assert DOMAIN.format(ids) == text
    assert DOMAIN.parse("  subtract\n  cuboid 16 16 16 20 20 20\n  ELLIPSOID 16 16 16 2 2 2  ") == \
        DOMAIN.parse("diff cuboid 16 16 16 20 20 20 ellipsoid 16 16 16 2 2 2")
    assert DOMAIN.parse("intersect cuboid 1 1 1 2 2 2 cuboid 1 1 1 2 2 2")[0] == TABLE.index("inter")
    # format stops where the program is complete (padding after it is ignored)
    assert DOMAIN.format(ids + [0, 0, 0]) == text


@pytest.mark.parametrize("text, position, token, message", [
    ("cuboid 16 16 16 8 8", 6, None, "program is incomplete: cuboid at token 0 has 5 of its 6 parameters"),
    ("cuboid 16 16 16 8 8 32", 6, "32", "token 6 '32': parameters are integers 1..31"),
    ("cuboid 16 16 0 8 8 8", 3, "0", "token 3 '0': parameters are integers 1..31"),
    ("cuboid 16 16 -4 8 8 8", 3, "-4", "token 3 '-4': parameters are integers 1..31"),
    ("union cuboid 1 1 1 2 2 2", 8, None, "program is incomplete: union at token 0 is missing its second operand"),
    ("union", 1, None, "program is incomplete: union at token 0 is missing its first operand"),
    ("cuboid 16 16 16 8 8 union", 6, "union",
     "token 6 'union': expected an integer parameter, but cuboid at token 0 has 5 of its 6 parameters"),
    ("16 cuboid", 0, "16", "token 0 '16': expected a shape (cuboid, ellipsoid, union, inter or diff), got a number"),
    ("diff cuboid 1 1 1 2 2 2 7", 8, "7", "token 8 '7': expected a shape"),
    ("cube 1 2 3 4 5 6", 0, "cube", "token 0 'cube' is not a csg3d token"),
    ("cuboid 16 16 16 8 8 8.5", 6, "8.5", "token 6 '8.5' is not a csg3d token"),
    ("cuboid(16,16,16,8,8,8)", 0, "cuboid(16,16,16,8,8,8)", "is not a csg3d token"),
    ("cuboid 1 1 1 2 2 2 cuboid 1 1 1 2 2 2", 7, "cuboid",
     "token 7 'cuboid' comes after the program is already complete"),
    ("union " * 13 + "cuboid 1 1 1 2 2 2 " * 14, 100, None, "program has 111 tokens; the length cap is 100"),
])
def test_parse_errors_are_one_line_and_name_the_token(text, position, token, message):
    with pytest.raises(ProgramError) as info:
        DOMAIN.parse(text)
    err = info.value
    assert message in str(err) and "\n" not in str(err)
    assert err.position == position
    if token is not None:
        assert err.token == token


def test_check_rejects_incomplete_and_overlong_id_sequences():
    with pytest.raises(ProgramError, match="incomplete"):
        DOMAIN.check(TABLE.encode("union cuboid 1 1 1 2 2 2".split()))
    with pytest.raises(ProgramError, match="already complete"):
        DOMAIN.check(TABLE.encode("cuboid 1 1 1 2 2 2 7".split()))


# ---- executor: exact voxels of the inside tests (docs/domains.md) --------------------------
def box(x0, x1, y0, y1, z0, z1):
    """Inclusive voxel index ranges -> bool grid."""
    g = np.zeros((32, 32, 32), bool)
    g[x0:x1 + 1, y0:y1 + 1, z0:z1 + 1] = True
    return g


def test_cuboid_voxels_exact():
    # |p - 16| <= 2 on every axis
    assert np.array_equal(run("cuboid 16 16 16 4 4 4"), box(14, 18, 14, 18, 14, 18))
    # odd extents: |p - c| <= 1.5, 2.5, 0.5; axes are [x, y, z] in that order
    assert np.array_equal(run("cuboid 10 20 5 3 5 1"), box(9, 11, 18, 22, 5, 5))
    # clipped at the grid: |p - 1| <= 15.5 keeps 0..16
    assert np.array_equal(run("cuboid 1 1 1 31 31 31"), box(0, 16, 0, 16, 0, 16))
    assert np.array_equal(run("cuboid 31 2 30 31 2 4"), box(16, 31, 1, 3, 28, 31))


def test_ellipsoid_voxels_exact():
    # (p - c)^2 summed <= 1: the center and its 6 face neighbours
    want = np.zeros((32, 32, 32), bool)
    for dx, dy, dz in [(0, 0, 0), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]:
        want[16 + dx, 16 + dy, 16 + dz] = True
    assert np.array_equal(run("ellipsoid 16 16 16 2 2 2"), want)
    # exactly on the surface: 4/9 + 4/9 + 4/36 = 1 at offset (1, 1, 1) with d = (3, 3, 6); inside
    g = run("ellipsoid 16 16 16 3 3 6")
    assert g[17, 17, 17] and g[15, 15, 15] and g[16, 16, 19] and not g[16, 16, 20]
    # along an axis the ellipsoid reaches |p - c| <= d/2
    g = run("ellipsoid 16 16 16 31 9 20")
    xs, ys, zs = (np.nonzero(g.any(axis=(1, 2)))[0], np.nonzero(g.any(axis=(0, 2)))[0],
                  np.nonzero(g.any(axis=(0, 1)))[0])
    assert (xs.min(), xs.max(), ys.min(), ys.max(), zs.min(), zs.max()) == (1, 31, 12, 20, 6, 26)


def test_operators_and_operand_order():
    a, b = "cuboid 10 16 16 12 12 12", "cuboid 16 16 16 12 12 12"
    A, B = run(a), run(b)
    assert np.array_equal(run(f"union {a} {b}"), A | B)
    assert np.array_equal(run(f"inter {a} {b}"), A & B)
    assert np.array_equal(run(f"diff {a} {b}"), A & ~B)      # diff A B = A and not B
    assert np.array_equal(run(f"diff {b} {a}"), B & ~A)
    nested = f"diff union {a} ellipsoid 20 20 20 9 9 9 inter {b} ellipsoid 16 16 16 8 8 8"
    assert np.array_equal(run(nested), render(nested))


def test_pack_unpack_round_trip():
    grids = torch.rand(3, 32, 32, 32, generator=torch.Generator().manual_seed(0)) > 0.5
    words = pack(grids)
    assert words.dtype == torch.int32 and words.shape == (3, 32, 32)
    assert torch.equal(unpack(words), grids)


def test_executor_equals_reference_on_1000_sampled_programs():
    programs = DOMAIN.sample(1000, np.random.default_rng(11))
    got = DOMAIN.execute(pad_programs(programs)).numpy()
    for ids, grid in zip(programs, got):
        text = DOMAIN.format(ids)
        assert np.array_equal(grid, render(text)), text


def test_executor_equals_reference_on_random_grammar_programs():
    # masked random decoding: any parameters (primitives past the grid border, extents up
    # to 31, odd extents, up to 12 primitives and deep nesting)
    programs = masked_rollouts(DOMAIN, 300, seed=5)
    got = DOMAIN.execute(pad_programs(programs)).numpy()
    for ids, grid in zip(programs, got):
        text = DOMAIN.format(ids)
        assert np.array_equal(grid, render(text)), text


def test_every_primitive_shape_in_a_parameter_sweep():
    # all extents 1..31 on each axis for both kinds, at a center near the border
    rng = np.random.default_rng(2)
    params = np.concatenate([rng.integers(1, 32, size=(400, 3)), rng.integers(1, 32, size=(400, 3))], axis=1)
    ell = rng.random(400) < 0.5
    words = render_primitives(torch.from_numpy(params), torch.from_numpy(ell))
    got = unpack(words).numpy()
    for p, e, g in zip(params, ell, got):
        text = f"{'ellipsoid' if e else 'cuboid'} {' '.join(map(str, p))}"
        assert np.array_equal(g, render(text)), text


def test_padding_is_ignored_and_batches_are_independent():
    programs = DOMAIN.sample(20, np.random.default_rng(1))
    zero = DOMAIN.execute(pad_programs(programs))
    minus = DOMAIN.execute(pad_programs(programs, pad=-1))
    junk = pad_programs(programs, pad=TABLE.index("union"))
    assert torch.equal(zero, minus) and torch.equal(zero, DOMAIN.execute(junk))
    small_chunks = Executor(TABLE, chunk=3)(pad_programs(programs))
    assert torch.equal(zero, small_chunks)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_cuda_equals_cpu():
    programs = pad_programs(DOMAIN.sample(200, np.random.default_rng(7)) + masked_rollouts(DOMAIN, 100, seed=2))
    on_gpu = DOMAIN.execute(programs.cuda())
    assert on_gpu.device.type == "cuda"
    assert torch.equal(on_gpu.cpu(), DOMAIN.execute(programs))


def test_import_does_not_touch_cuda():
    import subprocess
    import sys

    code = ("import torch, plad.domains.csg3d as m; from plad.domains import get_domain; "
            "get_domain('csg3d'); print(torch.cuda.is_initialized())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def _with_pseudo_primitives(programs: list[list[int]], seed: int) -> list[list[int]]:
    """Copies of ``programs`` with random primitives drawing the empty or the full grid (rewriting's templates)."""
    from plad.domains.csg3d.executor import EMPTY_PRIMITIVE, FULL_PRIMITIVE

    rng = np.random.default_rng(seed)
    prims = {TABLE.index("cuboid"), TABLE.index("ellipsoid")}
    out = []
    for ids in programs:
        ids = list(ids)
        for i, t in enumerate(ids):
            if t in prims and rng.random() < 0.3:
                ids[i] = EMPTY_PRIMITIVE if rng.random() < 0.5 else FULL_PRIMITIVE
        out.append(ids)
    return out


@pytest.mark.parametrize("compiled", [False, True])
@pytest.mark.parametrize("check_degenerate", [False, True])
def test_cpu_programs_run_one_at_a_time_to_the_same_bits(check_degenerate, compiled, monkeypatch):
    """On the CPU programs run one at a time, in chunks of ``EACH_CHUNK``, in numpy or compiled
    (plad.domains.csg3d.compiled): the same words and degenerate flags as the batched path, for sampled programs,
    random grammar programs, rewriting's pseudo primitives and any padding, in batches of 1 to 256 and all at
    once; in numpy through a primitive cache that fills, is cleared and is reused."""
    import plad.domains.csg3d.executor as ex

    monkeypatch.setattr(ex, "_COMPILED", compiled)
    monkeypatch.setattr(ex, "PRIMITIVE_CACHE", 500)     # small: the cache is cleared during the test
    programs = DOMAIN.sample(200, np.random.default_rng(3)) + masked_rollouts(DOMAIN, 150, seed=9)
    programs += _with_pseudo_primitives(programs[:120], seed=4)
    batched, each = Executor(TABLE, per_program=False), Executor(TABLE)
    calls = []
    monkeypatch.setattr(Executor, "_run", lambda self, *a, _orig=Executor._run: calls.append(1) or _orig(self, *a))
    for pad in (0, -1, TABLE.index("union")):
        padded = pad_programs(programs, pad=pad)
        want_words, want_flags = batched.run_packed(padded, check_degenerate=check_degenerate)
        assert calls and want_flags.any() == check_degenerate
        calls.clear()
        for size in (1, 7, 64, 256, len(padded)):
            for start in range(0, len(padded), size):
                words, flags = each.run_packed(padded[start:start + size], check_degenerate=check_degenerate)
                assert torch.equal(words, want_words[start:start + size])
                assert torch.equal(flags, want_flags[start:start + size])
        assert not calls                                # every batch ran program by program
    if compiled:
        assert each._primitives == {}                   # compiled, primitives are rendered where they are drawn
    else:
        assert 0 < len(each._primitives) <= 500 + 256 * 12


@pytest.mark.parametrize("compiled", [False, True])
def test_a_row_that_does_not_end_runs_batched(compiled, monkeypatch):
    """A row whose program does not end within its length: the per-program path leaves it to the batched one."""
    import plad.domains.csg3d.executor as ex

    monkeypatch.setattr(ex, "_COMPILED", compiled)
    ids = DOMAIN.parse("union cuboid 16 16 16 8 8 8 ellipsoid 10 10 10 6 6 6")
    cut = torch.tensor([ids[:-3], ids[:-3]])
    assert Executor(TABLE)._run_each(cut, False) is None
    assert torch.equal(Executor(TABLE).run_packed(cut)[0], Executor(TABLE, per_program=False).run_packed(cut)[0])


def test_a_pickled_executor_leaves_its_primitive_cache_behind(monkeypatch):
    import pickle

    import plad.domains.csg3d.executor as ex

    monkeypatch.setattr(ex, "_COMPILED", False)         # the numpy path keeps the cache
    executor = Executor(TABLE)
    programs = pad_programs(DOMAIN.sample(20, np.random.default_rng(5)))
    want = executor.run_packed(programs)[0]
    assert executor._primitives
    copy = pickle.loads(pickle.dumps(executor))
    assert copy._primitives == {} and executor._primitives
    assert torch.equal(copy.run_packed(programs)[0], want)
