"""The contract every domain plugin must meet. A domain counts as added when this passes for it."""
import numpy as np
import pytest
import torch

from plad.domains import domain_names, get_domain
from plad.domains.base import pad_programs
from plad.domains.grammar import ProgramError
from plad.metrics import Metric
from tests.grammar import masked_rollouts

DOMAINS = domain_names()


@pytest.fixture(scope="module", params=DOMAINS)
def domain(request):
    return get_domain(request.param)


def test_masked_decoding_always_yields_valid_programs(domain):
    programs = masked_rollouts(domain, 500, seed=0)
    for ids in programs:
        domain.check(ids)
        assert len(ids) <= domain.tokens.max_len
    shapes = domain.execute(pad_programs(programs))
    assert shapes.dtype == torch.bool and tuple(shapes.shape) == (len(programs), *domain.shape)


def test_text_round_trip(domain):
    for ids in masked_rollouts(domain, 100, seed=1):
        assert domain.parse(domain.format(ids)) == ids


def test_sampled_programs_are_valid_and_accepted_by_the_mask(domain):
    programs = domain.sample(300, np.random.default_rng(0))
    assert len(programs) == 300
    table = domain.tokens
    state = table.initial_state(len(programs))
    batch = pad_programs(programs)
    for t in range(batch.shape[1]):
        live = ~state.done
        if not live.any():
            break
        mask = table.mask(state)
        rows = torch.nonzero(live).flatten()
        # the mask never forbids a token of a valid program (it is not too strict)
        assert mask[rows, batch[rows, t]].all()
        state = table.advance(state, batch[:, t])
    assert state.done.all()
    for ids in programs:
        domain.check(ids)
    shapes = domain.execute(batch)
    flat = shapes.reshape(len(programs), -1)
    assert flat.any(dim=1).all() and not flat.all(dim=1).any()


def test_execution_is_deterministic_and_batch_independent(domain):
    programs = domain.sample(64, np.random.default_rng(3))
    batch = pad_programs(programs)
    whole = domain.execute(batch)
    one_by_one = torch.cat([domain.execute(batch[i:i + 1]) for i in range(len(programs))])
    assert torch.equal(whole, one_by_one)


def test_garbage_text_gets_a_program_error(domain):
    for text in ["", "   ", "???", "$$$", "(", ")" * 3]:
        with pytest.raises(ProgramError):
            domain.parse(text)


def test_metric_declares_its_direction(domain):
    assert isinstance(domain.metric, Metric)
    assert isinstance(domain.metric.higher_is_better, bool)
    programs = domain.sample(8, np.random.default_rng(4))
    shapes = domain.execute(pad_programs(programs))
    self_score = domain.metric(shapes, shapes)
    other = domain.metric(shapes, shapes.roll(1, dims=0))
    # a shape matches itself at least as well as it matches another one
    assert not domain.metric.better(other, self_score).any()


def test_reward_is_in_0_1_and_never_lower_for_a_better_metric_value(domain):
    programs = domain.sample(8, np.random.default_rng(7))
    shapes = domain.execute(pad_programs(programs))
    values = torch.cat([domain.metric(shapes, shapes), domain.metric(shapes, shapes.roll(1, dims=0)),
                        domain.metric(shapes, ~shapes)])
    r = domain.reward(values)
    assert r.shape == values.shape and ((r >= 0) & (r <= 1)).all()
    better = domain.metric.better(values[:, None], values[None, :])
    assert (r[:, None] >= r[None, :])[better].all()
    assert r.max() > r.min()   # the reward tells good from bad reconstructions


def test_display_data_and_paper_numbers_are_declared(domain):
    assert domain.display_name and domain.display_scale > 0 and domain.display_digits >= 0
    # the paper's numbers are keyed by method (rows of the table) and given in display units
    for numbers in (domain.paper_table, domain.paper_per_round):
        assert all(isinstance(k, str) and isinstance(v, float) for k, v in numbers.items())
    assert set(domain.paper_per_round) <= set(domain.paper_table)


def test_execute_text_writes_the_executed_grid(domain, tmp_path):
    """``plad execute DOMAIN PROGRAM -o x.npy`` of a token program is the executor's grid."""
    programs = domain.sample(4, np.random.default_rng(5))
    for i, ids in enumerate(programs):
        shown = domain.execute_text(domain.format(ids), tmp_path / f"{i}.npy")
        assert isinstance(shown, str) and "\n" not in shown
        assert np.array_equal(np.load(tmp_path / f"{i}.npy"), domain.execute(pad_programs([ids]))[0].numpy())
    with pytest.raises(ValueError, match="unsupported output type"):
        domain.execute_text(domain.format(programs[0]), tmp_path / "x.unknown")


def test_export_formats_are_declared_and_offered(domain):
    assert isinstance(domain.export_formats, tuple)
    text = domain.format(domain.sample(1, np.random.default_rng(6))[0])
    for fmt in domain.export_formats:
        assert domain.export_text(text, fmt).strip()
    with pytest.raises(ValueError, match="unknown export format"):
        domain.export_text(text, "no-such-format")


def test_target_data_has_the_domain_shape(domain, datasets_dir):
    shapes = domain.target_data("val", datasets_dir)
    assert shapes.dtype == bool and shapes.shape[1:] == domain.shape and len(shapes) > 0


def test_tabulated_stack_tops_give_the_same_masks_and_states_as_comparing_rules(domain):
    """The mask's lookup table per stack top (TokenTable._table) is only a faster way to compare every
    rule with the stack: both give the same masks and stacks along random masked rollouts."""
    import dataclasses

    table = domain.tokens
    compared = dataclasses.replace(table, lookup_limit=0)
    assert table._table(table._t(torch.device("cpu"))) is not None
    assert compared._table(compared._t(torch.device("cpu"))) is None
    gen = torch.Generator().manual_seed(3)
    fast, slow = table.initial_state(300), compared.initial_state(300)
    for _ in range(table.max_len):
        mask = table.mask(fast)
        assert torch.equal(mask, compared.mask(slow))
        if fast.done.all():
            break
        tok = torch.multinomial(mask.float() + fast.done.float()[:, None], 1, generator=gen)[:, 0]
        fast, slow = table.advance(fast, tok), compared.advance(slow, tok)
        for a, b in ((fast.depth, slow.depth), (fast.length, slow.length), (fast.cost, slow.cost)):
            assert torch.equal(a, b)
        rows = torch.arange(fast.stack.shape[1])[None, :] < fast.depth[:, None]
        assert torch.equal(fast.stack[rows], slow.stack[rows])
    assert fast.done.all()
