"""The force model's MLflow models-from-code entry point."""

import pytest

from tests.helpers import import_entry, lazy_model_class


def test_loading_the_pyfunc_module_sets_the_model_and_does_not_ask_for_type_hints():
    model, err = import_entry("dozerlab.learn.pyfunc_entry")
    assert model == "ForcePyfunc"
    assert "Add type hints" not in err


@pytest.mark.slow  # fresh interpreters importing torch
def test_jobs_read_models_without_mlflow_and_older_directories_still_find_the_class():
    assert lazy_model_class("dozerlab.learn.pyfunc", "ForcePyfunc") == [
        "False",
        "ForcePyfunc",
        "True",
    ]
