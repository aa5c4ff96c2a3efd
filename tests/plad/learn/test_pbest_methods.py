"""P_BEST and the PLAD sources (ST, LEST) and mixture parsing."""
import numpy as np
import pytest
import torch

from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.learn.methods import Mixture, lest_source, mixture_batches, parse_mixture, st_source
from plad.learn.pbest import PBest
from plad.metrics import IOU

DOMAIN = get_domain("csg2d")


def offer(pbest, idx, programs, targets):
    shapes = DOMAIN.execute(pad_programs(programs))
    values = DOMAIN.metric(shapes, torch.from_numpy(targets[idx])).numpy()
    return pbest.update(idx, programs, values, shapes.numpy()), values


@pytest.fixture(scope="module")
def targets():
    return DOMAIN.execute(pad_programs(DOMAIN.sample(40, np.random.default_rng(0)))).numpy()


def test_all_time_pbest_keeps_the_best_and_never_gets_worse(targets):
    pbest = PBest(len(targets), DOMAIN.shape, DOMAIN.tokens.max_len, DOMAIN.metric, "all-time")
    rng = np.random.default_rng(1)
    idx = np.arange(len(targets))
    best = np.full(len(targets), np.inf)
    means = []
    for _ in range(6):
        programs = DOMAIN.sample(len(targets), rng)
        stats, values = offer(pbest, idx, programs, targets)
        best = np.minimum(best, values)  # Chamfer: lower is better
        assert np.allclose(pbest.values, best)
        means.append(stats.mean)
        # every entry executes to its stored execution and scores its stored value
        again = DOMAIN.execute(pad_programs([pbest.program(i) for i in idx]))
        assert np.array_equal(again.numpy(), pbest.executions)
    assert all(b <= a + 1e-12 for a, b in zip(means, means[1:]))


def test_ties_go_to_the_new_program(targets):
    pbest = PBest(1, DOMAIN.shape, DOMAIN.tokens.max_len, IOU)
    a, b = DOMAIN.parse("c(32,32,16)$"), DOMAIN.parse("c(32,32,16)c(32,32,16)+$")
    shape = DOMAIN.execute(pad_programs([a])).numpy()
    pbest.update(np.array([0]), [a], np.array([0.5]), shape)
    pbest.update(np.array([0]), [b], np.array([0.5]), shape)
    assert pbest.program(0) == b
    pbest.update(np.array([0]), [a], np.array([0.4]), shape)
    assert pbest.program(0) == b  # IoU: 0.4 is worse


def test_per_round_mode_forgets_and_save_load_round_trip(targets, tmp_path):
    pbest = PBest(len(targets), DOMAIN.shape, DOMAIN.tokens.max_len, DOMAIN.metric, "per-round")
    offer(pbest, np.arange(10), DOMAIN.sample(10, np.random.default_rng(2)), targets)
    pbest.save(tmp_path / "pbest.npz")
    loaded = PBest.load(tmp_path / "pbest.npz", DOMAIN.metric)
    assert loaded.mode == "per-round"
    assert np.array_equal(loaded.programs, pbest.programs)
    assert np.array_equal(loaded.values, pbest.values, equal_nan=True)
    assert np.array_equal(loaded.executions, pbest.executions)
    loaded.start_round()
    assert not loaded.has.any()
    with pytest.raises(ValueError, match="mode"):
        PBest(1, DOMAIN.shape, 14, DOMAIN.metric, "sometimes")


def test_sources_pair_shapes_and_programs_correctly(targets):
    pbest = PBest(len(targets), DOMAIN.shape, DOMAIN.tokens.max_len, DOMAIN.metric)
    offer(pbest, np.arange(0, 40, 2), DOMAIN.sample(20, np.random.default_rng(3)), targets)
    rng = np.random.default_rng(0)
    shapes, programs, lengths = lest_source(pbest, torch.device("cpu"))(rng, 16)
    # LEST pairs execute exactly to their shapes
    assert torch.equal(DOMAIN.execute(programs), shapes)
    shapes, programs, lengths = st_source(pbest, targets, torch.device("cpu"))(rng, 16)
    # ST pairs: a real shape with the best program of that same shape
    for s, p, n in zip(shapes.numpy(), programs, lengths):
        i = next(i for i in range(len(targets)) if np.array_equal(targets[i], s))
        assert pbest.has[i] and p[: int(n)].tolist() == pbest.program(i)


@pytest.mark.parametrize("text, names, weights", [
    ("lest", ("lest",), (1.0,)),
    ("st", ("st",), (1.0,)),
    ("LEST+ST", ("lest", "st"), (0.5, 0.5)),
    ("lest+st+ws", ("lest", "st", "ws"), (1 / 3, 1 / 3, 1 / 3)),
    ("lest:3+st:1", ("lest", "st"), (0.75, 0.25)),
])
def test_mixture_parsing_is_exact(text, names, weights):
    m = parse_mixture(text)
    assert m.names == names and np.allclose(m.weights, weights)


@pytest.mark.parametrize("text", ["", "les", "lest+", "lestst", "st+st", "lest:0+st", "lest:x", "rl"])
def test_bad_mixtures_are_errors(text):
    with pytest.raises(ValueError):
        parse_mixture(text)


def test_each_batch_comes_whole_from_one_source_by_weight():
    def const(tag):
        return lambda rng, n: (torch.full((n,), tag), torch.zeros(n, 1), torch.ones(n))
    batches = mixture_batches(Mixture(("lest", "st"), (0.8, 0.2)), {"lest": const(1), "st": const(2)}, 4, seed=0)
    stream = batches(0)
    drawn = [next(stream)[0] for _ in range(2000)]
    tags = np.array([int(b[0]) for b in drawn])
    assert all(len(set(b.tolist())) == 1 for b in drawn)
    assert abs((tags == 1).mean() - 0.8) < 0.03
    first = [int(next(stream)[0][0]) for stream in (batches(5), batches(5))]
    assert first[0] == first[1]  # the stream is fixed by (seed, epoch)
