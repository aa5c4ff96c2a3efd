# size: one protocol, kept whole: the shipped models and the pretrained networks are one ShippedModel, whose
# verify() re-reads either kind under the domain's lock, and both are replaced by the same pending-file
# renames (_pending, _settle, _write_pair; the docstring below); moving the pretrained half to a module of its
# own would make an import circle with this one (tests/plad/test_layers.py). No function over 100 lines.
"""The trained models shipped with the package: one small checkpoint per domain and its sidecar.

Layout of the folder (this package's directory, or ``$PLAD_SHIPPED_DIR``)::

    <domain>/model.pt     a checkpoint (plad.model.checkpoint: config, token table, weights; no training state)
    <domain>/model.json   the sidecar: the checkpoint's sha256 and size, its config and token table,
                          its test metric values, and provenance (params, git revision, data checksums)

:func:`ship` writes both from a trained checkpoint and the ``metrics.json`` of its test
evaluation (``plad models ship``); :func:`shipped_model` and :func:`list_shipped` read them
back. Reading a sidecar needs neither torch nor MLflow (``plad models`` lists the shipped
models without them); :func:`ship` loads the checkpoint and so imports torch.

Two files make one model, so concurrent use is coordinated by ``<domain>/.ship.lock``
(:func:`plad.fsutil.file_lock`): :func:`ship` writes the pair under the exclusive lock (two ships
at once: one after the other, the last one shipped), :meth:`ShippedModel.verify` checks it under
the shared one, and refuses (one line) a model re-shipped since its sidecar was read.

A pair is replaced so that a process killed at any moment loses nothing (:func:`_write_pair`): both new
files are first written completely beside the old ones (``.model.pt.new``, ``.model.json.new``), then
renamed into place, the checkpoint first. A kill between the two renames leaves the new checkpoint and its
pending sidecar, which readers take as the sidecar (it names that checkpoint's sha256) and the next ship
renames into place (:func:`_settle`). The model a ship replaces goes to ``previous/`` only when its pair is
valid (the sidecar names the checkpoint's sha256), by the same two-step replacement: a damaged pair never
replaces the one backup. The pretrained networks and their index (:func:`ship_pretrained`) are replaced
the same way.
"""
from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from plad.errors import RunFailure
from plad.fsutil import sha256_file
from plad.provenance import code_state

#: overrides the folder of shipped models (tests; a site that keeps its own)
SHIPPED_ENV = "PLAD_SHIPPED_DIR"
CHECKPOINT = "model.pt"
SIDECAR = "model.json"
#: the lock file of a domain's folder (never removed; not package data)
LOCK = ".ship.lock"
FORMAT = "plad-shipped-1"


class ShipError(RunFailure):
    """A model cannot be shipped or a shipped one is unusable; one line naming the file (exit status 1, as a
    damaged checkpoint: :mod:`plad.errors`)."""


def shipped_dir() -> Path:
    """The folder of shipped models: ``$PLAD_SHIPPED_DIR``, else this package's directory."""
    env = os.environ.get(SHIPPED_ENV)
    return Path(env) if env else Path(__file__).resolve().parent


def _pending(path: Path) -> Path:
    """Where the new version of ``path`` is written before it replaces ``path`` (``.<name>.new``)."""
    return path.with_name(f".{path.name}.new")


def _recorded_sha(info: Any) -> str | None:
    """The checkpoint sha256 a sidecar or index entry records (None: it records none)."""
    ckpt = info.get("checkpoint") if isinstance(info, dict) else None
    sha = ckpt.get("sha256") if isinstance(ckpt, dict) else None
    return sha if isinstance(sha, str) else None


def _read_json(path: Path) -> Any:
    """A JSON file's value, or None when it cannot be read."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


@dataclass(frozen=True)
class ShippedModel:
    domain: str
    checkpoint: Path
    info: dict[str, Any]
    #: "model" (model.pt: the network `plad infer` uses) or "pretrained" (pretrained.pt, continued by pretraining)
    kind: str = "model"
    #: what a ship did besides shipping, one line each (e.g. a damaged pair it did not keep in previous/)
    notes: tuple[str, ...] = ()

    def problem(self) -> str | None:
        """Why the checkpoint is not the file its sidecar describes (one line), None when it is."""
        want = _recorded_sha(self.info)
        try:
            got = sha256_file(self.checkpoint)
        except OSError as err:
            return f"{self.checkpoint}: cannot be read ({err.strerror or err.__class__.__name__})"
        if got != want:
            return (f"{self.checkpoint}: sha256 {got[:12]}... differs from its sidecar's {str(want)[:12]}... (a "
                    f"damaged or replaced shipped model)")
        return None

    @property
    def test(self) -> dict[str, Any]:
        """The test metric: ``{"metric", "higher_is_better", "mean", "n", "beam", ...}``."""
        return self.info.get("metrics", {})

    def describe(self) -> str:
        if self.kind == "pretrained":
            return f"shipped pretrained {self.domain} network (SP; {describe_totals(self)}) {self.checkpoint}"
        m = self.test
        return (f"shipped {self.domain} model ({self.info.get('method', '?')}, test {m.get('metric', '?')} "
                f"{m.get('mean', '?')}) {self.checkpoint}")

    def verify(self) -> None:
        """Raise :class:`ShipError` when the checkpoint is not the file the sidecar describes, or when the
        model was shipped again since this sidecar was read (a ``plad models ship`` at the same time)."""
        from plad.fsutil import file_lock

        folder = self.checkpoint.parent
        with file_lock(folder / LOCK, shared=True, create=False):   # not while a ship writes the pair
            now = (pretrained_model if self.kind == "pretrained" else shipped_model)(self.domain, folder.parent)
            if now is None or now.info != self.info:
                where = folder.parent / PRETRAINED_INDEX if self.kind == "pretrained" else folder / SIDECAR
                raise ShipError(f"{where}: the {self.domain} model was shipped again while this command read it; "
                                "run the command again")
            want = self.info.get("checkpoint", {})
            got = sha256_file(self.checkpoint)
        if got != want.get("sha256"):
            raise ShipError(f"{self.checkpoint}: sha256 {got[:12]}... differs from its sidecar's "
                            f"{str(want.get('sha256'))[:12]}... (a damaged or replaced shipped model)")


def shipped_model(domain: str, folder: Path | None = None) -> ShippedModel | None:
    """The shipped model of ``domain``, or ``None`` when none is shipped. A sidecar that is not
    readable JSON is a :class:`ShipError`. A ship killed between its two renames left the new checkpoint in
    place and its sidecar pending: the pending sidecar is read then (it names that checkpoint)."""
    return _pair(domain, (folder or shipped_dir()) / domain)


def _pair(domain: str, base: Path) -> ShippedModel | None:
    """The model whose pair is in ``base`` (a domain's folder, or its ``previous/``), as :func:`shipped_model`."""
    ckpt, side = base / CHECKPOINT, base / SIDECAR
    if not (ckpt.is_file() and (side.is_file() or _pending(side).is_file())):
        return None
    pending = _read_json(_pending(side)) if _pending(side).is_file() else None
    if pending is not None and _recorded_sha(pending) is not None and \
            _recorded_sha(pending) == _sha_or_none(ckpt) and isinstance(pending, dict) and \
            pending.get("format") == FORMAT:
        return ShippedModel(domain, ckpt, pending)
    if not side.is_file():
        return None
    try:
        info = json.loads(side.read_text())
    except (OSError, ValueError) as err:
        raise ShipError(f"{side}: not a readable sidecar ({err})") from None
    if not isinstance(info, dict) or info.get("format") != FORMAT:
        raise ShipError(f"{side}: not a shipped-model sidecar (expected format {FORMAT})")
    return ShippedModel(domain, ckpt, info)


def _sha_or_none(path: Path) -> str | None:
    try:
        return sha256_file(path)
    except OSError:
        return None


def _settle(folder: Path) -> None:
    """Finish or undo the replacement of the pair in ``folder`` that a killed ship left (under the domain's
    exclusive lock): a complete pending pair, or a pending sidecar naming the checkpoint in place, is renamed
    into place; anything else pending is removed."""
    ckpt, side = folder / CHECKPOINT, folder / SIDECAR
    new_ckpt, new_side = _pending(ckpt), _pending(side)
    want = _recorded_sha(_read_json(new_side)) if new_side.is_file() else None
    if want is not None and new_ckpt.is_file() and _sha_or_none(new_ckpt) == want:
        os.replace(new_ckpt, ckpt)
    if want is not None and not new_ckpt.exists() and _sha_or_none(ckpt) == want:
        os.replace(new_side, side)
    for leftover in (new_ckpt, new_side):
        leftover.unlink(missing_ok=True)


def _write_pair(folder: Path, write_checkpoint, sidecar: Callable[[Path], bytes]) -> None:
    """Replace the pair in ``folder``: ``write_checkpoint(path)`` writes the new checkpoint (atomically) at a
    pending name and ``sidecar(path)`` gives the sidecar's bytes for it; both are complete on disk before
    either replaces an old file (see the module docstring)."""
    from plad.fsutil import atomic_write_bytes

    ckpt, side = folder / CHECKPOINT, folder / SIDECAR
    new_ckpt, new_side = _pending(ckpt), _pending(side)
    write_checkpoint(new_ckpt)
    atomic_write_bytes(new_side, sidecar(new_ckpt))
    os.replace(new_ckpt, ckpt)     # from here the pending sidecar names the checkpoint in place
    os.replace(new_side, side)


def list_shipped(folder: Path | None = None, errors: list[str] | None = None) -> list[ShippedModel]:
    """Every shipped model, by domain name. ``errors``: where a damaged sidecar's one line goes (the others
    are still listed); None: it is raised (:class:`ShipError`)."""
    base = folder or shipped_dir()
    if not base.is_dir():
        return []
    return _each([d.name for d in sorted(base.iterdir()) if d.is_dir()], lambda d: shipped_model(d, base), errors)


def _each(domains: list[str], load, errors: list[str] | None) -> list[ShippedModel]:
    """``load(domain)`` for every domain that has a model; a :class:`ShipError`'s line goes to ``errors`` (the
    others are still listed), or is raised where ``errors`` is None."""
    out = []
    for d in domains:
        try:
            m = load(d)
        except ShipError as err:
            if errors is None:
                raise
            errors.append(str(err))
            continue
        if m is not None:
            out.append(m)
    return out


def _portable(path: Path, base: Path) -> str:
    """``path`` as the sidecar records it: relative to ``base`` (the layout root, the data directory) when
    inside it, else its file name; never a path of the machine it was shipped on (the checksums name the
    content)."""
    try:
        return Path(path).resolve().relative_to(Path(base).resolve()).as_posix()
    except ValueError:
        return Path(path).name


def _provenance(domain: str, root: Path, params_path: Path, data_dir: str | None) -> dict[str, Any]:
    """Params of the domain (every per-domain section, resolved with the profile), git revision, data checksums."""
    import importlib

    from plad.config import PER_DOMAIN, load_params
    from plad.data.datasets import FILES
    from plad.data.files import resolve_data_dir
    from plad.domains import get_domain
    from plad.layout import Layout

    params = load_params(params_path)
    sections = {name: params[name][domain] for name in sorted(PER_DOMAIN)
                if isinstance(params.get(name), dict) and domain in params[name]}
    source = get_domain(domain).targets.name
    files: dict[str, str] = {}
    if source in FILES:
        module, attr = FILES[source].split(":")
        found = getattr(importlib.import_module(module), attr)(data_dir)
        base = resolve_data_dir(data_dir)
        files = {_portable(Path(f), base): digest for f, digest in found.items()}
    prepared = Layout(root).prepared(domain)
    data = {"source": source, "files": files}
    if prepared.is_file():
        data["prepared"] = {str(prepared.relative_to(root)): sha256_file(prepared)}
    # the git state every metrics file records (plad.provenance.code_state), under the sidecar's key names
    code = code_state(str(root))
    return {"params_file": _portable(params_path, root), "profile": params.get("profile"), "params": sections,
            "git": {"revision": code["commit"], "dirty": code["dirty"]}, "data": data}


def _test_metrics(metrics_path: Path, domain: str, checkpoint: Path) -> tuple[dict[str, Any], str | None]:
    """(the test metric record, the method) of an evaluation's ``metrics.json``, checked against the checkpoint."""
    try:
        record = json.loads(metrics_path.read_text())
    except (OSError, ValueError) as err:
        raise ShipError(f"{metrics_path}: not a readable metrics file ({err})") from None
    test = record.get("test") if isinstance(record, dict) else None
    if not isinstance(test, dict) or "mean" not in test:
        raise ShipError(f"{metrics_path}: no test metric (expected the metrics.json of an evaluation)")
    if record.get("domain") != domain:
        raise ShipError(f"{metrics_path}: metrics of a {record.get('domain')} model, not a {domain} one")
    described = record.get("checkpoint")
    if described and not checkpoint.resolve().as_posix().endswith(Path(described).as_posix()):
        raise ShipError(f"{metrics_path}: the metrics of {described}, not of {checkpoint}")
    keep = {k: record[k] for k in ("metric", "higher_is_better", "beam") if k in record}
    return {**keep, **test}, record.get("method")


#: where the model a ship replaced is kept: ``<domain>/previous/`` (its checkpoint and sidecar)
PREVIOUS = "previous"


def _better(new: dict[str, Any], old: ShippedModel) -> str | None:
    """Why the test metric ``new`` does not beat ``old``'s (None when it does): the same metric on the same
    test (shapes and beam), better in the metric's direction."""
    have = old.test
    shown = f"the shipped {old.domain} model's test {have.get('metric')} {have.get('mean')} (n {have.get('n')}, " \
            f"beam {have.get('beam')})"
    mine = f"this one's {new.get('metric')} {new.get('mean')} (n {new.get('n')}, beam {new.get('beam')})"
    if any(new.get(k) != have.get(k) for k in ("metric", "n", "beam")):
        return f"{mine} and {shown} are not measured alike"
    higher = bool(new.get("higher_is_better", have.get("higher_is_better", False)))
    try:
        better = float(new["mean"]) > float(have["mean"]) if higher else float(new["mean"]) < float(have["mean"])
    except (KeyError, TypeError, ValueError):
        return f"{shown} or {mine} is not a number"
    return None if better else f"{mine} is not better than {shown}"


def _refuse_worse(test: dict[str, Any], current: ShippedModel, checkpoint: Path, folder: Path) -> None:
    why = _better(test, current)
    if why is not None:
        raise ShipError(f"{checkpoint}: not shipped: {why}; `--force` ships it anyway (the shipped one is kept "
                        f"in {folder / PREVIOUS})")


def ship(domain: str, checkpoint: str | os.PathLike, metrics: str | os.PathLike, *,
         dest: str | os.PathLike | None = None, root: str | os.PathLike = ".",
         params: str | os.PathLike = "params.yaml", data_dir: str | None = None, force: bool = False
         ) -> ShippedModel:
    """Package a trained checkpoint as the shipped model of ``domain`` (in ``dest``, default :func:`shipped_dir`).

    The checkpoint is loaded and saved again without its training state (small); the sidecar
    records its sha256, config, token table, the test metrics of ``metrics`` (an evaluation's
    ``metrics.json`` of this very checkpoint) and the provenance read under ``root`` (the layout
    root the model was trained in): ``params`` with its profile, the git revision, the data files'
    checksums. Both files are written atomically.

    A model already shipped is replaced only by a better one, by the test metric in its direction on the
    same test (shapes, beam), unless ``force``; the replaced one is kept in ``<domain>/previous/``.
    """
    from plad.domains import get_domain
    from plad.fsutil import file_lock
    from plad.model.checkpoint import CheckpointError, load_model, save_checkpoint

    checkpoint, metrics, root = Path(checkpoint), Path(metrics), Path(root)
    try:
        model, got = load_model(checkpoint, "cpu", expect_domain=domain)
    except CheckpointError as err:
        raise ShipError(str(err)) from None
    test, method = _test_metrics(metrics, domain, checkpoint)
    params_path = params if Path(params).is_absolute() else root / params
    if not Path(params_path).is_file():
        raise ShipError(f"{params_path}: no such params file (the provenance of the model)")
    folder = Path(dest or shipped_dir()) / domain
    current = shipped_model(domain, folder.parent)
    if current is not None and not force:   # refused before the provenance's checksums are computed
        _refuse_worse(test, current, checkpoint, folder)
    provenance = _provenance(domain, root, Path(params_path), data_dir)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ShipError(f"{folder}: cannot create the shipped model's folder ({err.strerror or err})") from None
    names = get_domain(domain).tokens.names
    with file_lock(folder / LOCK) as held:   # the pair is written by one ship at a time
        if not held:
            raise ShipError(f"{folder}: cannot create {LOCK} there (a read-only folder?); pass --dest a writable one")
        _settle(folder)   # a ship killed between its renames: finished (or undone) first
        current = shipped_model(domain, folder.parent)   # again under the lock: another ship may have come first
        if current is not None and not force:
            _refuse_worse(test, current, checkpoint, folder)
        notes = []
        keep = folder / PREVIOUS
        if current is not None:   # keep the model being replaced (one generation; git keeps the older ones)
            problem = current.problem()
            if problem is None:   # only a valid pair is a backup: a damaged one never replaces a good one
                keep.mkdir(exist_ok=True)
                _settle(keep)
                sidecar_bytes = (folder / SIDECAR).read_bytes()
                _write_pair(keep, lambda p: _copy(folder / CHECKPOINT, p), lambda p: sidecar_bytes)
            else:
                notes.append(f"the model replaced was not kept in {keep} ({problem}); "
                             + (f"{keep} still holds the one before" if _pair(domain, keep) else "nothing was kept"))
        info: dict[str, Any] = {}

        def sidecar(path: Path) -> bytes:
            info.update({
                "format": FORMAT, "domain": domain, "method": method,
                "checkpoint": {"file": CHECKPOINT, "sha256": sha256_file(path), "bytes": path.stat().st_size,
                               "shipped_from": _portable(checkpoint, root)},
                "config": model.cfg.to_dict(), "tokens": list(names),
                "metrics": test, "metrics_file": _portable(metrics, root),
                "provenance": provenance,
            })
            return (json.dumps(info, indent=1) + "\n").encode()

        _write_pair(folder, lambda p: save_checkpoint(p, model, domain, names), sidecar)
    return ShippedModel(domain, folder / CHECKPOINT, info, notes=tuple(notes))


def _copy(source: Path, target: Path) -> None:
    """``source``'s bytes as ``target``, atomically."""
    from plad.fsutil import atomic_write

    with open(source, "rb") as src:
        atomic_write(target, lambda fh: shutil.copyfileobj(src, fh))


# -- pretrained networks (supervised pretraining, SP), kept to be continued ------------------------------------
#: the checkpoint of a domain's pretrained network: its whole training state (weights, optimizer, schedule,
#: curriculum stage, history, provenance segments), so that a pretraining can continue it (pretrain.init)
PRETRAINED = "pretrained.pt"
#: one index for every domain's pretrained network: the pretraining stages depend on this one file, which
#: names each checkpoint's sha256 (a domain without a pretrained network has no entry)
PRETRAINED_INDEX = "pretrained.json"
PRETRAINED_FORMAT = "plad-pretrained-1"
#: a shipped file stays small enough for the repository and the package
MAX_BYTES = 20 * 1024 * 1024


def _entry_problem(base: Path, domain: Any, info: Any) -> str | None:
    """Why an index entry cannot name a pretrained network (one line), None when it can: a mapping with a
    ``checkpoint`` of a ``file`` inside the folder of shipped models and a ``sha256``."""
    where = f"{base / PRETRAINED_INDEX}: the entry of {domain!r}"
    if not isinstance(info, dict):
        return f"{where} is not a mapping"
    ckpt = info.get("checkpoint")
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("file"), str) or not ckpt["file"] or \
            not isinstance(ckpt.get("sha256"), str):
        return f"{where} has no checkpoint file and sha256 (a damaged index)"
    rel = Path(ckpt["file"])
    if rel.is_absolute() or ".." in rel.parts:
        return f"{where} names {ckpt['file']!r}, outside the folder of shipped models"
    return None


def _index_files_match(base: Path, index: dict[str, Any], pending: bool) -> bool:
    """Whether every entry of ``index`` names a file (its pending version where ``pending`` and one exists)
    of the recorded sha256."""
    for domain, info in index["domains"].items():
        if _entry_problem(base, domain, info) is not None:
            return False
        path = base / info["checkpoint"]["file"]
        path = _pending(path) if pending and _pending(path).is_file() else path
        if _sha_or_none(path) != info["checkpoint"]["sha256"]:
            return False
    return True


def _valid_index(index: Any) -> bool:
    return isinstance(index, dict) and index.get("format") == PRETRAINED_FORMAT and \
        isinstance(index.get("domains"), dict)


def _read_index(base: Path) -> dict[str, Any]:
    """The index of pretrained networks; the pending one of a ship killed between its renames when every file
    it names is in place (:func:`ship_pretrained`)."""
    path = base / PRETRAINED_INDEX
    pending = _read_json(_pending(path)) if _pending(path).is_file() else None
    if _valid_index(pending) and _index_files_match(base, pending, pending=False):
        return pending
    if not path.is_file():
        return {"format": PRETRAINED_FORMAT, "domains": {}}
    try:
        index = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ShipError(f"{path}: not a readable index of pretrained networks ({err})") from None
    if not _valid_index(index):
        raise ShipError(f"{path}: not an index of pretrained networks (expected format {PRETRAINED_FORMAT})")
    return index


def _settle_index(base: Path) -> None:
    """Finish or undo a pretrained network's replacement that a killed ship left (under the index's lock)."""
    path = base / PRETRAINED_INDEX
    pending = _read_json(_pending(path)) if _pending(path).is_file() else None
    if _valid_index(pending) and _index_files_match(base, pending, pending=True):
        for info in pending["domains"].values():
            target = base / info["checkpoint"]["file"]
            if _pending(target).is_file():
                os.replace(_pending(target), target)
        os.replace(_pending(path), path)
    _pending(path).unlink(missing_ok=True)
    for leftover in base.glob(f"*/{_pending(Path(PRETRAINED)).name}"):
        leftover.unlink(missing_ok=True)


def pretrained_model(domain: str, folder: Path | None = None) -> ShippedModel | None:
    """The shipped pretrained network of ``domain`` (its index entry as ``info``), or None. A damaged entry
    or a missing file is a :class:`ShipError` (one line)."""
    base = folder or shipped_dir()
    info = _read_index(base)["domains"].get(domain)
    if info is None:
        return None
    problem = _entry_problem(base, domain, info)
    if problem is not None:
        raise ShipError(problem)
    path = base / info["checkpoint"]["file"]
    if not path.is_file():
        raise ShipError(f"{path}: listed in {base / PRETRAINED_INDEX} but missing")
    return ShippedModel(domain, path, info, "pretrained")


def list_pretrained(folder: Path | None = None, errors: list[str] | None = None) -> list[ShippedModel]:
    """Every shipped pretrained network, by domain. ``errors``: where a damaged entry's one line goes (the
    others are still listed); None: it is raised (:class:`ShipError`)."""
    base = folder or shipped_dir()
    try:
        domains = sorted(_read_index(base)["domains"])
    except ShipError as err:
        if errors is None:
            raise
        errors.append(str(err))
        return []
    return _each(domains, lambda d: pretrained_model(d, base), errors)


def pretrained_checkpoint(domain: str, folder: Path | None = None) -> Path:
    """The verified checkpoint ``pretrain.<domain>.init: shipped`` continues; ShipError when none is shipped."""
    model = pretrained_model(domain, folder)
    if model is None:
        raise ShipError(f"no pretrained {domain} network is shipped in {folder or shipped_dir()} (set "
                        f"pretrain.{domain}.init: null to pretrain from scratch)")
    model.verify()
    return model.checkpoint


def ship_pretrained(domain: str, checkpoint: str | os.PathLike, *,
                    dest: str | os.PathLike | None = None) -> ShippedModel:
    """Ship a pretraining's training state (its ``last.pt``) as the pretrained network of ``domain``.

    The checkpoint must carry provenance segments (a pretraining of this version writes them). The file is
    copied as it is (at most :data:`MAX_BYTES`) and the index entry names its sha256, config and provenance
    (segments and totals: epochs, shapes seen, CPU hours, the real-validation metric at each segment's end).
    """
    from plad.learn.state import check_training_state
    from plad.model.checkpoint import CheckpointError, read_checkpoint

    checkpoint = Path(checkpoint)
    try:
        payload = read_checkpoint(checkpoint)
    except CheckpointError as err:
        raise ShipError(str(err)) from None
    if payload.get("domain") != domain:
        raise ShipError(f"{checkpoint}: a {payload.get('domain')} checkpoint, not a {domain} one")
    prov = payload.get("provenance")
    if not (isinstance(prov, dict) and prov.get("segments")) or "optimizer" not in payload:
        raise ShipError(f"{checkpoint}: no training state with provenance segments (ship a pretraining's last.pt)")
    try:   # the one check of a training state: what is shipped can be continued
        check_training_state(checkpoint, payload)
    except CheckpointError as err:
        raise ShipError(str(err)) from None
    size = checkpoint.stat().st_size
    if size > MAX_BYTES:
        raise ShipError(f"{checkpoint}: {size / 2**20:.1f} MiB, above the {MAX_BYTES // 2**20} MiB a shipped file "
                        "may have")
    from plad.fsutil import atomic_write_text, file_lock

    base = Path(dest or shipped_dir())
    try:
        (base / domain).mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ShipError(f"{base / domain}: cannot write there ({err.strerror})") from None
    target = base / domain / PRETRAINED
    # the checkpoint and its index entry change together: under the domain's lock (which verify() shares),
    # and the index, which every domain shares, under its own
    with file_lock(base / domain / LOCK), file_lock(base / f".{PRETRAINED_INDEX}.lock"):
        _settle_index(base)   # a ship killed between its renames: finished (or undone) first
        # both new files complete beside the old ones, then renamed into place, the checkpoint first (a kill
        # between the renames leaves a pending index naming the checkpoint in place: read as the index)
        _copy(checkpoint, _pending(target))
        info = {"domain": domain, "method": "sp",
                "checkpoint": {"file": f"{domain}/{PRETRAINED}", "sha256": sha256_file(_pending(target)),
                               "bytes": size, "shipped_from": checkpoint.name},
                "config": payload.get("config"), "provenance": prov}
        try:
            index = _read_index(base)
        except ShipError:   # a damaged index is replaced by one naming the networks whose entries are intact
            index = {"format": PRETRAINED_FORMAT, "domains": {}}
        index["domains"] = {d: e for d, e in index["domains"].items() if _entry_problem(base, d, e) is None}
        index["domains"][domain] = info
        atomic_write_text(_pending(base / PRETRAINED_INDEX), json.dumps(index, indent=1) + "\n")
        os.replace(_pending(target), target)
        os.replace(_pending(base / PRETRAINED_INDEX), base / PRETRAINED_INDEX)
    return ShippedModel(domain, target, info, "pretrained")


def describe_totals(model: ShippedModel) -> str:
    """``"<epochs> epochs, <shapes> shapes, <h> CPU h"`` of a pretrained network's provenance."""
    t = (model.info.get("provenance") or {}).get("totals") or {}
    hours = f"{t.get('train_seconds', 0) / 3600:.1f} h of training"
    if t.get("cpu_hours_complete", True):
        hours += f" ({t.get('cpu_hours', 0):.1f} CPU h)"
    else:   # a segment written before threads were recorded
        hours += f" ({t.get('cpu_hours', 0):.1f} CPU h recorded, some segments' threads unknown)"
    if t.get("gpu_hours"):
        hours += f", {t['gpu_hours']:.1f} GPU h"
    return f"{t.get('epochs', '?')} epochs, {t.get('shapes_seen', 0) / 1e6:.2f} M shapes, {hours}"


#: the indexes of the networks teaching may start from (``teach.<domain>.init``), kept in files of their own so
#: that shipping a taught network does not change the start of the stage that made it: ``search_seeded``, each
#: domain's search-seeded LEST+ST+WS network as it was shipped before a taught network replaced it; ``taught``,
#: a taught network as it was shipped, the start of a later teaching run that continues it (a fresh clone
#: rebuilds that run without training its earlier ones again; the index names the commit and run it came from)
KEPT_STARTS = {"search_seeded": "search_seeded.json", "taught": "taught.json"}


def kept_checkpoint(domain: str, name: str, folder: Path | None = None) -> Path:
    """The kept network ``name`` (:data:`KEPT_STARTS`) of ``domain`` that ``teach.<domain>.init: <name>`` starts
    from, verified against the sha256 its index names; ShipError naming the file when it is missing or
    differs."""
    folder = Path(folder) if folder is not None else shipped_dir()
    index_path = folder / KEPT_STARTS[name]
    what = name.replace("_", "-")
    try:
        entry = json.loads(index_path.read_text())["models"][domain]
    except FileNotFoundError:
        raise ShipError(f"{index_path}: missing (the index of the {what} networks)") from None
    except (ValueError, KeyError, TypeError):
        raise ShipError(f"{index_path}: no {what} network of {domain} is indexed") from None
    path = folder / entry["file"]
    if not path.is_file():
        raise ShipError(f"{path}: missing (the {what} {domain} network {index_path.name} names)")
    got = sha256_file(path)
    if got != entry["sha256"]:
        raise ShipError(f"{path}: sha256 {got[:12]} differs from {entry['sha256'][:12]} in {index_path.name}")
    return path


def keep_taught(domain: str, commit: str, folder: Path | None = None) -> dict:
    """Copy the shipped taught model of ``domain`` to ``<domain>/taught.pt`` and index it in ``taught.json`` as
    shipped at ``commit`` (the start ``teach.<domain>.init: taught`` continues); returns the index entry.
    ShipError when there is no shipped model, it differs from its sidecar or it is not a taught network."""
    from plad.fsutil import atomic_write_text

    folder = Path(folder) if folder is not None else shipped_dir()
    shipped = shipped_model(domain, folder)
    if shipped is None:
        raise ShipError(f"{folder / domain}: no shipped model to keep")
    shipped.verify()
    if shipped.info.get("method") != "taught":
        raise ShipError(f"{shipped.checkpoint}: method {shipped.info.get('method')!r}, not a taught network")
    target = folder / domain / "taught.pt"
    _copy(shipped.checkpoint, target)
    index_path = folder / KEPT_STARTS["taught"]
    index = json.loads(index_path.read_text()) if index_path.exists() else {"format": "plad-taught-1", "models": {}}
    metrics = shipped.info.get("metrics") or {}
    entry = {"file": f"{domain}/taught.pt", "sha256": sha256_file(target),
             "from": shipped.info["checkpoint"].get("shipped_from"),
             "shipped_as": f"plad/shipped/{domain}/model.pt at {commit}",
             "test": {k: metrics[k] for k in ("metric", "beam", "mean", "n") if k in metrics}}
    index["models"] = {**index.get("models", {}), domain: entry}
    atomic_write_text(index_path, json.dumps(index, indent=1) + "\n")
    return entry


def search_seeded_checkpoint(domain: str, folder: Path | None = None) -> Path:
    """The search-seeded network of ``domain`` that ``teach.<domain>.init: search_seeded`` starts from
    (:func:`kept_checkpoint`)."""
    return kept_checkpoint(domain, "search_seeded", folder)
