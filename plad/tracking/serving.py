"""A PLAD checkpoint as an MLflow pyfunc model: shapes in, programs out.

:func:`log_pyfunc` logs a checkpoint as a model of the active run (and
registers it); :func:`load_registered` loads one back. Models are logged as
MLflow "models from code": the file ``plad/tracking/pyfunc_model.py`` is copied
into the model and run when it is loaded (no pickled object), the checkpoint
is the artifact ``checkpoint`` and the default beam the model config ``beam``.
That file reaches the package through one name, :class:`Predictor` (here), so
modules may move without breaking stored models as long as it stays importable
as ``plad.tracking.serving.Predictor``.

Models logged before (a pickled instance of ``plad.tracking.PladPyfuncModel``)
still load: :func:`legacy_pyfunc_class` is that class, found by that name.
Nothing here imports torch or MLflow at import time: ``import plad.tracking``
stays cheap (``plad models`` lists the registry without them).
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from plad import __version__
from plad.tracking.store import mlflow_module, open_store

#: the models-from-code file that every logged model carries (MLflow copies it into the model)
MODEL_CODE = Path(__file__).with_name("pyfunc_model.py")
#: the module that serves the legacy pickled class by name (see plad/tracking/__init__.py)
PUBLIC_MODULE = "plad.tracking"


def pip_requirements() -> list[str]:
    """Requirements of the logged pyfunc model (no environment capture: offline-safe)."""
    return ["torch", "numpy", "pandas", f"plad=={__version__}"]


def _model_arguments(checkpoint_path: str | os.PathLike, beam: int) -> dict[str, Any]:
    """What :func:`log_pyfunc` and :func:`load_checkpoint_pyfunc` pass to MLflow (but the destination)."""
    from mlflow.models import ModelSignature
    from mlflow.types import ParamSchema, ParamSpec

    # a params-only signature: without it MLflow drops predict(params=...) with a warning
    signature = ModelSignature(inputs=None, outputs=None,
                               params=ParamSchema([ParamSpec("beam", "long", int(beam))]))
    return {"python_model": str(MODEL_CODE), "model_config": {"beam": int(beam)},
            "artifacts": {"checkpoint": str(Path(checkpoint_path))},
            "pip_requirements": pip_requirements(), "signature": signature}


def log_pyfunc(checkpoint_path: str | os.PathLike, *, registered_name: str | None = None,
               beam: int = 10) -> str:
    """Log a checkpoint as a pyfunc model (artifact path ``model``) of the active run.

    Returns ``models:/<name>/<version>`` when ``registered_name`` is given
    (the model is registered under it), else the logged model's URI.
    """
    mlflow = mlflow_module()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*input example.*")
        info = mlflow.pyfunc.log_model(name="model", registered_model_name=registered_name,
                                       **_model_arguments(checkpoint_path, beam))
    if registered_name:
        return f"models:/{registered_name}/{info.registered_model_version}"
    return info.model_uri


def load_registered(uri: str) -> Any:
    """The pyfunc model at ``uri`` (``models:/name@champion``, ``models:/name/3``, ...)."""
    open_store()
    return mlflow_module().pyfunc.load_model(uri)


def load_checkpoint_pyfunc(checkpoint_path: str | os.PathLike, beam: int = 10) -> Any:
    """A checkpoint file as the pyfunc model :func:`log_pyfunc` would log, without a store.

    Saved as an MLflow model in a temporary folder (not under the working directory) and
    loaded from there, so it behaves exactly as a logged one.
    """
    import tempfile

    mlflow = mlflow_module()
    folder = Path(tempfile.mkdtemp(prefix="plad-pyfunc-")) / "model"
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*input example.*")
        mlflow.pyfunc.save_model(str(folder), **_model_arguments(checkpoint_path, beam))
    return mlflow.pyfunc.load_model(str(folder))


# -- the pyfunc wrapper ---------------------------------------------------------------------------
def _input_items(model_input: Any, shape: tuple[int, ...]) -> list:
    """One :class:`plad.data.inputs.Item` per shape of the input, read by the one reader of every command
    (:func:`plad.data.inputs.read_array`: sizes, NaN, empty and full targets): an ndarray (one shape or a
    batch), a list of arrays, a dict of one such entry, or a DataFrame (one column of arrays, or one
    flattened shape per row). A shape that cannot be used is an item with its error."""
    from plad.data.inputs import Item, read_array

    if hasattr(model_input, "columns") and hasattr(model_input, "to_numpy"):   # DataFrame
        frame = model_input
        if frame.shape[1] == 1:
            model_input = list(frame.iloc[:, 0])
        else:  # one flattened shape per row
            cells = frame.to_numpy()
            if cells.shape[1] != int(np.prod(shape)):
                return [Item("input", Path("<input>"), error=f"expected {int(np.prod(shape))} columns (one "
                                                                f"flattened shape per row), got {cells.shape[1]}")]
            model_input = cells.reshape(len(frame), *shape)
    elif isinstance(model_input, dict) and len(model_input) == 1:
        model_input = next(iter(model_input.values()))
    if isinstance(model_input, np.ndarray) and model_input.ndim == len(shape) + 1 and len(model_input) == 0:
        return []   # an empty batch: no rows
    if isinstance(model_input, (list, tuple)) or (isinstance(model_input, np.ndarray) and model_input.dtype == object):
        items = []   # one shape per entry, each by the rule for one array
        for i, entry in enumerate(model_input):
            for it in read_array(entry, shape, name=f"input_{i}", source=f"<input {i}>"):
                items.append(it)
        return items
    return read_array(model_input, shape, source="<input>")


class Predictor:
    """Shapes in, programs out: best-of-beam inference with a PLAD checkpoint; what a logged model runs.

    ``Predictor(checkpoint, beam)`` loads the checkpoint (on CUDA when present). ``predict(model_input,
    params=None)``: ``model_input`` is a bool/uint8 array (N, *shape), one shape (*shape), a list of
    them or a one-column DataFrame of them; returns a DataFrame with one row per shape and columns
    ``program`` (text), the domain metric's name and ``error`` (None, or why that shape could not be read:
    its program is None and its metric NaN, the other rows are answered). ``params={"beam": k}``
    overrides the beam width (checked as the CLI checks ``--beam``).

    Stored models import this class by its name, ``plad.tracking.serving.Predictor``
    (``plad/tracking/pyfunc_model.py``): keep that name and this interface.
    """

    #: shapes per beam search (bounds memory: beam x batch candidates are executed at once)
    batch_size = 64

    def __init__(self, checkpoint: str | os.PathLike, beam: int = 10):
        import torch

        from plad.domains import get_domain
        from plad.model.checkpoint import load_model

        # CUDA when present (as plad.device.default_device, which the stages logging models do not depend on)
        self.model, name = load_model(checkpoint, "cuda" if torch.cuda.is_available() else "cpu")
        self.domain = get_domain(name)
        self.beam = int(beam)

    def predict(self, model_input: Any, params: dict[str, Any] | None = None) -> Any:
        import pandas as pd
        import torch

        from plad.config import MAX_BEAM_ROWS, check_beam
        from plad.model.decode import infer_programs

        beam = check_beam((params or {}).get("beam", self.beam))   # 0, -1, 10**9: a ValueError, as in the CLI
        items = _input_items(model_input, tuple(self.domain.shape))
        good = [it for it in items if it.error is None]
        device = next(self.model.parameters()).device
        found: dict[int, tuple[str, float]] = {}
        step = max(1, min(self.batch_size, MAX_BEAM_ROWS // beam))   # memory bounded whatever the beam
        for i in range(0, len(good), step):
            chunk = good[i:i + step]
            targets = torch.from_numpy(np.stack([it.shape for it in chunk])).to(device)
            result = infer_programs(self.model, self.domain, targets, beam)
            for it, p, v in zip(chunk, result.programs, result.values.double().cpu().tolist()):
                found[id(it)] = (self.domain.format(p), v)
        return pd.DataFrame({
            "program": [found[id(it)][0] if it.error is None else None for it in items],
            self.domain.metric.name: [found[id(it)][1] if it.error is None else float("nan") for it in items],
            "error": [it.error for it in items],
        })


# -- models logged before models from code ---------------------------------------------------------
def _build_legacy_class() -> type:
    # Until models from code, a logged model was a pickled instance of this class (attributes ``beam``,
    # ``model`` and ``domain``, the last two None), found by its public name plad.tracking.PladPyfuncModel:
    # kept so that those models still load. It subclasses an mlflow class, so it is built on first use.
    import mlflow.pyfunc

    def load_context(self, context):
        self.predictor = Predictor(context.artifacts["checkpoint"], self.beam)

    def predict(self, context, model_input, params=None):
        return self.predictor.predict(model_input, params)

    # An ndarray hint tells MLflow not to infer a schema from the hints (the input is passed through
    # untouched; DataFrames work too); without any hint MLflow warns, unfilterably.
    predict.__annotations__ = {"model_input": np.ndarray}

    def __init__(self, beam: int = 10):
        self.beam = int(beam)
        self.model = None
        self.domain = None

    namespace = {"__module__": PUBLIC_MODULE, "__qualname__": "PladPyfuncModel",
                 "__doc__": "A PLAD model as logged before models from code (pickled); see :class:`Predictor`.",
                 "__init__": __init__, "load_context": load_context, "predict": predict}
    return type("PladPyfuncModel", (mlflow.pyfunc.PythonModel,), namespace)


_LEGACY_CLASS: list[type] = []   # built once


def legacy_pyfunc_class() -> type:
    """``plad.tracking.PladPyfuncModel``, the class of models logged as pickles (built on first call)."""
    if not _LEGACY_CLASS:
        _LEGACY_CLASS.append(_build_legacy_class())
    return _LEGACY_CLASS[0]
