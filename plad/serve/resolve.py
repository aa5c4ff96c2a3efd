"""Which model a command uses, in one place (``plad infer``, the pyfunc model of :func:`load_pyfunc`).

In order:

1. the model the user named (``--model``): a checkpoint file or an MLflow model URI;
2. the registered champion ``models:/plad-<domain>@champion`` of the MLflow store, *if a
   store is configured*: ``$MLFLOW_TRACKING_URI`` is set (for a SQLite URI: and its database
   file exists), or ``./mlflow.db`` exists in the current directory (the store ``dvc repro``
   writes there); only if that store has the champion, and only if it was evaluated on the
   domain's real, full test set (its version's or run's ``plad.test_set`` tag is ``full``:
   :func:`plad.tracking.registry.evaluated_on`; a smoke run's models, measured on a few shapes,
   are registered under names of their own anyway, e.g. ``plad-<domain>-smoke``);
3. the model shipped with the package (:mod:`plad.shipped`).

:func:`default_model` says which of 2 and 3 a domain gets and why, without downloading anything
(``plad models`` prints it); :func:`resolve` downloads the champion it chose.

A look-up never creates anything: an unconfigured store is not opened (opening a SQLite URI
would create an empty database), and a champion is downloaded to a temporary folder.
Only the checkpoint's location is resolved here; loading it (torch) is the caller's, or
:func:`load_pyfunc`'s, which returns it as an MLflow pyfunc model. No pipeline stage imports
this module (they name their models by the layout).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from plad.errors import RunFailure
from plad.shipped import ShipError, ShippedModel, pretrained_model, shipped_dir, shipped_model

TRACKING_ENV = "MLFLOW_TRACKING_URI"


class ModelError(RunFailure):
    """The model cannot be found or used; one line (exit status 1, as a damaged checkpoint: :mod:`plad.errors`)."""


def champion_uri(domain: str) -> str:
    return f"models:/plad-{domain}@champion"


def configured_store() -> str | None:
    """The MLflow store to look for champions in, or ``None`` when none is configured (see the module doc)."""
    from plad.tracking.store import sqlite_path, tracking_uri

    uri = os.environ.get(TRACKING_ENV)
    if uri:
        # a local store that does not exist yet would be created by opening it: not configured
        db = sqlite_path(uri)
        if db is not None:
            return uri if db.is_file() else None
        if uri.startswith("file:") or "://" not in uri:
            local = Path(urlparse(uri).path if uri.startswith("file:") else uri)
            return uri if local.exists() else None
        return uri
    return tracking_uri() if (Path.cwd() / "mlflow.db").is_file() else None


@dataclass(frozen=True)
class Choice:
    """A resolved model: ``kind`` is ``file``, ``mlflow`` (a URI the user named), ``champion`` or ``shipped``."""

    kind: str
    #: what the user is shown: the path, the URI, or the shipped model's description
    ref: str
    #: the checkpoint file on this machine (a temporary download for ``mlflow`` and ``champion``)
    path: Path
    #: why earlier choices were passed over (e.g. the configured store has no champion)
    notes: tuple[str, ...] = field(default=())

    @property
    def uri(self) -> str | None:
        """The MLflow model URI of a registered or logged model, else ``None``."""
        return self.ref if self.kind in ("mlflow", "champion") else None


@dataclass(frozen=True)
class Default:
    """The model ``plad infer DOMAIN`` uses without ``--model``, before anything is downloaded.

    ``kind``: ``champion``, ``shipped`` or ``none``; ``model``: the registered version
    (``models:/plad-<domain>/<version>``), the shipped checkpoint's path, or ``""``; ``why``: one line
    saying why this one (and why the champion is passed over, where it is)."""

    kind: str
    model: str
    why: str
    #: why the champion was passed over, one line each (empty when it is used or no store is configured)
    notes: tuple[str, ...] = field(default=())
    #: the champion's URI (kind ``champion``), or the shipped model (kind ``shipped``)
    uri: str | None = None
    shipped: ShippedModel | None = None


def _download(uri: str) -> Path:
    from plad.tracking.registry import download_checkpoint
    from plad.tracking.store import StoreError

    try:
        return download_checkpoint(uri)
    except StoreError as err:    # the store cannot be opened (one line naming it and what to do)
        raise ModelError(str(err)) from None
    except LookupError as err:   # not in the store
        raise ModelError(str(err)) from None
    except ValueError as err:    # a logged model without a checkpoint
        raise ModelError(str(err)) from None


def _champion(domain: str) -> tuple[str | None, str]:
    """(``models:/plad-<domain>/<version>``, why it is the default) when the configured store's champion may
    be ``plad infer``'s default; (None, why not) otherwise. Reads tags only (MLflow), downloads nothing."""
    from plad.tracking.registry import FULL, PROFILE_TAG, SUBSET, champion_record, evaluated_on
    from plad.tracking.store import StoreError

    uri = champion_uri(domain)
    name = uri.removeprefix("models:/").split("@", 1)[0]
    try:
        found = champion_record(name)
    except StoreError as err:   # the store cannot be opened (one line naming it and what to do)
        return None, f"no champion in the MLflow store ({err})"
    if found is None:
        return None, f"no champion in the MLflow store ({uri}: not registered in {configured_store()})"
    version, tags = found
    profile = tags.get(PROFILE_TAG) or "unknown"
    test_set = evaluated_on(tags)
    if test_set != FULL:
        measured = "on a subset of the test set" if test_set == SUBSET else "on an unknown test set (no " \
            "plad.test_set tag, and not a cpu or paper profile run)"
        return None, (f"{uri} (version {version}, profile {profile}) was evaluated {measured}, so it is not a "
                      f"default; --model {uri} uses it")
    return f"models:/{name}/{version}", (f"{uri} (version {version}, profile {profile}): the MLflow store's "
                                         f"champion, evaluated on the full test set")


def _shipped(domain: str) -> ShippedModel | None:
    """The fine-tuned network shipped for ``domain``, else its pretrained one (a domain that ships no
    fine-tuned network yet), else None."""
    try:
        return shipped_model(domain) or pretrained_model(domain)
    except ShipError as err:
        raise ModelError(str(err)) from None


def default_model(domain: str) -> Default:
    """What ``plad infer DOMAIN`` uses without ``--model`` and why (:class:`Default`): the configured store's
    champion if it was evaluated on the full test set, else the shipped model. Nothing is downloaded or
    verified here (:func:`resolve` does both); a damaged shipped sidecar is a :class:`ModelError`."""
    if configured_store() is None:
        return _shipped_default(domain, (), "no MLflow store is configured")
    found, why = _champion(domain)
    if found is not None:
        return Default("champion", found, why, uri=champion_uri(domain))
    return _shipped_default(domain, (why,), why)


def _shipped_default(domain: str, notes: tuple[str, ...], passed: str) -> Default:
    """The shipped model as the default, the champion ``passed`` over (why, one line)."""
    shipped = _shipped(domain)
    if shipped is None:
        return Default("none", "", f"no {domain} model: {passed}, and none is shipped in {shipped_dir()}", notes)
    what = "pretrained network" if shipped.kind == "pretrained" else "model"
    return Default("shipped", str(shipped.checkpoint), f"the shipped {what}, as {passed}", notes, shipped=shipped)


def resolve(domain: str, model: str | None = None) -> Choice:
    """The checkpoint ``domain``'s commands use; :class:`ModelError` (one line) when there is none."""
    from plad.tracking.registry import is_model_uri

    if model:
        path = Path(model)
        if path.is_file():
            return Choice("file", str(path), path)
        if is_model_uri(model):
            if configured_store() is None:   # opening the default store would create ./mlflow.db
                env = os.environ.get(TRACKING_ENV)
                why = f"${TRACKING_ENV}={env} does not exist" if env else f"${TRACKING_ENV} is unset and there " \
                    f"is no ./mlflow.db"
                raise ModelError(f"{model}: no MLflow store to look it up in ({why}); a look-up creates none")
            return Choice("mlflow", model, _download(model))
        raise ModelError(f"{model}: no such checkpoint file, and not an MLflow model URI (models:/NAME@ALIAS, "
                         "models:/NAME/VERSION, runs:/RUN/model)")
    default = default_model(domain)
    notes = list(default.notes)
    if default.kind == "champion":
        try:
            # the version chosen, not the alias again: the alias may have moved since its tags were read
            return Choice("champion", default.uri, _download(default.model))
        except ModelError as err:
            notes.append(f"no champion in the MLflow store ({err})")
            default = _shipped_default(domain, tuple(notes), notes[-1])
    shipped = default.shipped
    if shipped is None:
        where = "no MLflow store is configured" if not notes else notes[0]
        raise ModelError(f"no {domain} model: {where}, and none is shipped in {shipped_dir()}; pass --model a "
                         "checkpoint file, or train and register one with `dvc repro`")
    try:
        shipped.verify()
    except ShipError as err:
        raise ModelError(str(err)) from None
    return Choice("shipped", shipped.describe(), shipped.checkpoint, tuple(notes))


def load_pyfunc(domain: str, model: str | None = None, beam: int = 10) -> Any:
    """The pyfunc model of ``domain`` chosen as ``plad infer`` chooses (:func:`resolve`).

    ``model`` (a checkpoint file or an MLflow model URI), else the champion of a configured
    store, else the shipped model. A logged model is loaded as it was logged; a checkpoint file
    (``model`` or the shipped one) becomes the same kind of pyfunc model
    (:func:`plad.tracking.serving.load_checkpoint_pyfunc`), so every choice returns an object
    with ``predict(shapes, params={"beam": k})``. Raises :class:`ModelError` (one line) when
    there is no model.
    """
    from plad.tracking.serving import load_checkpoint_pyfunc, load_registered

    choice = resolve(domain, model)
    if choice.uri is not None:
        return load_registered(choice.uri)
    return load_checkpoint_pyfunc(choice.path, beam)
