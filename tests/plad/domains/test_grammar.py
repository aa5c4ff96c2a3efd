"""The generic grammar machinery, on the 2D table and on a small prefix grammar."""
import pytest
import torch

from plad.domains.csg2d.tokens import token_table
from plad.domains.grammar import ProgramError, Token, TokenTable


def prefix_table(max_len: int = 30) -> TokenTable:
    """A 3D-CSG-like prefix grammar: union/diff take two shapes, a box takes six integers."""
    ints = [Token(str(i), pops=("N",)) for i in range(1, 4)]
    return TokenTable(
        tuple([Token("union", pops=("E",), pushes=("E", "E")), Token("diff", pops=("E",), pushes=("E", "E")),
               Token("box", pops=("E",), pushes=("N",) * 6)] + ints),
        start=("E",), max_len=max_len)


def test_symbol_costs_are_the_shortest_completions():
    assert token_table().symbol_cost == {"shape": 1}
    assert prefix_table().symbol_cost == {"E": 7, "N": 1}


def names_allowed(table, state):
    return {table.tokens[i].name for i in torch.nonzero(table.mask(state)[0]).flatten().tolist()}


def test_postfix_mask_follows_the_stack():
    t = token_table()
    s = t.initial_state(1)
    allowed = names_allowed(t, s)
    assert "$" not in allowed and "+" not in allowed and "c(32,32,16)" in allowed
    s = t.advance(s, torch.tensor([t.index("c(32,32,16)")]))
    allowed = names_allowed(t, s)
    assert "$" in allowed and "+" not in allowed
    s = t.advance(s, torch.tensor([t.index("s(32,32,16)")]))
    allowed = names_allowed(t, s)
    assert {"+", "*", "-"} <= allowed and "$" not in allowed
    s = t.advance(s, torch.tensor([t.index("-")]))
    s = t.advance(s, torch.tensor([t.index("$")]))
    assert bool(s.done[0]) and not t.mask(s).any()


def test_postfix_mask_enforces_the_length_cap():
    t = token_table()  # 13 tokens before $
    s = t.initial_state(1)
    draw = t.index("c(32,32,16)")
    for _ in range(7):
        s = t.advance(s, torch.tensor([draw]))
    # 7 shapes on the stack after 7 tokens: only operators can still finish within 13 + $
    allowed = names_allowed(t, s)
    assert allowed == {"+", "*", "-"}


def test_prefix_mask_reserves_room_for_arguments():
    t = prefix_table(max_len=14)  # "union box box" needs 1 + 7 + 7 = 15 tokens: only a box fits
    s = t.initial_state(1)
    assert names_allowed(t, s) == {"box"}
    t = prefix_table(max_len=15)
    s = t.initial_state(1)
    assert names_allowed(t, s) == {"box", "union", "diff"}
    s = t.advance(s, torch.tensor([t.index("union")]))
    assert names_allowed(t, s) == {"box"}
    s = t.advance(s, torch.tensor([t.index("box")]))
    assert names_allowed(t, s) == {"1", "2", "3"}


def test_check_names_the_offending_token():
    t = token_table()
    with pytest.raises(ProgramError) as err:
        t.check(t.encode(["c(32,32,16)", "+", "$"]))
    assert err.value.position == 1 and "'+'" in str(err.value)
    with pytest.raises(ProgramError, match="incomplete"):
        t.check(t.encode(["c(32,32,16)", "c(32,32,16)"]))
    with pytest.raises(ProgramError, match="left unused"):
        t.check(t.encode(["c(32,32,16)", "c(32,32,16)", "$"]))
    with pytest.raises(ProgramError, match="after the program is already complete"):
        t.check(t.encode(["c(32,32,16)", "$", "c(32,32,16)"]))
    with pytest.raises(ProgramError, match="longer than the cap"):
        t.check(t.encode(["c(32,32,16)"] + ["c(32,32,16)", "+"] * 7 + ["$"]))
    with pytest.raises(ProgramError, match="out of range"):
        t.check([10_000])
    with pytest.raises(ProgramError, match="empty"):
        t.check([])
    t.check(t.encode(["c(32,32,16)", "$"]))


def test_select_reorders_rows():
    t = token_table()
    s = t.advance(t.initial_state(2), torch.tensor([0, 1]))
    s2 = s.select(torch.tensor([1, 1, 0]))
    assert s2.stack.shape[0] == 3 and s2.stack[0, 0] == s.stack[1, 0]
    assert torch.equal(s2.length, torch.tensor([1, 1, 1]))


def test_duplicate_token_names_are_rejected():
    with pytest.raises(ValueError, match="duplicate"):
        TokenTable((Token("a", pushes=("E",)), Token("a", pops=("E",))), start=(), max_len=3)
