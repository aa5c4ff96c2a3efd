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
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from plad.errors import RunFailure
from plad.fsutil import sha256_file

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


@dataclass(frozen=True)
class ShippedModel:
    domain: str
    checkpoint: Path
    info: dict[str, Any]
    #: "model" (model.pt: the network `plad infer` uses) or "pretrained" (pretrained.pt, continued by pretraining)
    kind: str = "model"

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
    readable JSON is a :class:`ShipError`."""
    base = (folder or shipped_dir()) / domain
    ckpt, side = base / CHECKPOINT, base / SIDECAR
    if not (ckpt.is_file() and side.is_file()):
        return None
    try:
        info = json.loads(side.read_text())
    except (OSError, ValueError) as err:
        raise ShipError(f"{side}: not a readable sidecar ({err})") from None
    if not isinstance(info, dict) or info.get("format") != FORMAT:
        raise ShipError(f"{side}: not a shipped-model sidecar (expected format {FORMAT})")
    return ShippedModel(domain, ckpt, info)


def list_shipped(folder: Path | None = None) -> list[ShippedModel]:
    """Every shipped model, by domain name."""
    base = folder or shipped_dir()
    if not base.is_dir():
        return []
    found = (shipped_model(d.name, base) for d in sorted(base.iterdir()) if d.is_dir())
    return [m for m in found if m is not None]


def _git(root: Path, *args: str) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


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
    status = _git(root, "status", "--porcelain", "--untracked-files=no")
    return {"params_file": _portable(params_path, root), "profile": params.get("profile"), "params": sections,
            "git": {"revision": _git(root, "rev-parse", "HEAD"), "dirty": bool(status) if status is not None else None},
            "data": data}


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
    from plad.fsutil import atomic_write_text, file_lock
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
        current = shipped_model(domain, folder.parent)   # again under the lock: another ship may have come first
        if current is not None and not force:
            _refuse_worse(test, current, checkpoint, folder)
        if current is not None:   # keep the model being replaced (one generation; git keeps the older ones)
            keep = folder / PREVIOUS
            keep.mkdir(exist_ok=True)
            for name in (CHECKPOINT, SIDECAR):
                shutil.copy2(folder / name, keep / f".{name}.part")
                os.replace(keep / f".{name}.part", keep / name)
        out = save_checkpoint(folder / CHECKPOINT, model, domain, names)
        info = {
            "format": FORMAT, "domain": domain, "method": method,
            "checkpoint": {"file": CHECKPOINT, "sha256": sha256_file(out), "bytes": out.stat().st_size,
                           "shipped_from": _portable(checkpoint, root)},
            "config": model.cfg.to_dict(), "tokens": list(names),
            "metrics": test, "metrics_file": _portable(metrics, root),
            "provenance": provenance,
        }
        atomic_write_text(folder / SIDECAR, json.dumps(info, indent=1) + "\n")
    return ShippedModel(domain, out, info)


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


def _read_index(base: Path) -> dict[str, Any]:
    path = base / PRETRAINED_INDEX
    if not path.is_file():
        return {"format": PRETRAINED_FORMAT, "domains": {}}
    try:
        index = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ShipError(f"{path}: not a readable index of pretrained networks ({err})") from None
    if not isinstance(index, dict) or index.get("format") != PRETRAINED_FORMAT or \
            not isinstance(index.get("domains"), dict):
        raise ShipError(f"{path}: not an index of pretrained networks (expected format {PRETRAINED_FORMAT})")
    return index


def pretrained_model(domain: str, folder: Path | None = None) -> ShippedModel | None:
    """The shipped pretrained network of ``domain`` (its index entry as ``info``), or None."""
    base = folder or shipped_dir()
    info = _read_index(base)["domains"].get(domain)
    if info is None:
        return None
    path = base / info["checkpoint"]["file"]
    if not path.is_file():
        raise ShipError(f"{path}: listed in {base / PRETRAINED_INDEX} but missing")
    return ShippedModel(domain, path, info, "pretrained")


def list_pretrained(folder: Path | None = None) -> list[ShippedModel]:
    base = folder or shipped_dir()
    return [m for d in sorted(_read_index(base)["domains"]) if (m := pretrained_model(d, base)) is not None]


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
    import shutil
    import tempfile

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
        with tempfile.NamedTemporaryFile(dir=target.parent, delete=False) as tmp:   # atomic: never half a file
            with open(checkpoint, "rb") as src:
                shutil.copyfileobj(src, tmp)
        os.replace(tmp.name, target)
        info = {"domain": domain, "method": "sp",
                "checkpoint": {"file": f"{domain}/{PRETRAINED}", "sha256": sha256_file(target), "bytes": size,
                               "shipped_from": checkpoint.name},
                "config": payload.get("config"), "provenance": prov}
        index = _read_index(base)
        index["domains"][domain] = info
        atomic_write_text(base / PRETRAINED_INDEX, json.dumps(index, indent=1) + "\n")
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
