"""The grammar as data: a token table that drives validity, masks and the length cap.

Every domain describes its language as a *typed stack machine*. Each token
pops a sequence of grammar symbols from the top of a stack and pushes a
sequence of symbols; a program is complete when the stack becomes empty.
A token may have several rules (``alt``): the first rule whose pops match the
top of the stack applies. This lets a bounded counter live in the symbols
(ShapeAssembly: "the part being declared is cuboid n", so a reference
``cube_j`` is allowed only for j < n) without one token per context.
This one mechanism covers the notations the paper uses:

* postfix (2D CSG, CSGNet): the stack holds finished sub-shapes ``E``. A draw
  token pops nothing and pushes ``E``; an operator pops ``E E`` and pushes
  ``E``; the stop token ``$`` pops the last ``E`` (and is only allowed when
  that empties the stack).
* prefix (3D CSG): the stack holds what is still *expected*. It starts as
  ``[E]``; ``union`` pops ``E`` and pushes ``E E``; ``cuboid`` pops ``E`` and
  pushes six ``N``; an integer pops ``N``.

From the table alone the generic code derives, per symbol, the least number
of tokens that can remove it from the stack (a potential; see
:func:`_symbol_costs`). For a prefix, ``length + sum(cost(stack))`` is the
shortest complete program it can still become, so the decoding mask keeps
exactly the tokens after which that bound stays within ``max_len``: every
masked decode ends in a valid program. The contract test checks this bound
by random masked rollouts for every domain.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import torch

from plad.errors import BadInput


class ProgramError(BadInput, ValueError):
    """An invalid program (exit status 2); ``position`` is the 0-based index of the offending token."""

    def __init__(self, message: str, position: int | None = None, token: str | None = None):
        super().__init__(message)
        self.position = position
        self.token = token


@dataclass(frozen=True)
class Token:
    """One entry of a domain's token table.

    ``pops``/``pushes`` list grammar symbols bottom-to-top (the last one is the
    stack top). ``stop`` tokens may only be used when they empty the stack.
    ``kind`` and ``params`` are for the domain's own use (executor, printing).
    ``alt`` lists further ``(pops, pushes)`` rules; the first rule (the primary
    one first) whose pops match the stack top is the one applied.
    """

    name: str
    pops: tuple[str, ...] = ()
    pushes: tuple[str, ...] = ()
    stop: bool = False
    kind: str = ""
    params: tuple = ()
    alt: tuple[tuple[tuple[str, ...], tuple[str, ...]], ...] = ()

    @property
    def rules(self) -> tuple[tuple[tuple[str, ...], tuple[str, ...]], ...]:
        """All (pops, pushes) rules in the order they are tried."""
        return ((self.pops, self.pushes),) + tuple(self.alt)


@dataclass
class GrammarState:
    """Batched decoding state: one typed stack per sequence.

    stack:  (B, D) long, symbol ids bottom-to-top; entries at or above ``depth`` are junk.
    depth:  (B,) long, stack height.
    length: (B,) long, tokens emitted so far.
    cost:   (B,) long, sum of symbol costs on the stack (lower bound on tokens still needed).
    """

    stack: torch.Tensor
    depth: torch.Tensor
    length: torch.Tensor
    cost: torch.Tensor

    @property
    def done(self) -> torch.Tensor:
        """(B,) bool: the program is complete (the stack emptied after at least one token)."""
        return (self.depth == 0) & (self.length > 0)

    def select(self, index: torch.Tensor) -> GrammarState:
        """Reorder/duplicate rows (beam search keeps the surviving hypotheses)."""
        return GrammarState(self.stack[index], self.depth[index], self.length[index], self.cost[index])


def _symbol_costs(tokens: Sequence[Token], symbols: Sequence[str], ceiling: int) -> dict[str, int]:
    """Least tokens needed to remove each symbol from the stack.

    We look for the largest potential ``c`` with, for every token,
    ``sum c(pops) <= 1 + sum c(pushes)``: then ``sum c(stack)`` never
    overestimates the tokens still needed. Starting from an upper bound and
    tightening one constraint at a time converges to it for the grammars we
    use (2D: c(E) = 1; 3D: c(N) = 1, c(E) = 7). Symbols that can never be
    removed keep ``ceiling`` and therefore are never allowed on the stack.
    """
    cost = {s: ceiling for s in symbols}
    rules = [r for t in tokens for r in t.rules]
    for _ in range(4 * len(symbols) + 8):
        changed = False
        for pops, pushes in rules:
            if not pops:
                continue
            gain = 1 + sum(cost[s] for s in pushes)
            for i, s in enumerate(pops):
                others = sum(cost[o] for j, o in enumerate(pops) if j != i)
                bound = max(0, min(ceiling, gain - others))
                if bound < cost[s]:
                    cost[s] = bound
                    changed = True
        if not changed:
            break
    return cost


@dataclass
class TokenTable:
    """A domain's vocabulary and grammar.

    ``start`` is the initial stack (bottom-to-top); ``max_len`` caps the
    number of tokens of a program, stop token included.
    """

    tokens: tuple[Token, ...]
    start: tuple[str, ...]
    max_len: int
    #: most stack tops tabulated by :meth:`_table`; beyond it, rules are compared at every step
    lookup_limit: int = 1 << 16
    _by_name: dict[str, int] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.tokens = tuple(self.tokens)
        self._by_name = {}
        for i, t in enumerate(self.tokens):
            if t.name in self._by_name:
                raise ValueError(f"duplicate token name {t.name!r} in token table")
            self._by_name[t.name] = i
        names: list[str] = []
        for t in self.tokens:
            for pops, pushes in t.rules:
                for s in (*pops, *pushes):
                    if s not in names:
                        names.append(s)
        for s in self.start:
            if s not in names:
                names.append(s)
        self.symbols: tuple[str, ...] = tuple(names)
        self._sym = {s: i for i, s in enumerate(self.symbols)}
        self.symbol_cost = _symbol_costs(self.tokens, self.symbols, self.max_len + 1)
        # Stack height can never exceed the cap: every symbol costs >= 1 token
        # to remove, unless it has cost 0 (then it needs no slot bound anyway).
        self.max_depth = self.max_len + len(self.start)
        self._tensors: dict[torch.device, dict[str, torch.Tensor]] = {}

    # ---- plain (per-program) API -------------------------------------------------
    def __len__(self) -> int:
        return len(self.tokens)

    @property
    def names(self) -> list[str]:
        return [t.name for t in self.tokens]

    def index(self, name: str) -> int:
        try:
            return self._by_name[name]
        except KeyError:
            raise ProgramError(f"unknown token {name!r}", token=name) from None

    def has(self, name: str) -> bool:
        return name in self._by_name

    def check(self, ids: Sequence[int]) -> None:
        """Raise :class:`ProgramError` naming the first token that makes ``ids`` invalid."""
        stack = list(self.start)
        if not ids:
            raise ProgramError("empty program", position=0)
        for pos, i in enumerate(ids):
            if not 0 <= int(i) < len(self.tokens):
                raise ProgramError(f"token id {i} at position {pos} is out of range", position=pos)
            t = self.tokens[int(i)]
            if stack == [] and pos > 0:
                raise ProgramError(
                    f"token {pos} {t.name!r} comes after the program is already complete",
                    position=pos, token=t.name)
            rule = next(((pops, pushes) for pops, pushes in t.rules
                         if len(stack) >= len(pops) and tuple(stack[len(stack) - len(pops):]) == pops), None)
            if rule is None:
                need = " or ".join(" ".join(pops) or "nothing" for pops, _ in t.rules)
                raise ProgramError(
                    f"token {pos} {t.name!r} needs {need} on the stack, "
                    f"found {' '.join(stack) or 'an empty stack'}", position=pos, token=t.name)
            del stack[len(stack) - len(rule[0]):]
            stack.extend(rule[1])
            if t.stop and stack:
                raise ProgramError(
                    f"token {pos} {t.name!r} ends the program but {' '.join(stack)} is left unused",
                    position=pos, token=t.name)
            if pos + 1 > self.max_len:
                raise ProgramError(f"program is longer than the cap of {self.max_len} tokens",
                                   position=pos, token=t.name)
        if stack:
            raise ProgramError(
                f"program is incomplete: {' '.join(stack)} still expected after the last token",
                position=len(ids))

    # ---- batched (decoding) API ------------------------------------------------
    def _t(self, device: torch.device) -> dict[str, torch.Tensor]:
        """Per-(token, rule) tensors: pops (V, R, P) top first and -1 padded, push ids
        (V, R, Q), depth and cost deltas (V, R); rule 0 is the primary rule and
        ``used`` (V, R) marks the rule slots a token really has."""
        if device not in self._tensors:
            V = len(self.tokens)
            R = max(len(t.rules) for t in self.tokens) if self.tokens else 1
            P = max([len(p) for t in self.tokens for p, _ in t.rules] + [1])
            Q = max([len(q) for t in self.tokens for _, q in t.rules] + [1])
            pops = torch.full((V, R, P), -1, dtype=torch.long)
            pushes = torch.full((V, R, Q), -1, dtype=torch.long)
            n_pop = torch.zeros(V, R, dtype=torch.long)
            n_push = torch.zeros(V, R, dtype=torch.long)
            dcost = torch.zeros(V, R, dtype=torch.long)
            used = torch.zeros(V, R, dtype=torch.bool)
            stop = torch.zeros(V, dtype=torch.bool)
            for v, t in enumerate(self.tokens):
                for r, (tp, tq) in enumerate(t.rules):
                    for j, s in enumerate(reversed(tp)):
                        pops[v, r, j] = self._sym[s]
                    for j, s in enumerate(tq):
                        pushes[v, r, j] = self._sym[s]
                    n_pop[v, r], n_push[v, r] = len(tp), len(tq)
                    dcost[v, r] = sum(self.symbol_cost[s] for s in tq) - sum(self.symbol_cost[s] for s in tp)
                    used[v, r] = True
                stop[v] = t.stop
            self._tensors[device] = {
                k: x.to(device) for k, x in dict(
                    pops=pops, pushes=pushes, n_pop=n_pop, n_push=n_push, dcost=dcost, used=used,
                    stop=stop, sym_cost=torch.tensor([self.symbol_cost[s] for s in self.symbols]),
                ).items()}
        return self._tensors[device]

    def _tops(self, T: dict[str, torch.Tensor], state: GrammarState) -> torch.Tensor:
        """(B, P) the top P symbols of each stack, top first; -2 below the bottom."""
        P = T["pops"].shape[2]
        offs = torch.arange(P, device=state.stack.device)
        pos = state.depth[:, None] - 1 - offs[None, :]                      # (B, P)
        tops = torch.gather(state.stack, 1, pos.clamp(min=0))
        return torch.where(pos >= 0, tops, torch.full_like(tops, -2))

    def _match(self, T: dict[str, torch.Tensor], tops: torch.Tensor,
               tokens: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(applies, rule) by comparing stack tops (B, P) with every rule's pops: shapes (B, V),
        or (B,) for ``tokens`` (B,)."""
        if tokens is None:
            need, used, tops = T["pops"][None], T["used"][None], tops[:, None, None, :]   # (1, V, R, P)
        else:
            need, used, tops = T["pops"][tokens], T["used"][tokens], tops[:, None, :]     # (B, R, P)
        match = ((tops == need) | (need == -1)).all(dim=-1) & used          # (B, [V,] R)
        return match.any(dim=-1), match.int().argmax(dim=-1)

    def _table(self, T: dict[str, torch.Tensor]) -> dict[str, torch.Tensor] | None:
        """Everything a token does, per possible stack top, or None when there are too many tops.

        A rule depends only on the top P symbols, so with S symbols there are (S + 1)^P tops (one more
        value for "below the bottom"); for our grammars 9 (2D), a few (3D CSG) and 58 (ShapeAssembly,
        whose 30 alternative rules per token made comparing every rule at every step the mask's main
        cost). Per top (K of them) and token: applies, the rule, its depth and cost changes, (K, V) each.
        """
        if "key_applies" in T:
            return T
        P, base = T["pops"].shape[2], len(self.symbols) + 1
        if base ** P > self.lookup_limit:
            return None
        keys = torch.arange(base ** P, device=T["pops"].device)
        # key = sum_j (tops[:, j] mapped to 0..S) * base^j, "below the bottom" (-2) mapped to S
        tops = torch.stack([(keys // base ** j) % base for j in range(P)], 1)
        tops = torch.where(tops == base - 1, torch.full_like(tops, -2), tops)
        applies, rule = self._match(T, tops)                                # (K, V)
        ddepth, dcost = self._changes(T, rule)
        T.update(key_applies=applies, key_rule=rule, key_ddepth=ddepth, key_dcost=dcost,
                 key_weights=base ** torch.arange(P, device=rule.device))
        return T

    @staticmethod
    def _changes(T: dict[str, torch.Tensor], rule: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(depth change, cost change) of every token under its rule ``rule`` (B, V): (B, V) each."""
        vv = torch.arange(rule.shape[1], device=rule.device)[None, :]
        return T["n_push"][vv, rule] - T["n_pop"][vv, rule], T["dcost"][vv, rule]

    def _key(self, T: dict[str, torch.Tensor], state: GrammarState) -> torch.Tensor:
        """(B,) each stack top's row of :meth:`_table`."""
        tops = self._tops(T, state)
        tops = torch.where(tops < 0, torch.full_like(tops, len(self.symbols)), tops)
        return (tops * T["key_weights"]).sum(1)

    def _rule(self, T: dict[str, torch.Tensor], state: GrammarState,
              tokens: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(applies, rule): whether some rule of a token matches each stack top, and the
        first matching rule's index. Shapes (B, V) for all tokens, or (B,) for ``tokens`` (B,)."""
        if self._table(T) is None:
            return self._match(T, self._tops(T, state), tokens)
        key = self._key(T, state)
        if tokens is None:
            return T["key_applies"][key], T["key_rule"][key]
        return T["key_applies"][key, tokens], T["key_rule"][key, tokens]

    def initial_state(self, batch: int, device: torch.device | str = "cpu") -> GrammarState:
        device = torch.device(device)
        stack = torch.zeros(batch, self.max_depth + 1, dtype=torch.long, device=device)
        for j, s in enumerate(self.start):
            stack[:, j] = self._sym[s]
        cost = sum(self.symbol_cost[s] for s in self.start)
        return GrammarState(
            stack=stack,
            depth=torch.full((batch,), len(self.start), dtype=torch.long, device=device),
            length=torch.zeros(batch, dtype=torch.long, device=device),
            cost=torch.full((batch,), cost, dtype=torch.long, device=device),
        )

    def mask(self, state: GrammarState) -> torch.Tensor:
        """(B, V) bool: tokens that keep each prefix completable within ``max_len``.

        A finished row allows nothing. Vectorized over batch and vocabulary.
        """
        T = self._t(state.stack.device)
        new_len = state.length[:, None] + 1
        if self._table(T) is not None:
            key = self._key(T, state)
            match, ddepth, dcost = T["key_applies"][key], T["key_ddepth"][key], T["key_dcost"][key]   # (B, V)
        else:
            match, rule = self._rule(T, state)
            ddepth, dcost = self._changes(T, rule)
        new_depth = state.depth[:, None] + ddepth
        new_cost = state.cost[:, None] + dcost
        ok = match & (new_len + new_cost <= self.max_len) & (new_depth <= self.max_depth)
        ok &= ~T["stop"][None, :] | (new_depth == 0)
        ok &= ~state.done[:, None]
        return ok

    def advance(self, state: GrammarState, tokens: torch.Tensor) -> GrammarState:
        """Apply one token per row ((B,) long). Rows already done are left unchanged.

        The caller is expected to have respected :meth:`mask`; this does not re-check.
        """
        T = self._t(state.stack.device)
        live = ~state.done
        _, rule = self._rule(T, state, tokens)                              # (B,)
        n_pop, n_push = T["n_pop"][tokens, rule], T["n_push"][tokens, rule]
        base = state.depth - n_pop                                          # (B,)
        stack = state.stack.clone()
        Q = T["pushes"].shape[2]
        for j in range(Q):
            write = live & (j < n_push)
            col = (base + j).clamp(0, stack.shape[1] - 1)
            cur = torch.gather(stack, 1, col[:, None])[:, 0]
            val = torch.where(write, T["pushes"][tokens, rule, j], cur)
            stack.scatter_(1, col[:, None], val[:, None])
        return GrammarState(
            stack=stack,
            depth=torch.where(live, base + n_push, state.depth),
            length=torch.where(live, state.length + 1, state.length),
            cost=torch.where(live, state.cost + T["dcost"][tokens, rule], state.cost),
        )

    def encode(self, names: Iterable[str]) -> list[int]:
        return [self.index(n) for n in names]


def near_matrix(tokens: Sequence) -> torch.Tensor:
    """(V, V) bool: ``near[a, b]`` when token ``b`` is ``a`` or one grid step from it: the same kind, the same
    non-numeric parameters, and every numeric parameter at most one place apart in the sorted values that
    parameter takes over the kind's tokens (a token without parameters is near itself only)."""
    V = len(tokens)
    near = torch.eye(V, dtype=torch.bool)
    by_kind: dict[str, list[int]] = {}
    for i, t in enumerate(tokens):
        if t.params:
            by_kind.setdefault(t.kind, []).append(i)
    for ids in by_kind.values():
        params = [tokens[i].params for i in ids]
        if len({len(p) for p in params}) != 1:
            continue
        columns = []                                    # per parameter: (len(ids),) rank or exact value code
        for k in range(len(params[0])):
            values = [p[k] for p in params]
            numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
            # numeric: the value's place in order; otherwise any code will do (only equality counts)
            ranks = {v: r for r, v in enumerate(sorted(set(values)) if numeric else dict.fromkeys(values))}
            columns.append((numeric, torch.tensor([ranks[v] for v in values])))
        ok = torch.ones(len(ids), len(ids), dtype=torch.bool)
        for numeric, col in columns:
            diff = (col[:, None] - col[None, :]).abs()
            ok &= diff <= 1 if numeric else diff == 0
        index = torch.tensor(ids)
        near[index[:, None], index[None, :]] = ok
    return near


def near_targets(tokens: Sequence[Token], smoothing: float) -> torch.Tensor:
    """(V, V) float: row ``a`` the training target of token ``a`` when a near miss should cost less than a far
    one: ``1 - smoothing`` on ``a`` and ``smoothing`` shared evenly by the tokens one grid step from it
    (:func:`near_matrix`); a token with none (an operator, a stop) keeps its one-hot row. Each row sums to 1."""
    if not 0.0 <= smoothing < 1.0:
        raise ValueError(f"near smoothing {smoothing}: expected 0 <= smoothing < 1")
    near = near_matrix(tokens)
    eye = torch.eye(len(tokens), dtype=torch.float64)
    others = near.double() - eye                                   # (V, V) 1 where one step away
    count = others.sum(1, keepdim=True)
    spread = torch.where(count > 0, others / count.clamp(min=1), torch.zeros_like(others))
    keep = torch.where(count > 0, torch.full_like(count, 1.0 - smoothing), torch.ones_like(count))
    return (eye * keep + spread * smoothing).float()
