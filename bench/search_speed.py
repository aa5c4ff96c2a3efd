"""Search and network + refinement: the same programs, in how much CPU time, with and without the speedups.

Usage: ``python -m bench.search_speed [csg2d csg3d shapeassembly] [--efforts fast default] [--shapes 20] [--repeats 2]``

For each domain and effort level, on the first N prepared test shapes, one torch thread: search from scratch,
and refinement of the shipped network's programs (beam 10, each shape's best, decoded once outside the timing),
run alternately with every speedup of :data:`SPEEDUPS` switched off (the baseline: the path before them) and on,
``--repeats`` times each, in this one process on the same shapes. Prints the CPU seconds per shape of both (the
fastest repeat: the machine may be busy), their ratio, and whether the programs and values are identical (they
must be: a speedup changes no program). Last line: ``ratio <min over rows of baseline/new>``.
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import importlib
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import torch

from plad.data.files import load_prepared
from plad.domains import bits, get_domain
from plad.rewrite import refine, search, search_config


@contextlib.contextmanager
def _set(module: str, name: str, value: object) -> Iterator[None]:
    """``module.name = value`` for the duration, then back: a speedup's switch (the compiled kernels' is
    ``_COMPILED``, False: the path before them)."""
    found = importlib.import_module(module)
    saved = getattr(found, name)
    setattr(found, name, value)
    try:
        yield
    finally:
        setattr(found, name, saved)


@contextlib.contextmanager
def _scalar_popcount() -> Iterator[None]:
    """Bit counts in tensor arithmetic (SWAR), as before numpy's hardware popcount."""
    saved, bits._BITWISE_COUNT = bits._BITWISE_COUNT, None
    try:
        yield
    finally:
        bits._BITWISE_COUNT = saved


@contextlib.contextmanager
def _batched_csg3d() -> Iterator[None]:
    """Every 3D CSG batch through the batched stack machine, as before the per-program path
    (its primitive cache emptied, so the new path is timed with the cache it builds itself)."""
    executor = get_domain("csg3d").executor
    saved, executor.per_program = executor.per_program, False
    executor._primitives.clear()
    try:
        yield
    finally:
        executor.per_program = saved
        executor._primitives.clear()


@contextlib.contextmanager
def _batched_csg2d() -> Iterator[None]:
    """Every 2D CSG batch through the batched stack machine, as before the per-program path: the domain's executor
    and the rewrite space's extended copy of it (pseudo draws), made once per process."""
    domain = get_domain("csg2d")
    executors = (domain.executor, domain.rewrite._extended)
    saved = [e.per_program for e in executors]
    for e in executors:
        e.per_program = False
    try:
        yield
    finally:
        for e, value in zip(executors, saved):
            e.per_program = value


@contextlib.contextmanager
def _reference_boxes() -> Iterator[None]:
    """The insertion's residual boxes with the summed-volume table and box growing before they were made fast
    (the frozen copy in tests/reference/boxes_v0.py)."""
    from plad.domains import boxes
    from tests.reference import boxes_v0

    saved = boxes.prefix_sums, boxes.grow_box
    boxes.prefix_sums, boxes.grow_box = boxes_v0.prefix_sums, boxes_v0.grow_box
    try:
        yield
    finally:
        boxes.prefix_sums, boxes.grow_box = saved


@contextlib.contextmanager
def _torch_sweeps() -> Iterator[None]:
    """The exact Chamfer's distance-transform sweeps and masked sums in torch whatever the batch, as before."""
    import importlib

    chamfer = importlib.import_module("plad.metrics.chamfer")
    saved = chamfer._NUMPY_SWEEP, chamfer._NUMPY_SUMS
    chamfer._NUMPY_SWEEP = chamfer._NUMPY_SUMS = 0
    try:
        yield
    finally:
        chamfer._NUMPY_SWEEP, chamfer._NUMPY_SUMS = saved


@contextlib.contextmanager
def _torch_screen() -> Iterator[None]:
    """2D's screen scores in torch, as before their numpy path."""
    space = get_domain("csg2d").rewrite
    saved, space.numpy_screen = space.numpy_screen, False
    try:
        yield
    finally:
        space.numpy_screen = saved


@contextlib.contextmanager
def _original_shapeassembly_executor() -> Iterator[None]:
    """ShapeAssembly's run_batch as before its prefix cache and grid-aligned voxelizing (the frozen copy in
    tests/reference/shapeassembly_v0.py); the fast one's prefix cache emptied after, so it is timed with the
    cache it builds itself."""
    from plad.domains.shapeassembly import ShapeAssembly, cuboids
    from tests.reference import shapeassembly_v0

    own = ShapeAssembly.run_batch
    ShapeAssembly.run_batch = lambda self, programs: shapeassembly_v0.run_batch(
        programs.tolist() if isinstance(programs, torch.Tensor) else programs)
    try:
        yield
    finally:
        ShapeAssembly.run_batch = own
        cuboids.clear_cache()


@contextlib.contextmanager
def _reference_placements() -> Iterator[None]:
    """ShapeAssembly insertion's attachment placements as before they were made fast (the frozen copy)."""
    from plad.domains.shapeassembly.rewrite import ShapeAssemblyRewrite
    from tests.reference.shapeassembly_placements_v0 import placements

    own = ShapeAssemblyRewrite._placements
    ShapeAssemblyRewrite._placements = lambda self, cuboids, dims, center: placements(cuboids, dims, center)
    try:
        yield
    finally:
        ShapeAssemblyRewrite._placements = own


#: each speedup by name, with the context that switches it off (the baseline runs with all of them off)
SPEEDUPS: dict[str, Callable[[], contextlib.AbstractContextManager]] = {
    "numpy popcount in the 2D and 3D screens": _scalar_popcount,
    "3D CSG programs run one at a time on the CPU (numpy, cached primitives)": _batched_csg3d,
    "3D CSG's one-at-a-time path and unpack compiled (numba)":
        functools.partial(_set, "plad.domains.csg3d.executor", "_COMPILED", False),
    "2D CSG programs run one at a time on the CPU (a canvas as one Python integer)": _batched_csg2d,
    "3D residual boxes: int32 summed-volume table, boxes grown face by face": _reference_boxes,
    "2D exact Chamfer: the sweeps and masked sums of a few images in numpy": _torch_sweeps,
    "2D exact Chamfer compiled (numba): Canny at boundary pixels, distances at the other edges only":
        functools.partial(_set, "plad.metrics.chamfer", "_COMPILED", False),
    "2D screen scores in numpy": _torch_screen,
    "ShapeAssembly's executor: prefix cache, grid-aligned voxelizing": _original_shapeassembly_executor,
    "ShapeAssembly insertion's placements: per-cuboid moves cached, norms without checks": _reference_placements,
    "ShapeAssembly's voxel counts compiled (numba), voxel by voxel over each cuboid":
        functools.partial(_set, "plad.data.datasets.partnet.voxels", "_COMPILED", False),
    "IoU's bit counts read in place (rows of whole chunks of words, no zero padding copied)":
        functools.partial(_set, "plad.metrics", "_chunk_words", lambda row_bytes: None),
}


@contextlib.contextmanager
def _baseline() -> Iterator[None]:
    with contextlib.ExitStack() as stack:
        for off in SPEEDUPS.values():
            stack.enter_context(off())
        yield


def _timed(run: Callable[[], object]) -> tuple[float, object]:
    start = time.process_time()
    out = run()
    return time.process_time() - start, out


def _same(a, b) -> bool:
    return a.programs == b.programs and torch.equal(a.values, b.values)


def compare(run: Callable[[], object], repeats: int) -> tuple[float, float, bool]:
    """(baseline CPU seconds, new CPU seconds, identical): ``run`` (a search or refinement returning a
    ``Result``) with every speedup off and on, alternately ``repeats`` times; the fastest repeat of each."""
    base_s, new_s, identical = [], [], True
    for _ in range(repeats):
        with _baseline():
            seconds, before = _timed(run)
        base_s.append(seconds)
        seconds, after = _timed(run)
        new_s.append(seconds)
        identical &= _same(before, after)
    return min(base_s), min(new_s), identical


def network_programs(domain, targets: torch.Tensor) -> list[list[int]] | None:
    """The shipped network's best-of-beam program per shape (beam 10), or None without a shipped network."""
    from plad.model.checkpoint import load_model
    from plad.model.decode import infer_programs
    from plad.shipped import shipped_model

    shipped = shipped_model(domain.name)
    if shipped is None:
        return None
    model, _ = load_model(shipped.checkpoint, expect_domain=domain.name)
    return [list(p) for p in infer_programs(model, domain, targets, beam=10).programs]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("domains", nargs="*", default=["csg2d", "csg3d", "shapeassembly"])
    parser.add_argument("--efforts", nargs="+", default=["fast", "default"])
    parser.add_argument("--shapes", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--prepared", default="data/prepared")
    args = parser.parse_args(argv)
    from plad import jit

    jit.load()   # the compiled kernels from the first call, as a long process runs them once it has earned them
    torch.set_num_threads(1)
    print("speedups (off in the baseline): " + "; ".join(SPEEDUPS))

    worst = float("inf")
    for name in args.domains:
        domain = get_domain(name)
        path = Path(args.prepared) / f"{name}.npz"
        if not path.is_file():
            raise SystemExit(f"{path}: no such prepared dataset (run the prepare stages first)")
        targets = torch.from_numpy(load_prepared(path, "test")[: args.shapes])
        search(domain, targets[:2], search_config(domain, effort="fast"))          # warm-up (lookup tables)
        starts = network_programs(domain, targets)
        for effort in args.efforts:
            cfg = search_config(domain, effort=effort)
            paths = {"search": functools.partial(search, domain, targets, cfg)}
            if starts is not None:
                paths["network + refinement"] = functools.partial(refine, domain, starts, targets, cfg.refine)
            for label, run in paths.items():
                base, new, identical = compare(run, args.repeats)
                base, new = base / len(targets), new / len(targets)
                worst = min(worst, base / new)
                print(f"{name} {effort:8s} {label:21s} baseline {base:.3f} s/shape, new {new:.3f} s/shape: "
                      f"ratio {base / new:.2f}, identical programs and values: {identical}")
    print(f"ratio {worst:.2f}")


if __name__ == "__main__":
    main()
