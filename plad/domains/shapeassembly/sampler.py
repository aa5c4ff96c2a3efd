"""Synthetic discretized ShapeAssembly programs for supervised pretraining (paper supplement).

A program has K part blocks, K uniform in 2..8 (balanced: equal numbers of
programs per K). Each block declares a cuboid, then one move block (one
Attach 40%, two Attaches 25%, a Squeeze 35%), then a symmetry block
(Reflect 25%, Translate 10%, none 65%; reflections are more common than
translations). Parameters follow simple heuristics of our own, in the
spirit of the supplement:

* bbox height: discrete normal around 20/32 (sd 8), within 8..31;
* cuboid dims: discrete normal around 8/32 (sd 6), within 2..30;
* references: uniform over bbox and the cuboids declared before (a cuboid
  never attaches to itself; a second reference differs from the first);
* faces: against the bbox only top or bot (the part hangs from the top or
  stands on the bottom); against a cuboid left/right/back/front 1/8 each and
  top/bot 1/4 each, a second face differs from the first;
* in-face points: the mover's is its face center half of the time, else a
  discrete normal around the center (sd 2); the target's is uniform half of
  the time, else the same normal;
* symmetry axis X 60%, Y 20%, Z 20%; copies 1..4; translate distance 4..28/32.

Every candidate is executed and rejected unless each cuboid (copies
included) owns at least 8 voxels of the 32^3 grid that no other cuboid
occupies, or if it is longer than the 100-token cap. Equal numbers of
programs per K come from :mod:`plad.domains.synthetic`.

The ``inside`` sampler (beyond the paper; params ``synthesize.shapeassembly.sampler``) draws the same part
blocks but redraws each one until it and its copies lie in the bbox, and makes 70% of the bboxes full
height (31/32). The paper's sampler puts some part outside the bbox in 98% of its programs (of 2,000
drawn: 1.8% inside), so the grid clips them and neither the bbox height nor a clipped part's size can be
read from the shape; PartNet's parts lie in their bbox, and 74% of the voxelized test shapes fill the
grid's height (of the first 300).
"""
from __future__ import annotations

import numpy as np
import torch

from plad.data.datasets.partnet.execute import ExecutionError
from plad.domains.grammar import ProgramError
from plad.domains.shapeassembly.cuboids import token_cuboids
from plad.domains.shapeassembly.tokens import MAX_LEN, RES, token_table
from plad.domains.synthetic import stratified_rejection_sample

MIN_PARTS, MAX_PARTS = 2, 8
MIN_UNIQUE_VOXELS = 8
_MOVES = (("attach",), ("attach", "attach"), ("squeeze",))
_MOVE_P = (0.4, 0.25, 0.35)
_SYMS = ("reflect", "translate", None)
_SYM_P = (0.25, 0.1, 0.65)
_FACES = ("left", "right", "bot", "top", "back", "front")
_FACE_P = np.array([1, 1, 2, 2, 1, 1], dtype=float) / 8
_AXIS_P = (0.6, 0.2, 0.2)


def _normal_int(rng: np.random.Generator, mean: float, sd: float, lo: int, hi: int) -> int:
    """Discrete normal, resampled until it falls in [lo, hi]."""
    while True:
        v = int(round(mean + sd * rng.standard_normal()))
        if lo <= v <= hi:
            return v


def _bbox_height(rng: np.random.Generator, tall: bool) -> int:
    """``START h``: a discrete normal around 20/32 (sd 8) in 8..31; ``tall``: 31 for 70% of programs."""
    if tall and rng.random() < 0.7:
        return 31
    return _normal_int(rng, 20, 8, 8, 31)


def _random_part(c: int, rng: np.random.Generator) -> list[str]:
    """The tokens of part block c (0-based): ``Cuboid l h w``, its moves, maybe a symmetry."""
    out = ["Cuboid"] + [str(_normal_int(rng, 8, 6, 2, 30)) for _ in range(3)]
    targets = ["bbox"] + [f"cube{j}" for j in range(c)]
    move = _MOVES[rng.choice(3, p=_MOVE_P)]
    used_target, used_face = None, None

    def target() -> str:
        nonlocal used_target
        pool = [t for t in targets if t != used_target] or targets
        used_target = pool[rng.integers(len(pool))]
        return used_target

    def face(against: str) -> str:
        nonlocal used_face
        p = np.array([0, 0, 0.5, 0.5, 0, 0]) if against == "bbox" else _FACE_P.copy()
        if used_face is not None and p.sum() > p[_FACES.index(used_face)]:
            p[_FACES.index(used_face)] = 0
        used_face = _FACES[rng.choice(6, p=p / p.sum())]
        return used_face

    def fpos(centered: bool) -> str:
        if rng.random() < 0.5:
            i, j = (5, 5) if centered else rng.integers(1, 10, size=2)
        else:
            i, j = _normal_int(rng, 5, 2, 1, 9), _normal_int(rng, 5, 2, 1, 9)
        return f"fpos_{i}_{j}"

    if move[0] == "squeeze":
        t1, t2 = target(), target()
        out += ["Squeeze", t1, t2, face(t1), fpos(False)]
    else:
        for _ in move:
            t = target()
            out += ["Attach", t, face(t), fpos(True), fpos(False)]
    sym = _SYMS[rng.choice(3, p=_SYM_P)]
    axis = "XYZ"[rng.choice(3, p=_AXIS_P)]
    if sym == "reflect":
        out += ["Reflect", axis]
    elif sym == "translate":
        out += ["Translate", axis, f"snum_{rng.integers(1, 5)}", str(rng.integers(4, 29))]
    return out


def _random_program(k: int, rng: np.random.Generator) -> list[str]:
    """The paper's sampler: k part blocks drawn independently (parts may leave the bbox and the grid)."""
    out = ["START", str(_bbox_height(rng, tall=False))]
    for c in range(k):
        out += _random_part(c, rng)
    return out + ["END"]


def _inside(tokens: list[str], table, tol: float = 0.5 / RES) -> bool:
    """Whether every cuboid of ``tokens + END`` (copies included) lies in the bbox, within half a voxel."""
    try:
        c = token_cuboids(table.encode(tokens + ["END"]))
    except (ExecutionError, ProgramError):
        return False
    if not np.isfinite(c).all():
        return False
    centre, axes, half = c[:, 0:3], c[:, 3:12].reshape(-1, 3, 3), np.abs(c[:, 12:15]) / 2
    axes = axes / np.linalg.norm(axes, axis=2, keepdims=True)
    reach = np.abs(centre) + (half[:, :, None] * np.abs(axes)).sum(1)        # (n, 3) axis-aligned half-extent
    limit = np.array([0.5, int(tokens[1]) / RES / 2, 0.5]) + tol
    return bool((reach <= limit).all())


def _inside_program(k: int, rng: np.random.Generator, table, tries: int = 30) -> list[str] | None:
    """A program of k part blocks whose cuboids all lie in its bbox, as PartNet's parts do (beyond the paper).

    Each part block is redrawn (at most ``tries`` times) until the program so far stays in the bbox; moving a
    later part never moves an earlier one, so the check is per part. None if a part never fits.
    """
    out = ["START", str(_bbox_height(rng, tall=True))]
    for c in range(k):
        for _ in range(tries):
            part = _random_part(c, rng)
            if len(out) + len(part) + 1 <= MAX_LEN and _inside(out + part, table):
                out += part
                break
        else:
            return None
    return out + ["END"]


def sample_programs(domain, n: int, rng: np.random.Generator, min_parts: int = MIN_PARTS,
                    max_parts: int = MAX_PARTS, batch: int = 512, inside: bool = False) -> list[list[int]]:
    """``n`` valid programs (token ids) satisfying the 8-unique-voxel rule, uniform over the part count.

    ``inside``: the parts sampler (:func:`_inside_program`) instead of the paper's.
    """
    table = token_table()

    def draw(k: int, rng: np.random.Generator) -> list[str] | None:
        return _inside_program(k, rng, table) if inside else _random_program(k, rng)

    def propose(wanted: dict[int, int], rates, rng: np.random.Generator) -> tuple[list[int], list[list[int]]]:
        ks, progs = [], []
        for k, missing in wanted.items():
            for _ in range(min(batch, max(16, 2 * missing))):
                tokens = draw(k, rng)
                if tokens is None:
                    continue
                ids = table.encode(tokens)
                if len(ids) <= MAX_LEN:
                    ks.append(k)
                    progs.append(ids)
        return ks, progs

    def accept(progs: list[list[int]]) -> list[bool]:
        _, unique, owner, ok = domain.run_batch(progs)
        # per program: the fewest voxels any of its cuboids owns alone
        fewest = torch.full((len(progs),), 1 << 30, dtype=torch.long)
        fewest.scatter_reduce_(0, owner, unique, reduce="amin")
        return (ok & (fewest >= MIN_UNIQUE_VOXELS)).tolist()

    return stratified_rejection_sample(n, rng, range(min_parts, max_parts + 1), propose, accept)
