"""Typed configuration from ``params.yaml``, with a profile applied.

Each component has a dataclass; its section of ``params.yaml`` is named after
the DVC stage that uses it. Unknown keys are errors (a typo must not silently
fall back to a default), and so are values of the wrong type.

A stage that runs once per domain (:data:`PER_DOMAIN`) has a ``base`` block
and one block per domain holding only the keys that differ; its config for
domain ``d`` is ``base`` merged with block ``d``. The top-level ``profile``
names ``profiles/<profile>.yaml`` beside the params file: an override file in
the same shape that holds only what differs (``cpu``, the default, changes
nothing); it is merged on top, its base block before its domain block.
Mappings merge key by key, any other value replaces. A profile may only change
keys that params.yaml sets, so a typo there is an error too.
:func:`load_params` returns every section so resolved (``pretrain.<domain>``
is then one complete mapping), and :func:`section` builds its dataclass.
"""
# size: one contract, kept whole: how params.yaml and a profile are read (safe YAML, merged, checked
# against the keys params.yaml sets) and how a section is built (types, value rules, limits) are the
# checks the docstring states; every stage imports it, so a split would add modules to every stage's
# code deps in dvc.yaml. No function over 100 lines.
from __future__ import annotations

import copy
import dataclasses
import numbers
import os
import re
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from plad.errors import RunFailure

T = TypeVar("T")


class ConfigError(RunFailure, ValueError):
    """A params file problem; the message is one line naming the file and key (exit status 1)."""


#: Top-level keys dvc.yaml reads itself (stage names and files); a profile cannot change them.
PIPELINE_KEYS = ("profile", "domains", "methods", "beams")
#: One section per DVC stage (and the Prefect flows').
STAGE_SECTIONS = ("prepare", "synthesize", "pretrain", "evaluate", "search_only", "label", "teach", "finetune",
                  "report", "flows")
#: The config class each section builds, as ``module:Class`` (imported only when asked for: most import torch).
SECTION_CLASSES = {
    "prepare": "plad.stages.prepare:PrepareConfig", "synthesize": "plad.stages.synthesize:SynthesizeConfig",
    "pretrain": "plad.learn.pretrain:PretrainConfig", "evaluate": "plad.stages.evaluate:EvaluateConfig",
    "search_only": "plad.stages.search_only:SearchOnlyConfig", "label": "plad.learn.labels:LabelConfig",
    "teach": "plad.learn.teach:TeachConfig", "finetune": "plad.learn.finetune:FinetuneStageConfig",
    "report": "plad.stages.report:ReportConfig", "flows": "flows.finetune:FlowsConfig",
}
#: Top-level keys a params file may have.
SECTIONS = {*PIPELINE_KEYS, *STAGE_SECTIONS}
#: Sections with a ``base`` block and one block per domain (DVC stages ``<stage>@<domain>``).
PER_DOMAIN = ("synthesize", "pretrain", "evaluate", "search_only", "label", "teach", "finetune")
BASE = "base"
#: Top-level keys handed to a section as its keys of the same name (their one home is the top level).
INJECTED = {"prepare": ("domains",), "report": ("domains", "profile", "beams")}


def section_class(name: str) -> type:
    """The config class of stage section ``name`` (:data:`SECTION_CLASSES`; ``KeyError`` for another name)."""
    import importlib

    module, attr = SECTION_CLASSES[name].split(":")
    return getattr(importlib.import_module(module), attr)


def profile_path(params_path: str | os.PathLike, profile: str) -> Path:
    """The override file of ``profile``: ``profiles/<profile>.yaml`` beside the params file."""
    return Path(params_path).parent / "profiles" / f"{profile}.yaml"


def merge(*layers: Any) -> dict[str, Any]:
    """Mappings merged left to right: nested mappings key by key, any other value replaced (copied)."""
    out: dict[str, Any] = {}
    for layer in layers:
        for key, value in (layer or {}).items():
            if isinstance(value, dict) and isinstance(out.get(key), dict):
                out[key] = merge(out[key], value)
            else:
                out[key] = copy.deepcopy(value)
    return out


#: in a profile, the key of a mapping of mappings that stands for every key params.yaml sets there (e.g.
#: ``finetune.base.methods."*"``: every method, those added later too); the profile's named keys apply after it
EVERY = "*"


def expand_every(override: Any, target: Any) -> Any:
    """A profile's ``override`` with each :data:`EVERY` entry given to every key of the mapping it overrides in
    ``target`` (the resolved params), merged under that key's own entry of ``override``."""
    if not isinstance(override, dict):
        return override
    target = target if isinstance(target, dict) else {}
    out: dict[str, Any] = {key: copy.deepcopy(override[EVERY]) for key in target} if EVERY in override else {}
    for key, value in override.items():
        if key == EVERY:
            continue
        value = expand_every(value, target.get(key))
        out[key] = merge(out[key], value) if isinstance(out.get(key), dict) and isinstance(value, dict) else value
    return out


class Params(dict):
    """The resolved sections of a params file (a dict: section -> mapping; per-domain: domain -> mapping).

    ``source(name)`` is what error messages about section ``name`` cite: the
    params file, and the profile file where that one changed the section.
    """

    def __init__(self, data: dict[str, Any], path: Path, profile_file: Path | None = None,
                 touched: frozenset[str] = frozenset()):
        super().__init__(data)
        self.path = path
        self.profile_file = profile_file
        self.touched = touched

    def source(self, name: str) -> str:
        parts = name.split(".")
        key = ".".join(parts[:2]) if parts[0] in PER_DOMAIN else parts[0]
        if self.profile_file is not None and (key in self.touched or f"{parts[0]}.{BASE}" in self.touched):
            return f"{self.path} with {self.profile_file}"
        return str(self.path)


#: the most YAML nodes a params or profile file may expand to, anchors and aliases followed: params.yaml has
#: about 800; a file whose aliases nest into millions ("billion laughs") is refused before it is built
MAX_YAML_NODES = 100_000


def _expanded_size(node: yaml.Node, sizes: dict[int, int], open_: set[int]) -> int:
    """The number of nodes ``node`` stands for with every alias expanded (memoized per node: an alias is the
    very node its anchor names, so this takes one visit per distinct node however deep the nesting)."""
    key = id(node)
    if key in sizes:
        return sizes[key]
    if key in open_:
        raise ValueError("an alias refers to a node that holds it (a recursive structure)")
    open_.add(key)
    if isinstance(node, yaml.SequenceNode):
        children = node.value
    elif isinstance(node, yaml.MappingNode):
        children = [n for pair in node.value for n in pair]
    else:
        children = []
    total = 1
    for child in children:
        total += _expanded_size(child, sizes, open_)
        if total > MAX_YAML_NODES:
            break
    open_.discard(key)
    sizes[key] = total
    return total


def _check_unique_keys(node: yaml.Node, seen: set[int]) -> None:
    """ValueError naming a key given twice in one mapping (YAML would keep the last one silently: a second
    ``profile: smoke`` line switched a run's profile); each distinct node is visited once."""
    if id(node) in seen:
        return
    seen.add(id(node))
    if isinstance(node, yaml.MappingNode):
        first: dict[Any, int] = {}
        for key, _ in node.value:
            if isinstance(key, yaml.ScalarNode) and key.tag != "tag:yaml.org,2002:merge":
                line, same = key.start_mark.line + 1, (key.tag, key.value)
                if same in first:
                    raise ValueError(f"the key {key.value!r} is given twice in one mapping (lines {first[same]} "
                                     f"and {line}); YAML would silently keep the second: remove one")
                first[same] = line
    children = node.value if isinstance(node, yaml.SequenceNode) else \
        [n for pair in node.value for n in pair] if isinstance(node, yaml.MappingNode) else []
    for child in children:
        _check_unique_keys(child, seen)


def safe_yaml(text: str) -> Any:
    """``yaml.safe_load(text)``, refusing (``ValueError``) a document whose aliases expand beyond
    :data:`MAX_YAML_NODES` nodes or hold themselves, or a mapping that gives a key twice: checked on the
    composed nodes, before anything is built."""
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        size = _expanded_size(node, {}, set())
        if size > MAX_YAML_NODES:
            raise ValueError(f"its anchors and aliases expand to more than {MAX_YAML_NODES:,} values (an alias "
                             f"bomb?); write the values out")
        _check_unique_keys(node, set())
        return loader.construct_document(node)
    finally:
        loader.dispose()


def _read_yaml(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise ConfigError(f"{path}: not a file" if path.exists() else f"{path}: no such params file")
    try:
        data = safe_yaml(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML ({' '.join(str(err).split())})") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file (YAML is UTF-8 text)") from None
    except OSError as err:
        raise ConfigError(f"{path}: cannot read ({err.strerror or err.__class__.__name__})") from None
    except (ValueError, RecursionError) as err:
        raise ConfigError(f"{path}: refused: {' '.join(str(err).split()) or 'nested too deeply'}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of sections at the top level")
    return data


def _blocks(data: dict[str, Any], name: str, source: Path) -> dict[str, dict[str, Any]]:
    """The blocks (``base`` and per domain) of per-domain section ``name``, each a mapping."""
    value = data.get(name) or {}
    if not isinstance(value, dict):
        raise ConfigError(f"{source}: {name} must be a mapping of blocks ({BASE} and one per domain), got {value!r}")
    blocks = {}
    for block, body in value.items():
        body = {} if body is None else body
        if not isinstance(body, dict):
            raise ConfigError(f"{source}: {name}.{block} = {body!r}: expected a block ({name}.{BASE}, or a domain's "
                              f"keys that differ from it)")
        if "domain" in body:
            raise ConfigError(f"{source}: {name}.{block}.domain: not a key to set (a block's name is its domain)")
        blocks[str(block)] = body
    return blocks


def _check_known(override: dict[str, Any], known: dict[str, Any], where: str, source: Path) -> None:
    """Every key of a profile's ``override`` is a key params.yaml sets (``known``); an empty mapping takes any."""
    for key, value in override.items():
        if key == EVERY:
            entries = [v for v in known.values() if isinstance(v, dict)]
            if not isinstance(value, dict) or not entries:
                raise ConfigError(f"{source}: {where}.{EVERY}: applies a mapping to every entry of a mapping of "
                                  f"mappings")
            _check_known(value, merge(*entries), f"{where}.{EVERY}", source)
            continue
        if key not in known:
            raise ConfigError(f"{source}: {where}.{key} is not set in params.yaml; a profile only changes "
                              f"values params.yaml sets")
        if isinstance(value, dict) and isinstance(known[key], dict) and known[key]:
            _check_known(value, known[key], f"{where}.{key}", source)


def _read_profile(path: Path, data: dict[str, Any]) -> tuple[Path | None, dict[str, Any]]:
    profile = data.get("profile")
    if profile is None:
        return None, {}
    if not isinstance(profile, str) or not profile or "/" in profile:
        raise ConfigError(f"{path}: profile = {profile!r} should be the name of a file in profiles/")
    ppath = profile_path(path, profile)
    if not ppath.is_file():
        raise ConfigError(f"{path}: profile {profile!r}: no such file {ppath}")
    over = _read_yaml(ppath)
    for key in over:
        if key in PIPELINE_KEYS:
            raise ConfigError(f"{ppath}: {key} cannot be set by a profile (dvc.yaml reads it from {path.name})")
        if key not in STAGE_SECTIONS:
            raise ConfigError(f"{ppath}: unknown section {key}; allowed: {', '.join(STAGE_SECTIONS)}")
        if key not in data:
            raise ConfigError(f"{ppath}: section {key} is not in {path}")
        if key in PER_DOMAIN:
            blocks, mine = _blocks(data, key, path), _blocks(over, key, ppath)
            for block, body in mine.items():
                if block not in blocks:
                    raise ConfigError(f"{ppath}: {key}.{block} is not a block of {path}")
                known = merge(*blocks.values()) if block == BASE else merge(blocks.get(BASE), blocks[block])
                _check_known(body, known, f"{key}.{block}", ppath)
        else:
            if not isinstance(over[key], dict):
                raise ConfigError(f"{ppath}: {key} must be a mapping, got {over[key]!r}")
            _check_known(over[key], data[key] or {}, key, ppath)
    return ppath, over


def load_params(path: str | os.PathLike = "params.yaml", profile: str | None = None) -> Params:
    """The params file with its profile applied: every section resolved (see the module docstring).

    ``profile`` replaces the file's own ``profile`` key (as ``dvc exp run -S profile=...`` would).
    """
    path = Path(path)
    data = _read_yaml(path)
    if profile is not None:
        data["profile"] = profile
    unknown = sorted(set(data) - SECTIONS)
    if unknown:
        raise ConfigError(f"{path}: unknown section(s) {', '.join(unknown)}; allowed: {', '.join(sorted(SECTIONS))}")
    ppath, over = _read_profile(path, data)
    out: dict[str, Any] = {k: copy.deepcopy(data[k]) for k in PIPELINE_KEYS if k in data}
    touched = set()
    for name in STAGE_SECTIONS:
        if name not in data:
            continue
        if name in PER_DOMAIN:
            blocks, mine = _blocks(data, name, path), (_blocks(over, name, ppath) if name in over else {})
            touched.update(f"{name}.{b}" for b in mine)
            out[name] = {}
            for d, body in blocks.items():
                if d == BASE:
                    continue
                resolved = merge(blocks.get(BASE), body)
                for layer in (mine.get(BASE), mine.get(d)):   # the profile's base block, then its domain's
                    resolved = merge(resolved, expand_every(layer, resolved))
                out[name][d] = {**resolved, "domain": d}
            continue
        if data[name] is not None and not isinstance(data[name], dict):
            raise ConfigError(f"{path}: {name} must be a mapping, got {data[name]!r}")
        if name in over:
            touched.add(name)
        resolved = merge(data[name], expand_every(over.get(name), data[name]))
        for key in INJECTED.get(name, ()):
            if key in resolved:
                raise ConfigError(f"{path}: {name}.{key}: not a key to set here; its one home is the top-level "
                                  f"{key!r}")
            if key in data:
                resolved[key] = copy.deepcopy(data[key])
        out[name] = resolved
    return Params(out, path, ppath, frozenset(touched))


# ---- beams ------------------------------------------------------------------------------------------
#: the widest beam any command or stage searches with: the beam's rows (shapes x beam) and their decoder
#: caches grow with it, and a beam of a billion would only fail deep inside torch. The paper uses 10.
MAX_BEAM = 100
#: rows (shapes x beam) of one beam search call of ``plad infer`` and the pyfunc model: shapes are batched
#: by ``max(1, MAX_BEAM_ROWS // beam)``, so that the memory is bounded whatever the beam
MAX_BEAM_ROWS = 256


def check_beam(beam: object) -> int:
    """``beam`` as a beam width: an integer (NumPy's too) in [1, :data:`MAX_BEAM`], else ``ValueError``."""
    if isinstance(beam, bool) or not isinstance(beam, numbers.Integral) or not 1 <= int(beam) <= MAX_BEAM:
        raise ValueError(f"a beam width is an integer from 1 to {MAX_BEAM} (MAX_BEAM), got {beam!r}")
    return int(beam)


# ---- value rules --------------------------------------------------------------------------------
# One table for every component's config: a key of that name holding a number (or a list of numbers)
# must satisfy the rule. Relations between keys (e.g. n_heads dividing d_model) are checked by the
# config class itself (``__post_init__`` raising ValueError), and reported by :func:`build` with the key.
_POSITIVE = ("must be positive", lambda v: v > 0)
_BEAM = (f"must be a beam width from 1 to {MAX_BEAM} (MAX_BEAM)", lambda v: 1 <= v <= MAX_BEAM)
_NON_NEGATIVE = ("must be non-negative", lambda v: v >= 0)
_FRACTION = ("must be in [0, 1)", lambda v: 0 <= v < 1)
_OPEN_FRACTION = ("must be in (0, 1)", lambda v: 0 < v < 1)
_UNIT = ("must be in [0, 1]", lambda v: 0 <= v <= 1)
RULES: dict[str, tuple[str, Any]] = {
    **{k: _POSITIVE for k in (
        "train_programs", "val_programs", "val_metric_shapes", "batch_size", "limit", "train_limit",
        "val_limit", "threads", "max_minutes", "d_model", "n_layers", "n_heads", "dim_ff", "enc_channels",
        "enc_kernel", "lr", "min_lr", "steps_per_epoch", "infer_batch",
        "val_batch", "max_rounds", "accumulate", "latent",
        "hidden", "sample_batch", "max_sample_factor", "time_limit", "batch")},
    **{k: _NON_NEGATIVE for k in (
        # max_epochs 0: a continued pretraining that only takes over its checkpoint (pretrain.init)
        "seed", "max_epochs", "patience", "round_patience", "lr_patience", "min_delta", "grid_shapes", "grad_clip",
        "kl_weight", "rounds", "po_sweeps", "tune_sweeps", "insertions", "loader_workers")},
    **{k: _BEAM for k in ("beam", "beams", "sweep_beam", "infer_beam", "val_beam_epoch", "val_beam_round",
                          "val_beam")},
    "dropout": _FRACTION, "momentum": _FRACTION, "lr_factor": _OPEN_FRACTION, "baseline_alpha": _UNIT,
}


#: the largest value of every size a user can set, by key (in params, a profile, ``--set``, a search's settings):
#: far above what any run uses, so that a typo or an extra digit (``train_programs: 99999999999999999999``,
#: ``beam_width: 100000000``, ``threads: 1000``) is refused in one line instead of filling the memory or running
#: until killed
_COUNT = 10_000_000           # programs, shapes, steps, epochs, rounds
_BATCH = 65_536               # rows processed together
_WORKERS = 256                # threads and processes
_MINUTES = 525_600            # one year
LIMITS: dict[str, float] = {
    **{k: 50_000_000 for k in ("train_programs", "val_programs")},
    **{k: _COUNT for k in (
        "val_metric_shapes", "gap_programs", "real_val_shapes", "limit", "train_limit", "val_limit", "grid_shapes",
        "fit_shapes", "steps_per_epoch", "stage_steps", "max_epochs", "max_rounds", "patience", "round_patience",
        "lr_patience", "stage_patience", "warmup_steps", "rounds", "accumulate", "max_sample_factor")},
    **{k: _BATCH for k in ("batch_size", "batch", "sample_batch", "infer_batch", "val_batch", "chunk", "bucket_pool")},
    **{k: _WORKERS for k in ("threads", "threads_per_task", "workers", "refine_workers", "loader_workers", "shards")},
    **{k: 1_000 for k in ("po_sweeps", "tune_sweeps", "insertions", "graft", "stages", "retries", "overshoot")},
    **{k: MAX_BEAM for k in ("beam_width", "beam_refine", "fit_beam", "fit_beam_wide")},
    **{k: _MINUTES for k in ("max_minutes", "rewrite_minutes", "seed_minutes")},
    "time_limit": _MINUTES * 60, "retry_delay_seconds": 86_400,
    # a network's size as a whole is bounded by plad.model.checkpoint.MAX_PARAMETERS (checked before it is built)
    "d_model": 65_536, "dim_ff": 1_048_576, "n_heads": 256, "n_layers": 64, "enc_channels": 65_536,
    "enc_kernel": 15, "latent": 1_048_576, "hidden": 1_048_576, "seed": 2 ** 32 - 1,
}


#: the devices a config may name (plad.device.resolve_device)
DEVICE_NAMES = re.compile(r"auto|cpu|cuda(:\d+)?")


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _check_value(key: str, value: Any, where: str, source: str) -> None:
    """The :data:`RULES` of ``key``, and a known domain for ``domain``/``domains``; ConfigError naming the key."""
    if key == "device" and isinstance(value, str):
        if not DEVICE_NAMES.fullmatch(value):
            raise ConfigError(f"{source}: {where}.device = {value!r}: use auto (CUDA when present), cpu, cuda or "
                              f"cuda:N")
        return
    if key in ("domain", "domains") and value is not None:
        from plad.domains import domain_names

        known = domain_names()
        for name in [value] if isinstance(value, str) else value:
            if name not in known:
                raise ConfigError(f"{source}: {where}.{key}: unknown domain {name!r}; known: {', '.join(known)}")
        return
    rule, limit = RULES.get(key), LIMITS.get(key)
    for v in value if isinstance(value, (list, tuple)) else [value]:
        if not _number(v):
            continue
        if rule is not None and (v != v or not rule[1](v)):   # v != v: NaN
            raise ConfigError(f"{source}: {where}.{key} = {value!r} {rule[0]}")
        if limit is not None and (v != v or v > limit):
            raise ConfigError(f"{source}: {where}.{key} = {value!r} is more than the limit of {limit:,} "
                              f"(plad.config.LIMITS)")


def _check_type(value: Any, annotation: Any) -> bool:
    origin = typing.get_origin(annotation)
    if annotation is Any:
        return True
    if origin in (typing.Union, types.UnionType):
        return any(_check_type(value, a) for a in typing.get_args(annotation))
    if annotation is type(None):
        return value is None
    if origin in (list, tuple):
        (inner, *_) = typing.get_args(annotation) or (Any,)
        return isinstance(value, (list, tuple)) and all(_check_type(v, inner) for v in value)
    if origin is dict:
        return isinstance(value, dict)
    if annotation is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if annotation is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, annotation)


def build(cls: type[T], raw: Any, where: str, source: str = "params.yaml") -> T:
    """Build dataclass ``cls`` from a mapping; nested dataclass fields are built recursively.

    Unknown keys and wrongly typed values raise :class:`ConfigError` naming ``source`` and the key.
    """
    raw = {} if raw is None else raw
    if not isinstance(raw, dict):
        raise ConfigError(f"{source}: {where} must be a mapping, got {raw!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(raw) - fields)
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {', '.join(unknown)} in {where!r}; "
                          f"allowed: {', '.join(sorted(fields))}")
    values = {}
    for key, value in raw.items():
        hint = hints[key]
        if value is not None and typing.get_origin(hint) in (typing.Union, types.UnionType):
            # an optional dataclass (``X | None``): a mapping builds X
            inner = [a for a in typing.get_args(hint) if a is not type(None)]
            if len(inner) == 1 and dataclasses.is_dataclass(inner[0]):
                hint = inner[0]
        if dataclasses.is_dataclass(hint):
            values[key] = build(hint, value, f"{where}.{key}", source)
            continue
        if typing.get_origin(hint) is dict and dataclasses.is_dataclass(typing.get_args(hint)[-1]):
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: {where}.{key} must be a mapping, got {value!r}")
            inner = typing.get_args(hint)[-1]
            values[key] = {str(k): build(inner, v, f"{where}.{key}.{k}", source) for k, v in value.items()}
            continue
        if not _check_type(value, hint):
            raise ConfigError(f"{source}: {where}.{key} = {value!r} should be of type "
                              f"{getattr(hint, '__name__', hint)}")
        _check_value(key, value, where, source)
        values[key] = value
    # keys without a default (e.g. a stage's domain) must be given; checked after the given keys,
    # since a typo in those is the likelier mistake
    missing = [f.name for f in dataclasses.fields(cls)  # type: ignore[arg-type]
               if f.name not in raw and f.default is dataclasses.MISSING
               and f.default_factory is dataclasses.MISSING]
    if missing:
        raise ConfigError(f"{source}: missing key(s) {', '.join(missing)} in {where!r}")
    try:
        return cls(**values)
    except ValueError as err:   # a relation between keys, checked by the class (e.g. n_heads dividing d_model)
        raise ConfigError(f"{source}: {where}: {err}") from None


def lookup(params: dict[str, Any], name: str, source: str | None = None) -> Any:
    """``params["pretrain"]["<domain>"]`` for ``name = "pretrain.<domain>"``; a missing part is an error."""
    source = source or (params.source(name) if isinstance(params, Params) else "params.yaml")
    parts = name.split(".")
    if len(parts) == 1 and parts[0] in PER_DOMAIN and isinstance(params.get(parts[0]), dict):
        raise ConfigError(f"{source}: section {name!r} has one block per domain: name one, e.g. "
                          f"{name}.<domain> ({', '.join(params[name]) or 'none in the file'})")
    node: Any = params
    for i, part in enumerate(parts):
        if not isinstance(node, dict) or part not in node:
            raise ConfigError(f"{source}: section {'.'.join(parts[:i + 1])!r} is missing")
        node = node[part]
    return node


def section(params: dict[str, Any], name: str, cls: type[T], source: str | None = None) -> T:
    """Build ``cls`` from the section ``name`` (dotted for a domain's block, e.g. ``pretrain.<domain>``)."""
    source = source or (params.source(name) if isinstance(params, Params) else "params.yaml")
    return build(cls, lookup(params, name, source), name, source)


def apply_overrides(raw: dict[str, Any], overrides: list[str], where: str) -> dict[str, Any]:
    """``["a.b=3", "c=x"]`` applied to a copy of section ``raw``; values are parsed as YAML.

    Keys are checked later by :func:`build`, so a typo is still an error.
    """
    out = copy.deepcopy(raw) if raw is not None else {}
    for item in overrides:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
        parts = key.strip().split(".")
        node = out
        for p in parts[:-1]:
            if not isinstance(node.get(p), dict):
                node[p] = {}
            node = node[p]
        if not text.strip():   # `--set init=` is a typo or a shell's empty variable, never "none"
            raise ConfigError(f"--set {item!r}: no value; write {key.strip()}=null for none")
        try:
            node[parts[-1]] = safe_yaml(text)
        except yaml.YAMLError:
            raise ConfigError(f"--set {item!r}: value is not valid YAML") from None
        except (ValueError, RecursionError) as err:
            raise ConfigError(f"--set {item!r}: refused: {' '.join(str(err).split())}") from None
    return out
