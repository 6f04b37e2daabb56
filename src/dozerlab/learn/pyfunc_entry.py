"""MLflow models-from-code entry point: the saved model directory runs this file (not a pickle)."""

import mlflow

from dozerlab.learn.pyfunc import ForcePyfunc

mlflow.models.set_model(ForcePyfunc())
