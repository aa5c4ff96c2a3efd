"""Inference on the user's own shapes: a model, shapes in, programs and files out (``plad infer``).

The model is a checkpoint file or an MLflow model URI (``models:/plad-<domain>@champion``,
``models:/plad-<domain>/3``, ``runs:/<id>/model``); without one, the registered
champion of a configured MLflow store, else the model shipped with the package
(:mod:`plad.serve.resolve`). Every run writes into a folder of its own,
``<out>/<UTC time>-<process id>/`` (:func:`new_run_dir`; created with
``exist_ok=False``), so runs into the same ``--out``, at once or one after
another, never overwrite each other's files or rows. For every input shape
the run's folder gets:

* ``<stem>.txt``: the program text (the domain's text form);
* ``<stem>.png``: input and reconstruction side by side (3D: three depth views each);
* ``<stem>.input.npy`` / ``<stem>.recon.npy``: the target shape as the model saw it
  (fitted to the canvas or voxelized) and the program's execution, so that
  ``plad score DOMAIN --pred <stem>.recon.npy --target <stem>.input.npy``
  reproduces the metric;
* the domain's exports (2D CSG: ``.svg``; 3D CSG: ``.ply`` and ``.scad``;
  ShapeAssembly: ``.ply``);

and the run's ``results.csv`` has a row per input (file, status, metric,
program, notes or error). A bad input is reported in its row and does not stop
the others.
"""
from __future__ import annotations

import contextlib
import csv
import io
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from tqdm import tqdm

from plad.config import MAX_BEAM_ROWS
from plad.data.inputs import Item
from plad.data.pictures import save_comparison, save_npy
from plad.device import torch_threads
from plad.domains.base import Domain
from plad.eval.refinement import Refinement, refinement  # noqa: F401 (plad infer's levels; also imported from here)
from plad.fsutil import WriteError, atomic_write_text, cause_of
from plad.model.checkpoint import CheckpointError, load_model
from plad.model.decode import infer_programs
from plad.model.network import PLADNet
from plad.serve.resolve import ModelError, resolve

if TYPE_CHECKING:  # pragma: no cover
    from plad.rewrite import RefineConfig


def resolve_model(domain: str, model: str | None, device: torch.device) -> tuple[PLADNet, str]:
    """(model in eval mode, where it came from), chosen by :func:`plad.serve.resolve.resolve`: ``model``, else the
    configured store's champion, else the shipped model. Raises :class:`ModelError` with a one-line reason."""
    choice = resolve(domain, model)
    try:
        net = load_model(choice.path, device, expect_domain=domain)[0]
    except CheckpointError as err:   # name the URI, not the temporary download
        raise ModelError(f"{choice.ref}: {str(err).removeprefix(f'{choice.path}: ')}"
                         if choice.uri else str(err)) from None
    return net, choice.ref + "".join(f" ({note})" for note in choice.notes)


def new_run_dir(out: str | Path) -> Path:
    """A new folder for one run under ``out``: ``<UTC time>-<process id>`` (``-2``, ... if taken).

    ``mkdir(exist_ok=False)`` is atomic: two runs never get the same folder.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"{time.strftime('%Y%m%d-%H%M%S', time.gmtime())}-{os.getpid()}"
    for k in range(1, 1000):
        path = out / (stem if k == 1 else f"{stem}-{k}")
        try:
            path.mkdir(exist_ok=False)
            return path
        except FileExistsError:
            continue
    raise FileExistsError(f"{out}: no free run folder named {stem}-N")


@dataclass
class Result:
    item: Item
    program: str | None = None
    value: float | None = None
    outputs: tuple[str, ...] = ()
    #: seconds spent on this shape (wall): its share of its batch's inference and refinement
    seconds: float = 0.0
    #: why some of its output files could not be written (e.g. a full disk; one line), None when all were: its
    #: program and value are still the result (printed, and in ``results.csv``), and the files that were written
    #: are kept (every file is written atomically: none is half written)
    write_error: str | None = None

    @property
    def ok(self) -> bool:
        return self.item.error is None


def _write_outputs(domain: Domain, item: Item, ids: list[int], recon: np.ndarray, value: float,
                   out: Path, written: list[str] | None = None) -> tuple[str, ...]:
    """Write a shape's files (each atomically), appending each to ``written`` once it is on disk."""
    written = [] if written is None else written
    # every file is <run folder>/<name><suffix>: names are safe and unique (plad.data.inputs.read_inputs)
    # and nothing is derived with with_suffix, which would cut a name like "part.left" to "part"
    stem = out / item.name
    program = domain.format(ids)
    files = [out / f"{item.name}{suffix}" for suffix in (".txt", ".png", ".input.npy", ".recon.npy")]
    atomic_write_text(files[0], program + "\n")
    written.append(str(files[0]))
    metric = domain.metric
    save_comparison([("input", item.shape), (f"program ({metric.name} {value:.3f})", recon)], files[1],
                    title=_wrap(program))
    written.append(str(files[1]))
    save_npy(item.shape, files[2])
    written.append(str(files[2]))
    save_npy(recon, files[3])
    written.append(str(files[3]))
    written += map(str, domain.export_files(ids, stem))
    return tuple(written)


def _wrap(text: str, width: int = 90) -> str:
    return "\n".join(text[i:i + width] for i in range(0, len(text), width))


def refine_inferred(domain: Domain, inferred, targets: torch.Tensor,
                    how: Refinement) -> tuple[list[list[int]], torch.Tensor]:
    """(refined programs, their values) per shape of one batch: ``inferred`` (:class:`plad.model.decode.Inferred`)
    refined towards ``targets`` (B, *shape) on the CPU as ``how`` says."""
    from plad.eval.refinement import beam_starts, keep_best
    from plad.rewrite import refine as rewrite

    starts, owner = beam_starts(inferred, how.all_candidates)
    # one thread: the rewriters run many small tensor operations, which a second thread only slows
    # (the four 2D examples, a busy 2-core machine: 2.2 s of CPU with one thread, 24 s with two)
    with torch_threads(1):   # the whole batch at once: the rewriters batch every candidate of every shape
        refined = rewrite(domain, starts, targets[owner], how.config)
    chosen = keep_best(domain.metric.better, len(targets), owner, refined.values)
    return [refined.programs[k] for k in chosen], refined.values[chosen].clone()


def infer_items(model: PLADNet | None, domain: Domain, items: list[Item], beam: int, out_dir: str | Path,
                batch_size: int = 16, progress: bool = True,
                refine: Refinement | RefineConfig | None = None, search=None,
                on_result: Callable[[Result], None] | None = None) -> list[Result]:
    """Best-of-beam programs for the good items, their output files, and ``results.csv``.

    ``on_result(result)`` is called for each item, in the items' order, as soon as it and every item before it
    are done (their files written): a caller prints each result before any later one can fail. A shape whose
    files cannot be written keeps its program (:attr:`Result.write_error`); ``results.csv`` is written last,
    and when the run stops early (an error, an interrupt) with the rows of the items done so far, as far as
    it can be; a failure to write it is a :class:`plad.fsutil.WriteError` raised after every result was handed
    to ``on_result``.

    ``refine`` (a :class:`Refinement`, e.g. :func:`refinement` of an effort level; a
    :class:`plad.rewrite.RefineConfig` means its best-of-beam refinement; None: none): rewrite each shape's
    best-of-beam program, or each of its beam candidates, with the rewriters before writing it (never worse;
    ``plad infer`` does unless ``--no-refine``). Shapes are inferred and refined in batches (the rewriters
    batch every candidate of every shape: the four 2D examples took 2.7 s of CPU so, 4.0 s one at a time);
    each result's ``seconds`` is its share of its batch's time.

    ``search`` (a :class:`plad.rewrite.SearchConfig`; the route recorded for the domain, :mod:`plad.serve.route`,
    found better): the programs come from search from scratch instead, no network (``model`` may be None).
    """
    if refine is not None and not isinstance(refine, Refinement):
        refine = Refinement(refine)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    device = next(model.parameters()).device if search is None else torch.device("cpu")
    results = {id(it): Result(it) for it in items}
    good = [it for it in items if it.error is None]
    batch_size = max(1, min(batch_size, MAX_BEAM_ROWS // beam))
    done: set[int] = {id(it) for it in items if it.error is not None}
    shown = 0   # items handed to on_result so far (in order)

    def hand_over() -> None:
        nonlocal shown
        while shown < len(items) and id(items[shown]) in done:
            if on_result is not None:
                on_result(results[id(items[shown])])
            shown += 1

    try:
        _infer_chunks(model, domain, good, beam, out, batch_size, progress, refine, search, device, results, done,
                      hand_over)
    except BaseException:   # keep the rows of the shapes done (their files are kept too), then stop
        with contextlib.suppress(Exception):
            write_csv([results[id(it)] for it in items if id(it) in done], domain, out / "results.csv")
        raise
    hand_over()
    ordered = [results[id(it)] for it in items]
    write_csv(ordered, domain, out / "results.csv")
    return ordered


def _infer_chunks(model, domain: Domain, good: list[Item], beam: int, out: Path, batch_size: int, progress: bool,
                  refine, search, device, results: dict, done: set[int], hand_over: Callable[[], None]) -> None:
    """The good items in batches: programs, values and files (:func:`infer_items`); each finished item's id goes
    into ``done`` and ``hand_over()`` follows every batch."""
    with tqdm(total=len(good), desc="infer", unit="shape", disable=not progress or None) as bar:
        for start in range(0, len(good), batch_size):
            chunk = good[start:start + batch_size]
            began = time.perf_counter()
            targets = torch.from_numpy(np.stack([it.shape for it in chunk])).to(device)
            if search is not None:
                from plad.rewrite import search as search_programs
                from plad.rewrite.evaluate import Scorer

                found = search_programs(domain, targets.cpu(), search)
                programs, values = found.programs, found.values.cpu()
                recons = Scorer(domain, targets.cpu()).outputs(programs)
            else:
                inferred = infer_programs(model, domain, targets, beam)
                programs, values, recons = inferred.programs, inferred.values.cpu(), inferred.shapes.cpu()
            if refine is not None and search is None:
                from plad.rewrite.evaluate import Scorer

                programs, values = refine_inferred(domain, inferred, targets.cpu(), refine)
                recons = Scorer(domain, targets.cpu()).outputs(programs)
            share = (time.perf_counter() - began) / len(chunk)
            for j, it in enumerate(chunk):
                r = results[id(it)]
                ids, value, recon = programs[j], float(values[j]), recons[j].numpy()
                r.program, r.value, r.seconds = domain.format(ids), value, share
                if not recon.any():
                    it.notes.append("the inferred program executes to an empty shape")
                written: list[str] = []
                try:
                    _write_outputs(domain, it, ids, recon, value, out, written)
                except OSError as err:   # a full disk, a read-only folder: one line naming the file
                    why = err if isinstance(err, WriteError) else cause_of(err)
                    r.write_error = f"could not write its outputs ({why})"
                r.outputs = tuple(written)
                done.add(id(it))
            bar.update(len(chunk))
            hand_over()


def _csv_name(path: Path) -> str:
    """A file name as ``results.csv`` holds it: valid UTF-8 always, the bytes of a name that is not UTF-8
    written as ``\\xff`` escapes (``bad_\\xff\\xfe.png``)."""
    return os.fsencode(str(path)).decode("utf-8", "backslashreplace")


def write_csv(results: list[Result], domain: Domain, path: Path) -> None:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["file", "index", "name", "status", domain.metric.name, "seconds", "program", "notes"])
    for r in results:
        it = r.item
        notes = it.error if it.error else "; ".join([*it.notes, *([r.write_error] if r.write_error else [])])
        w.writerow([_csv_name(it.source), "" if it.index is None else it.index, it.name,
                    "ok" if r.ok and not r.write_error else "error",
                    "" if r.value is None else f"{r.value:.6f}", f"{r.seconds:.3f}" if r.ok else "",
                    r.program or "", notes])
    atomic_write_text(path, buf.getvalue())
