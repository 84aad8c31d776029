"""Registering a model through MLflow's fluent API leaves the process's tracking and registry settings as
they were: MLflow writes the URIs into MLFLOW_TRACKING_URI and MLFLOW_REGISTRY_URI, which later work in
the process (and its children) would read as the user's choice of stores (schemas.settings)."""

from __future__ import annotations

import os

import mlflow
import pytest

from schemas.workspace import Workspace
from stages.redeploy import _fluent_tracking


@pytest.mark.parametrize("before", [None, "http://127.0.0.1:5000"])
def test_the_fluent_tracking_and_registry_uris_are_put_back_with_the_environment(monkeypatch, tmp_path, before):
    for name in ("MLFLOW_TRACKING_URI", "MLFLOW_REGISTRY_URI"):
        if before is None:
            monkeypatch.delenv(name, raising=False)
        else:
            monkeypatch.setenv(name, before)
    workspace = Workspace.at(tmp_path)
    with _fluent_tracking(workspace):
        expected = before or workspace.tracking_uri
        assert os.environ["MLFLOW_TRACKING_URI"] == mlflow.get_tracking_uri() == expected
        assert os.environ["MLFLOW_REGISTRY_URI"] == mlflow.get_registry_uri() == expected
    assert os.environ.get("MLFLOW_TRACKING_URI") == os.environ.get("MLFLOW_REGISTRY_URI") == before
    assert mlflow.get_registry_uri() == mlflow.get_tracking_uri() != workspace.tracking_uri
