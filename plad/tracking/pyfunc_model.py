"""The pyfunc model of a PLAD checkpoint, logged as MLflow "models from code".

Not imported by the package: :func:`plad.tracking.serving.log_pyfunc` passes this file's path to
``mlflow.pyfunc.log_model``, which copies it into the logged model and runs it (as a module of its
own) whenever the model is loaded; the last line hands MLflow the model object. Nothing is pickled,
so a stored model depends on the package only through what this file imports: one name,
``plad.tracking.serving.Predictor``, which stays put when modules move. The checkpoint is the
model's artifact ``checkpoint``, the default beam width its model config ``beam``.
"""
import mlflow.pyfunc
import numpy as np
from mlflow.models import set_model

from plad.tracking.serving import Predictor


class PladPyfuncModel(mlflow.pyfunc.PythonModel):
    """Shapes in, programs out (:class:`plad.tracking.serving.Predictor`): ``predict(context, shapes,
    params={"beam": k})`` -> a DataFrame of programs and their metric values."""

    def load_context(self, context):
        beam = (context.model_config or {}).get("beam", 10)
        self.predictor = Predictor(context.artifacts["checkpoint"], beam)

    # The ndarray hint tells MLflow not to infer a schema from the hints: the input is passed through
    # untouched (DataFrames and lists work too; Predictor reads them).
    def predict(self, context, model_input: np.ndarray, params=None):
        return self.predictor.predict(model_input, params)


set_model(PladPyfuncModel())
