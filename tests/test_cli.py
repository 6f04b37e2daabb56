"""The command line: every command registered once without heavy imports, the commands of no
layer (``config``, ``mlflow-start``, ``mlflow-end``), and errors a user can fix printed without a
traceback."""

import json

import pytest
import yaml

from dozerlab.cli import build_parser, main
from dozerlab.config import load_config
from tests.helpers import imported_by

COMMANDS = [
    "config",
    "mlflow-start",
    "mlflow-end",
    "mlflow-ingest",
    "report",
    "bed",
    "trajectory",
    "simulate",
    "plot-fields",
    "import-legacy",
    "export-legacy",
    "train",
    "validate",
    "evaluate",
    "train-dynamics",
    "validate-dynamics",
    "reduce",
    "reduce-points",
    "compare-reduced",
    "verify",
]


def test_every_command_is_registered_once_in_order():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert list(sub.choices) == COMMANDS


def test_config_prints_the_complete_document(tmp_path, capsys):
    path = tmp_path / "c.yaml"
    path.write_text("solver: {dt: 0.005}\n")
    assert main(["config", str(path)]) == 0
    printed = yaml.safe_load(capsys.readouterr().out)
    assert printed == load_config({"solver": {"dt": 0.005}})
    assert printed["solver"]["iterations"] == load_config()["solver"]["iterations"]


def test_config_error_names_the_field_and_exits_2(capsys):
    assert main(["config", json.dumps({"solver": {"dt": -1}})]) == 2
    err = capsys.readouterr().err
    assert err.startswith("dozerlab config: error:") and "solver.dt" in err
    assert "Traceback" not in err


def test_mlflow_start_and_end_a_parent_run(mlflow_store, tmp_path, capsys):
    cfg = json.dumps({"mlflow": {"experiment": "sweep"}})
    assert main(["mlflow-start", "--config", cfg, "--name", "wf", "--tag", "who=ci"]) == 0
    run_id = capsys.readouterr().out.strip()
    run = mlflow_store.get_run(run_id)
    assert run.info.status == "RUNNING" and run.info.run_name == "wf"
    assert run.data.tags["who"] == "ci" and run.data.params["mlflow.experiment"] == "sweep"
    assert mlflow_store.get_experiment(run.info.experiment_id).name == "sweep"

    (tmp_path / "snakemake.log").write_text("done")
    argv = ["mlflow-end", run_id, "--status", "FAILED", "--artifact", "snakemake.log"]
    assert main(argv) == 0
    assert "logged snakemake.log" in capsys.readouterr().err
    assert mlflow_store.get_run(run_id).info.status == "FAILED"
    assert [a.path for a in mlflow_store.list_artifacts(run_id)] == ["snakemake.log"]


def test_mlflow_start_refuses_a_malformed_tag_before_creating_a_run(mlflow_store, capsys):
    assert main(["mlflow-start", "--tag", "novalue"]) == 2
    assert "--tag must be KEY=VALUE, got 'novalue'" in capsys.readouterr().err
    experiments = [e.experiment_id for e in mlflow_store.search_experiments()]
    assert mlflow_store.search_runs(experiments) == []


def test_mlflow_end_offers_only_the_known_statuses(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["mlflow-end", "abc", "--status", "DONE"])
    assert exc.value.code == 2
    assert "FINISHED" in capsys.readouterr().err


def test_listing_the_commands_imports_no_heavy_library():
    heavy = ("numpy", "numba", "torch", "mlflow", "xarray", "zarr", "matplotlib", "yaml")
    assert imported_by("from dozerlab.cli import build_parser\nbuild_parser()", heavy) == []


def test_the_simulate_and_reduce_jobs_import_no_table_or_tracking_library():
    """xarray and pandas cost 0.3-0.4 s a job to import, MLflow 1-2 s: a workflow job's run is
    spooled, and neither job reads a store through xarray."""
    code = (
        "import dozerlab.fields.jobs, dozerlab.fields.run, dozerlab.reduce.jobs\n"
        "import dozerlab.reduce.models, dozerlab.reduce.run"
    )
    assert imported_by(code, ("xarray", "pandas", "mlflow", "matplotlib")) == []


def test_the_internal_commands_are_hidden_from_help(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    listed = capsys.readouterr().out
    assert "simulate" in listed and "mlflow-start" not in listed and "mlflow-end" not in listed
    with pytest.raises(SystemExit):
        main(["mlflow-end", "--help"])  # still there for the Snakefile's hooks
    assert "--status" in capsys.readouterr().out
