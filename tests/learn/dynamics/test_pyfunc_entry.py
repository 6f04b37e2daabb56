"""The evolution model's MLflow models-from-code entry point."""

import subprocess
import sys

from tests.helpers import import_entry


def test_loading_the_pyfunc_module_sets_the_model_and_does_not_ask_for_type_hints():
    model, err = import_entry("dozerlab.learn.dynamics.pyfunc_entry")
    assert model == "DynamicsPyfunc"
    assert "Add type hints" not in err


def test_jobs_read_models_without_mlflow_and_older_directories_still_find_the_class():
    code = (
        "import sys, dozerlab.learn.dynamics.pyfunc as m\n"
        "print('mlflow' in sys.modules)\n"
        "print(m.DynamicsPyfunc.__name__, 'mlflow' in sys.modules)\n"  # as a directory saved earlier asks
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "DynamicsPyfunc", "True"]
