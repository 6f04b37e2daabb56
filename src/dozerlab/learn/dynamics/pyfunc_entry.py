"""MLflow models-from-code entry point: the saved model directory runs this file (not a pickle)."""

import mlflow

from dozerlab.learn.dynamics.pyfunc import DynamicsPyfunc

mlflow.models.set_model(DynamicsPyfunc())
