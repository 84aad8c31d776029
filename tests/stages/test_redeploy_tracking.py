"""Registering a model through MLflow's fluent API leaves the process's tracking setting as it was:
MLflow writes the URI into MLFLOW_TRACKING_URI, which later work in the process (and its children)
would read as the user's choice of store (schemas.settings.tracking_uri)."""

from __future__ import annotations

import os

import mlflow
import pytest

from stages.redeploy import _fluent_tracking


@pytest.mark.parametrize("before", [None, "http://127.0.0.1:5000"])
def test_the_fluent_tracking_uri_is_put_back_with_the_environment(monkeypatch, before):
    if before is None:
        monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    else:
        monkeypatch.setenv("MLFLOW_TRACKING_URI", before)
    with _fluent_tracking("sqlite:////tmp/workspace-a/mlflow/mlflow.db"):
        assert os.environ["MLFLOW_TRACKING_URI"] == mlflow.get_tracking_uri() == "sqlite:////tmp/workspace-a/mlflow/mlflow.db"
    assert os.environ.get("MLFLOW_TRACKING_URI") == before
