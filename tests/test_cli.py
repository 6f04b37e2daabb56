"""The command line: every command registered once without heavy imports, the commands of no
layer (``config``, ``mlflow-start``, ``mlflow-end``), and errors a user can fix printed without a
traceback."""

import json
import os
import re
import shlex
import subprocess
import sys
from string import Formatter

import pytest
import yaml

from dozerlab import sweep as P
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
    "adaptive-points",
    "adaptive-record",
    "adaptive-curve",
    "verify",
]


def test_every_command_is_registered_once_in_order():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert list(sub.choices) == COMMANDS


def result_path_regex(template: str) -> str:
    """A regex of the paths a :data:`dozerlab.sweep.PATHS` template names under results/."""
    parts = [
        re.escape(text) + ("[^/]+" if field is not None else "")
        for text, field, _, _ in Formatter().parse(template)
    ]
    return "results/" + "".join(parts)


RESULT_PATHS = re.compile("|".join(result_path_regex(t) for t in P.PATHS.values()))


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_help_says_what_it_does_and_shows_a_real_example(command, capsys):
    """One line of what the command does, then its options, then an example: a command line
    that parses, on the paths of the default results layout."""
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    printed = capsys.readouterr().out
    usage, summary, *_ = printed.split("\n\n")
    assert usage.startswith(f"usage: dozerlab {command}")
    assert summary and "\n" not in summary and len(summary) <= 100
    _, sep, example = printed.partition("\nexample:\n")
    assert sep
    argv = shlex.split(example.replace("\\\n", " "))
    assert argv[:4] == ["python", "-m", "dozerlab", command]
    assert build_parser().parse_args(argv[3:]).command == command
    paths = [a for a in argv if a.startswith("results/")]
    assert all(RESULT_PATHS.fullmatch(a) for a in paths), paths


def test_python_m_dozerlab_lists_each_command_with_its_one_line_summary():
    """The entry a user types, in a fresh interpreter: ``python -m dozerlab --help``."""
    env = {**os.environ, "COLUMNS": "200"}  # one line per command, however narrow the terminal
    listed = subprocess.run(
        [sys.executable, "-m", "dozerlab", "--help"],
        capture_output=True,
        text=True,
        check=True,
        env=env,
    ).stdout
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    for choice in sub._choices_actions:  # the listed commands, with their help
        line = rf"^ +{choice.dest}\s+{re.escape(choice.help)}$"
        assert re.search(line, listed, re.M), choice.dest
    assert len(sub._choices_actions) == len(COMMANDS) - 3  # the Snakefile's hooks are not listed


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
