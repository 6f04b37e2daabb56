"""The MLflow side of the pyfunc model directories: each family's ``PythonModel`` class
(``ForcePyfunc``, ``DynamicsPyfunc``), made on first use (``pyfunc.python_model_class``).

Only MLflow's loader (through the models-from-code entries) and the save and log calls import
this, and MLflow with it: the jobs read a model directory directly (``PyfuncFormat.load``),
without the 1–2 s of importing MLflow.
"""

from __future__ import annotations

import contextlib
import json
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from mlflow.pyfunc.model import PythonModel


# No type hints on predict: MLflow would read them as a competing input schema (the signature
# already states it). It warns about their absence when the class is defined, in every job and
# script that loads a model, under a filter of its own, so the warning is caught, not filtered.
@contextlib.contextmanager
def untyped_predict() -> Iterator[None]:
    """Define a PythonModel with an untyped ``predict`` inside: MLflow's request for type hints
    is dropped, every other warning passes."""
    with warnings.catch_warnings(record=True) as caught:
        yield
    for w in caught:
        if "Add type hints to the `predict` method" not in str(w.message):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


with untyped_predict():

    class BuiltModel(PythonModel):
        """A pyfunc model that rebuilds ``self.model`` from its directory's artifacts with the
        subclass's ``build(meta, weights)`` (a staticmethod); the subclass defines ``predict``."""

        build: Callable[[dict[str, Any], str | Path], Any]

        def load_context(self, context: Any) -> None:
            meta = json.loads(Path(context.artifacts["meta"]).read_text())
            self.model = self.build(meta, context.artifacts["weights"])


def model_class(
    name: str,
    what: str,
    build: Callable[[dict[str, Any], str | Path], Any],
    predict: Callable[[Any, Any], Any],
) -> type:
    """A :class:`BuiltModel` named ``name`` (wrapping a ``what``) whose ``predict`` answers
    ``predict(model, model_input)``."""

    def predict_method(self, context, model_input, params=None):
        return predict(self.model, model_input)

    predict_method.__doc__ = predict.__doc__
    with untyped_predict():
        return type(
            name,
            (BuiltModel,),
            {
                "build": staticmethod(build),
                "predict": predict_method,
                "__module__": __name__,
                "__doc__": f"MLflow pyfunc wrapper around a {what}.",
            },
        )
