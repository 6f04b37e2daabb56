"""Fixtures shared by every test directory."""

from __future__ import annotations

from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

from dozerlab import spool, tracking
from tests.helpers import copy_mlflow_store


@pytest.fixture(scope="session", autouse=True)
def _working_folders_tracking_store_untouched():
    """No test may log to the MLflow store of the folder pytest runs in: after a sweep that is
    the user's ``mlflow.db``. A test that tracks takes :func:`mlflow_store`; one that runs a
    command in-process with tracking on would write there, so the session fails if it changed."""
    db = Path("mlflow.db").resolve()

    def stamp() -> tuple[int, int] | None:
        return (db.stat().st_size, db.stat().st_mtime_ns) if db.exists() else None

    before = stamp()
    yield
    assert stamp() == before, f"a test wrote to the working folder's MLflow store {db}"


@pytest.fixture(scope="session")
def mlflow_template(tmp_path_factory) -> Path:
    """An empty SQLite MLflow store, made once a session: tests copy it
    (:func:`tests.helpers.copy_mlflow_store`) instead of creating the tables again."""
    db = tmp_path_factory.mktemp("mlflow_template") / "mlflow.db"
    client = MlflowClient(tracking_uri=f"sqlite:///{db}")
    client.search_experiments()  # creates the tables and the Default experiment
    return db


@pytest.fixture
def mlflow_store(tmp_path, monkeypatch, mlflow_template) -> MlflowClient:
    """A fresh SQLite MLflow store in tmp_path (the working directory), tracking on, no parent
    run; returns a client of it."""
    uri = copy_mlflow_store(mlflow_template, tmp_path)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.delenv("DOZERLAB_MLFLOW", raising=False)
    monkeypatch.delenv(tracking.PARENT_ENV, raising=False)
    monkeypatch.delenv(spool.SPOOL_ENV, raising=False)
    return MlflowClient(tracking_uri=uri)
