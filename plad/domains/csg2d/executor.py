"""Batched 2D CSG executor on bit-packed canvases.

Every draw token is a fixed 64 x 64 bitmap, so the vocabulary is rendered once
and a program is a sequence of boolean operations on those bitmaps. A canvas
row of 64 pixels is packed into one int64 word (bit c = column c), so one
canvas is 64 words and a union/intersection/difference of two canvases is 64
bitwise operations: about 64 times less memory traffic than bool tensors.
All programs of a batch step through their tokens together; a program's
stack lives in a (B, S, 64) int64 tensor.
"""
from __future__ import annotations

import numpy as np
import torch

from plad.domains.csg2d.tokens import CANVAS, render_primitive, token_table
from plad.domains.grammar import TokenTable

# kind codes per token
_PAD, _DRAW, _OP, _STOP = 0, 1, 2, 3
# With a second-from-top and b top, every operator is
# result = (a & (b ^ X)) | (b & Y) for per-operator masks X, Y (all-ones or zero):
# union X=Y=1 gives (a & ~b) | b; intersection X=Y=0 gives a & b; difference X=1, Y=0.
_MASKS = {"union": (1, 1), "intersection": (0, 0), "difference": (1, 0)}


def pack(canvases: torch.Tensor) -> torch.Tensor:
    """bool (..., 64, 64) -> int64 (..., 64); bit c of word r is pixel [r, c]."""
    bits = canvases.to(torch.uint8).reshape(*canvases.shape[:-1], 8, 8)
    weights = (1 << torch.arange(8, dtype=torch.uint8, device=canvases.device))
    as_bytes = (bits * weights).sum(dim=-1, dtype=torch.uint8)          # (..., 64, 8)
    return as_bytes.contiguous().view(torch.int64).squeeze(-1)


_BYTE_LUT: dict[torch.device, torch.Tensor] = {}


def unpack(words: torch.Tensor) -> torch.Tensor:
    """int64 (..., 64) -> bool (..., 64, 64), the inverse of :func:`pack`."""
    dev = words.device
    if dev not in _BYTE_LUT:
        # byte value -> its 8 bits as 8 bytes of 0/1, stored as one int64
        b = torch.arange(256)
        bits = ((b[:, None] >> torch.arange(8)) & 1).to(torch.uint8)
        _BYTE_LUT[dev] = bits.contiguous().view(torch.int64).squeeze(1).to(dev)
    as_bytes = words.contiguous().view(torch.uint8).reshape(-1)
    out = torch.index_select(_BYTE_LUT[dev], 0, as_bytes.int())
    return out.view(torch.uint8).view(torch.bool).reshape(*words.shape, CANVAS)


# On the CPU, programs run one at a time (:meth:`Executor._run_each`): a search executes most of its programs in
# batches of 1-63, where the batched path's tensor operations per token cost more than the work, and one at a
# time is also faster on sampled programs at every batch size measured (16-4,096: 3-6 us a program once its
# integers are built, batched 8-166).
_UNION, _INTER, _DIFF = 0, 1, 2


class Executor:
    """Executes padded batches of token ids of a :class:`TokenTable` of 2D CSG."""

    def __init__(self, table: TokenTable | None = None, per_program: bool = True):
        self.table = table or token_table()
        #: on the CPU, run program by program (False: the batched path everywhere); the same bits
        self.per_program = per_program
        self._each: tuple[list[int], list[int], list[int]] | None = None
        V = len(self.table)
        self.max_stack = self.table.max_len // 2 + 1
        kind = torch.zeros(V, dtype=torch.long)
        masks = torch.zeros(V, 2, dtype=torch.long)
        bitmaps = torch.zeros(V, CANVAS, CANVAS, dtype=torch.bool)
        for v, t in enumerate(self.table.tokens):
            if t.kind == "draw":
                kind[v] = _DRAW
                bitmaps[v] = torch.from_numpy(render_primitive(*t.params))
            elif t.kind in _MASKS:
                kind[v] = _OP
                masks[v] = torch.tensor(_MASKS[t.kind])
            elif t.stop:
                kind[v] = _STOP
        self._cpu = {"kind": kind, "masks": -masks, "bitmaps": pack(bitmaps)}  # -1 = all bits set
        self._dev: dict[torch.device, dict[str, torch.Tensor]] = {}

    def _tables(self, device: torch.device) -> dict[str, torch.Tensor]:
        if device not in self._dev:
            self._dev[device] = {k: v.to(device) for k, v in self._cpu.items()}
        return self._dev[device]

    def extended(self, canvases: torch.Tensor) -> Executor:
        """A copy that also draws ``canvases`` (K, 64, 64) bool as pseudo draw tokens V .. V+K-1.

        The pseudo tokens are not in the vocabulary; rewriting uses an empty and
        a full canvas to find how a program's output depends on one of its draws.
        """
        out = object.__new__(Executor)
        out.table, out.max_stack = self.table, self.max_stack
        K = canvases.shape[0]
        c = self._cpu
        out._cpu = {"kind": torch.cat([c["kind"], torch.full((K,), _DRAW, dtype=torch.long)]),
                    "masks": torch.cat([c["masks"], torch.zeros(K, 2, dtype=torch.long)]),
                    "bitmaps": torch.cat([c["bitmaps"], pack(canvases)])}
        out._dev = {}
        out.per_program, out._each = self.per_program, None
        return out

    @property
    def packed_bitmaps(self) -> torch.Tensor:
        """(V, 64) int64: the rendered vocabulary, bit-packed (zero rows for non-draw tokens)."""
        return self._cpu["bitmaps"]

    @property
    def bitmaps(self) -> torch.Tensor:
        """(V, 64, 64) bool: the rendered vocabulary (all-False rows for non-draw tokens)."""
        return unpack(self._cpu["bitmaps"])

    def run_packed(self, programs: torch.Tensor, check_degenerate: bool = False,
                   chunk: int = 2048) -> tuple[torch.Tensor, torch.Tensor]:
        """programs (B, L) long -> (canvases int64 (B, 64), degenerate (B,) bool).

        ``degenerate`` (computed only with ``check_degenerate``) flags programs
        in which some operator's result equals one of its operands (a wasted
        operation). Each row must be a valid program ending with ``$``;
        whatever follows ``$`` is ignored.
        """
        if self.per_program and programs.device.type == "cpu" and programs.shape[0] > 0:
            each = self._run_each(programs, check_degenerate)
            if each is not None:
                return each
        T = self._tables(programs.device)
        kinds = T["kind"][programs]                                            # (B, L)
        # tokens before the first $; rows sorted longest first so that at step t
        # the rows still running are a prefix of the batch (contiguous slices)
        lengths = (kinds != _STOP).long().cumprod(dim=1).sum(dim=1)
        order = torch.argsort(lengths, descending=True, stable=True)
        words = torch.empty(programs.shape[0], CANVAS, dtype=torch.int64, device=programs.device)
        flags = torch.zeros(programs.shape[0], dtype=torch.bool, device=programs.device)
        # chunks keep each stack tensor in cache
        for start in range(0, programs.shape[0], chunk):
            rows = order[start:start + chunk]
            w, f = self._run_sorted(programs[rows], kinds[rows], lengths[rows].tolist(), check_degenerate)
            words[rows] = w
            flags[rows] = f
        return words, flags

    def __getstate__(self) -> dict:
        # the per-program path's integers are rebuilt on first use in another process
        return {**self.__dict__, "_each": None}

    def _run_each(self, programs: torch.Tensor, check_degenerate: bool) -> tuple[torch.Tensor, torch.Tensor] | None:
        """:meth:`run_packed` one program at a time (CPU): a canvas as one 4,096-bit Python integer (bit 64 r + c
        is pixel [r, c], the packed words' bits in little-endian order), so an operator is one integer operation
        and the bits are the batched path's. None where a row is not a well-formed program (a token that neither
        draws nor operates before its ``$``, an operator without two operands, more than one canvas left): the
        batched path defines what such a row gives."""
        if self._each is None:
            words = self._cpu["bitmaps"].numpy()
            masks = self._cpu["masks"].tolist()
            op = {(-1, -1): _UNION, (0, 0): _INTER, (-1, 0): _DIFF}
            self._each = (self._cpu["kind"].tolist(), [op.get(tuple(m), -1) for m in masks],
                          [int.from_bytes(w.astype("<i8").tobytes(), "little") for w in words])
        kinds, ops, canvases = self._each
        n_tokens = len(kinds)
        results, flags = [], []
        for row in programs.tolist():
            stack: list[int] = []
            degenerate = False
            for tok in row:
                if not 0 <= tok < n_tokens:
                    return None
                kind = kinds[tok]
                if kind == _DRAW:
                    stack.append(canvases[tok])
                    continue
                if kind == _STOP:
                    break
                if kind != _OP or len(stack) < 2:
                    return None
                b = stack.pop()                                   # the top
                a = stack.pop()                                   # below it: the first operand
                code = ops[tok]
                res = a | b if code == _UNION else a & b if code == _INTER else a & ~b
                degenerate = degenerate or res == a or res == b
                stack.append(res)
            if len(stack) != 1:
                return None
            results.append(stack[0])
            flags.append(degenerate and check_degenerate)
        data = b"".join(c.to_bytes(CANVAS * 8, "little") for c in results)
        words = torch.from_numpy(np.frombuffer(data, dtype="<i8").astype(np.int64).reshape(-1, CANVAS))
        return words, torch.tensor(flags, dtype=torch.bool)

    def _run_sorted(self, programs: torch.Tensor, kinds: torch.Tensor, lengths: list[int],
                    check_degenerate: bool) -> tuple[torch.Tensor, torch.Tensor]:
        T = self._tables(programs.device)
        B = programs.shape[0]
        S = self.max_stack
        dev = programs.device
        # The top of each stack is kept apart in ``top``; ``stack`` holds the
        # entries below it. Slot S is scratch: rows with nothing to store write there.
        top = torch.zeros(B, CANVAS, dtype=torch.int64, device=dev)
        stack = torch.zeros(B, S + 1, CANVAS, dtype=torch.int64, device=dev)
        below_depth = torch.zeros(B, dtype=torch.long, device=dev)            # entries under the top
        degenerate = torch.zeros(B, dtype=torch.bool, device=dev)
        n = B
        for t in range(lengths[0] if lengths else 0):
            while lengths[n - 1] <= t:                                         # rows that have finished
                n -= 1
            tok, kind = programs[:n, t], kinds[:n, t]
            is_draw = kind == _DRAW
            is_op = ~is_draw
            cur, bd = top[:n], below_depth[:n]
            if t > 0:  # draws push the old top below it
                slot = torch.where(is_draw, bd, torch.full_like(bd, S))
                stack[:n].scatter_(1, slot[:, None, None].expand(n, 1, CANVAS), cur[:, None, :])
            below = torch.gather(stack[:n], 1, (bd - 1).clamp(min=0)[:, None, None].expand(n, 1, CANVAS))[:, 0]
            xy = T["masks"][tok]                                               # (n, 2)
            result = (below & (cur ^ xy[:, 0:1])) | (cur & xy[:, 1:2])
            if check_degenerate:
                degenerate[:n] |= is_op & ((result == below).all(dim=1) | (result == cur).all(dim=1))
            top[:n] = torch.where(is_draw[:, None], T["bitmaps"][tok], result)
            below_depth[:n] = bd + (is_draw & (t > 0)).long() - is_op.long()
        return top, degenerate

    def __call__(self, programs: torch.Tensor) -> torch.Tensor:
        """programs (B, L) long -> bool canvases (B, 64, 64)."""
        return unpack(self.run_packed(programs)[0])
