"""Registry of fine-tuning methods and of the PLAD mixtures' pseudo-label sources (plugins, like domains).

A fine-tuning method is what a ``finetune.<domain>.methods.<key>.method`` value names:

* a **method with its own training step** (RL), registered by name with :func:`register_method`: a
  :class:`Method` whose :meth:`Method.run` trains the model;
* or a **PLAD mixture** of registered sources, e.g. ``lest+st`` or ``lest:2+st:1+ws:1``
  (:func:`parse_mixture`), trained by the PLAD rounds (:mod:`plad.learn.rounds`), themselves the
  :class:`Method` registered as :data:`MIXTURE` (:mod:`plad.learn.mixtures`). A source
  (:func:`register_source`) builds, each round, a draw of (shape, program) pairs from P_BEST or from data
  of its own (:class:`PairSource`).

The round loop, the ``finetune`` stage (:mod:`plad.learn.finetune`), the report's labels and the profiles
read this registry and name no method. Every method and source declares its label here, so that the report
(whose code must not depend on the training code) reads the labels without importing the plugins, which
are imported lazily on first use, as domains are. A method from outside ``plad/`` registers itself with
:func:`register_method` / :func:`register_source`, given an object or ``"package.module:attribute"``.

This module imports nothing of ``plad`` and no torch: the report and the command line read it cheaply.
"""
from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

#: name of the registered method that trains every PLAD mixture (not a ``method:`` value itself)
MIXTURE = "plad"


@dataclass(frozen=True)
class Entry:
    #: the plugin: an object, or ``"package.module:attribute"`` imported on first use
    target: Any
    #: the report's label of the method or source, e.g. ``"RL"`` or ``"LEST"``
    label: str


class Method:
    """A fine-tuning method's algorithm: checked against its params entry, then run on a job.

    Subclasses set :attr:`checkpoint` and implement :meth:`run`; :meth:`check` and :meth:`work` have defaults
    for a method that counts its work in PLAD rounds (the entry's ``max_rounds``, capped by ``plad.max_rounds``).
    """

    #: the file of the run folder that holds the last (not the selected) weights; MLflow logs it as "final"
    checkpoint: str = "current.pt"

    def check(self, spec: Any, cfg: Any, where: str) -> None:
        """Raise ``ValueError`` (the message names the key under ``where``, e.g. ``finetune.methods.st``) when
        the method entry ``spec`` (:class:`plad.learn.methods.MethodConfig`) of stage config ``cfg``
        (:class:`plad.learn.finetune.FinetuneStageConfig`) cannot run."""
        if spec.max_rounds is not None and spec.max_rounds < 1:
            raise ValueError(f"{where}.max_rounds = {spec.max_rounds}: expected at least 1")

    def rounds(self, spec: Any, cfg: Any) -> Any:
        """The PLAD rounds config of this run: ``cfg.plad`` with the entry's ``max_rounds`` (at most
        ``plad.max_rounds``: a profile caps every method with one key)."""
        from dataclasses import replace

        if spec.max_rounds is None:
            return cfg.plad
        return replace(cfg.plad, max_rounds=min(spec.max_rounds, cfg.plad.max_rounds))

    def work(self, spec: Any, cfg: Any) -> dict[str, int]:
        """What fixes the run's work, for its summary (e.g. ``{"max_rounds": 4}``)."""
        return {"max_rounds": self.rounds(spec, cfg).max_rounds}

    def run(self, job: Any, spec: Any, cfg: Any, hooks: Any) -> dict:
        """Fine-tune ``job.model`` (:class:`plad.learn.job.Job`), resumable from ``job.out_dir``; ``hooks``
        (:class:`plad.learn.rounds.RoundHooks`) run the steps and hear about each unit (``on_unit``). Returns
        the run summary (:meth:`plad.learn.loop.LoopResult.summary` with ``method`` first)."""
        raise NotImplementedError


class PairSource:
    """A pseudo-label source of the PLAD mixtures: each round, a draw of (shape, program) batches."""

    def build(self, ctx: Any) -> tuple[Callable, dict[str, float]]:
        """(``draw(rng, n) -> (shapes, programs, lengths)`` on ``ctx.device``, columns for the round's history)
        for round ``ctx.rnd`` (:class:`plad.learn.methods.RoundContext`). Building may train (wake-sleep's
        generator) and must be resumable: a resumed round draws the same pairs."""
        raise NotImplementedError


_METHODS: dict[str, Entry] = {
    MIXTURE: Entry("plad.learn.mixtures:PLAD_ROUNDS", "PLAD"),
    "rl": Entry("plad.learn.rl:RL", "RL"),
}
_SOURCES: dict[str, Entry] = {
    "st": Entry("plad.learn.methods:ST", "ST"),
    "lest": Entry("plad.learn.methods:LEST", "LEST"),
    "ws": Entry("plad.learn.rounds:WS", "WS"),
}
_LOADED: dict[tuple[str, str], Any] = {}

#: variants of a PLAD mixture's key and their labels: ``lest_st_per_round`` is LEST+ST with a per-round P_BEST
#: (``pbest_mode``), ``lest_st_ws_search`` LEST+ST+WS with a ``search`` block
KEY_VARIANTS = {"_per_round": " (per-round)", "_search": " + search-seeded P_BEST"}


def register_method(name: str, target: Any, label: str) -> None:
    """Register a method with its own training step: a :class:`Method` or ``"module:attribute"`` of one.
    ``name`` is its ``method:`` value in params, and the key whose table row shows ``label``."""
    _check_name(name, _SOURCES, "a source")
    _METHODS[name] = Entry(target, label)
    _LOADED.pop(("method", name), None)


def register_source(name: str, target: Any, label: str) -> None:
    """Register a PLAD mixture source: a :class:`PairSource` or ``"module:attribute"`` of one."""
    _check_name(name, _METHODS, "a method")
    _SOURCES[name] = Entry(target, label)
    _LOADED.pop(("source", name), None)


def unregister(name: str) -> None:
    """Forget method or source ``name`` (a test's plugin, after the test)."""
    for kind, table in (("method", _METHODS), ("source", _SOURCES)):
        table.pop(name, None)
        _LOADED.pop((kind, name), None)


def _check_name(name: str, other: dict[str, Entry], what: str) -> None:
    # a name is one token of a mixture or a key: "+", ":" and "_" would make the parsing ambiguous
    if not name or not name.isalnum() or name != name.lower():
        raise ValueError(f"method or source name {name!r}: lowercase letters and digits only")
    if name in other or name == MIXTURE:
        raise ValueError(f"{name!r} is already {what if name != MIXTURE else 'the PLAD mixtures method'}")


def method_names() -> list[str]:
    """The methods with their own training step (``method:`` values; mixtures of sources besides)."""
    return [n for n in _METHODS if n != MIXTURE]


def source_names() -> list[str]:
    return list(_SOURCES)


def plugin_modules() -> list[str]:
    """The modules of the methods and sources registered by ``"module:attribute"`` (what a fine-tuning run may
    import through the registry: the finetune stage's code, tests/pipeline/test_dvc_deps.py)."""
    entries = [*_METHODS.values(), *_SOURCES.values()]
    return sorted({e.target.split(":")[0] for e in entries if isinstance(e.target, str)})


def _load(kind: str, name: str, entry: Entry) -> Any:
    if (kind, name) not in _LOADED:
        target = entry.target
        if isinstance(target, str):
            module, attr = target.split(":")
            target = getattr(importlib.import_module(module), attr)
        _LOADED[(kind, name)] = target
    return _LOADED[(kind, name)]


def get_method(text: str) -> Method:
    """The method a ``method:`` value names: a registered one by name, else the PLAD rounds, for a mixture
    of registered sources (``ValueError`` naming the bad part otherwise)."""
    if text in _METHODS and text != MIXTURE:   # exactly its name, as params spell it
        return _load("method", text, _METHODS[text])
    parse_mixture(text)   # raises on a bad one
    return _load("method", MIXTURE, _METHODS[MIXTURE])


@dataclass(frozen=True)
class Mixture:
    names: tuple[str, ...]
    weights: tuple[float, ...]          # normalized, same order as ``names``

    def __str__(self) -> str:
        return "+".join(self.names)


def parse_mixture(text: str) -> Mixture:
    """``"lest+st"`` or ``"lest:2+st:1"`` -> Mixture of registered sources; raises ValueError naming the bad
    part. Names are parsed exactly: a substring test would read ``lest`` as containing ``st``."""
    if not text or not text.strip():
        raise ValueError("empty method: expected sources like lest+st")
    names, weights = [], []
    for part in text.strip().lower().split("+"):
        name, _, weight = part.strip().partition(":")
        name = name.strip()
        if name not in _SOURCES:
            raise ValueError(f"unknown PLAD source {name!r} in {text!r}; sources are {', '.join(_SOURCES)}")
        if name in names:
            raise ValueError(f"source {name!r} appears twice in {text!r}")
        try:
            w = float(weight) if weight.strip() else 1.0
        except ValueError:
            raise ValueError(f"weight {weight!r} of {name!r} in {text!r} is not a number") from None
        if not w > 0:
            raise ValueError(f"weight of {name!r} in {text!r} must be positive")
        names.append(name)
        weights.append(w)
    total = sum(weights)
    return Mixture(tuple(names), tuple(w / total for w in weights))


def get_source(name: str) -> PairSource:
    if name not in _SOURCES:
        raise KeyError(f"unknown PLAD source {name!r}; sources are {', '.join(_SOURCES)}")
    return _load("source", name, _SOURCES[name])


def key_label(key: str) -> str | None:
    """The report's label of a method key, by what the methods declare: a registered method's own label, a
    mixture's source labels joined by "+" (``lest_st``: LEST+ST) and the variants of one mixture
    (:data:`KEY_VARIANTS`); None for a key that is none of these."""
    if key in _METHODS and key != MIXTURE:
        return _METHODS[key].label
    for suffix, text in KEY_VARIANTS.items():
        if key.endswith(suffix) and (head := _mixture_label(key[: -len(suffix)])) is not None:
            return head + text
    return _mixture_label(key)


def _mixture_label(key: str) -> str | None:
    parts = key.split("_")
    if not key or not all(p in _SOURCES for p in parts):
        return None
    return "+".join(_SOURCES[p].label for p in parts)
