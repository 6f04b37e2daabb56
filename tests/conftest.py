"""Fixtures shared by every test directory."""

from __future__ import annotations

import pytest
from mlflow.tracking import MlflowClient

from dozerlab import spool, tracking


@pytest.fixture
def mlflow_store(tmp_path, monkeypatch) -> MlflowClient:
    """A fresh SQLite MLflow store in tmp_path (the working directory), tracking on, no parent
    run; returns a client of it."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.delenv("DOZERLAB_MLFLOW", raising=False)
    monkeypatch.delenv(tracking.PARENT_ENV, raising=False)
    monkeypatch.delenv(spool.SPOOL_ENV, raising=False)
    return MlflowClient(tracking_uri=uri)
