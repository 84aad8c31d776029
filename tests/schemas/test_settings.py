"""Settings from the environment and the secrets file (schemas/settings.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from schemas.settings import (
    CACHE_DIR_ENV, SCENES_PER_WORKER_ENV, SecretsFileError, SettingError, apply_secrets_file, read_secrets_file, redacted,
    scenes_per_worker, tracking_uri,
)
from schemas.workspace import Workspace


def _secrets(tmp_path, text: str, mode: int = 0o600):
    path = tmp_path / "secrets.env"
    path.write_text(text)
    path.chmod(mode)
    return path


def _binary(tmp_path):
    path = tmp_path / "binary.env"
    path.write_bytes(b"A=\xff\xfe\n")
    path.chmod(0o600)
    return path


def test_a_secrets_file_is_key_value_lines_with_comments_quotes_and_export(tmp_path):
    path = _secrets(tmp_path, "# the stack's databases\n\nMLFLOW_BACKEND_STORE_URI = 'postgresql://u:p w@h/db'\n"
                              'export PREFECT_SERVER_DATABASE_CONNECTION_URL="postgresql+asyncpg://u:p=q@h/db"\n'
                              "EMPTY=\n")
    assert read_secrets_file(path) == {"MLFLOW_BACKEND_STORE_URI": "postgresql://u:p w@h/db",
                                       "PREFECT_SERVER_DATABASE_CONNECTION_URL": "postgresql+asyncpg://u:p=q@h/db",
                                       "EMPTY": ""}


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604, 0o660])
def test_a_secrets_file_others_can_read_is_refused_saying_how_to_fix_it(tmp_path, mode):
    path = _secrets(tmp_path, "A=1\n", mode)
    with pytest.raises(SecretsFileError, match=rf"expected mode 600 \(only its owner reads it\), got {mode:03o}: "
                                               rf"chmod 600 {path}"):
        read_secrets_file(path)


def test_a_bad_line_is_refused_by_its_number_without_showing_it(tmp_path):
    path = _secrets(tmp_path, "A=1\npostgresql://u:hunter2@h/db\n")
    with pytest.raises(SecretsFileError) as refused:
        read_secrets_file(path)
    assert str(refused.value) == f"secrets file {path} line 2: expected KEY=VALUE" and "hunter2" not in str(refused.value)
    with pytest.raises(SecretsFileError, match="no such file"):
        read_secrets_file(tmp_path / "missing.env")
    folder = tmp_path / "a-folder"
    folder.mkdir(mode=0o700)
    with pytest.raises(SecretsFileError, match="expected a readable UTF-8 text file, got IsADirectoryError"):
        read_secrets_file(folder)
    with pytest.raises(SecretsFileError, match="expected a readable UTF-8 text file, got UnicodeDecodeError"):
        read_secrets_file(_binary(tmp_path))


def test_the_environment_wins_over_the_file_and_only_named_files_are_read(tmp_path):
    path = _secrets(tmp_path, "MLFLOW_TRACKING_URI=http://from-file\nPREFECT_API_URL=http://from-file/api\n")
    environ = {"SIM2ACT_SECRETS_FILE": str(path), "MLFLOW_TRACKING_URI": "http://from-env"}
    assert apply_secrets_file(environ) == ["PREFECT_API_URL"]
    assert environ["MLFLOW_TRACKING_URI"] == "http://from-env" and environ["PREFECT_API_URL"] == "http://from-file/api"
    assert apply_secrets_file({"MLFLOW_TRACKING_URI": "x"}) == []


def test_tracking_goes_to_the_workspace_unless_the_environment_names_a_store(tmp_path, monkeypatch):
    workspace = Workspace.at(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    assert tracking_uri(workspace) == f"sqlite:///{tmp_path / 'mlflow' / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://127.0.0.1:5000")
    assert tracking_uri(workspace) == "http://127.0.0.1:5000"


def test_a_url_is_shown_without_its_password():
    assert redacted("postgresql://sim2act:hunter2@127.0.0.1:5432/mlflow") == "postgresql://sim2act:***@127.0.0.1:5432/mlflow"
    assert redacted("http://127.0.0.1:5000") == "http://127.0.0.1:5000"
    assert redacted("https://mlflow.lab/?token=hunter2") == "https://mlflow.lab/?***"  # a token in the query
    assert redacted("https://sim2act:hunter2@[::1") == "https://sim2act:***@[::1"  # not a URL urlsplit takes
    # SQLAlchemy (so MLflow) takes a raw "/" or "?" in a password, where urlsplit ends the host early
    assert redacted("postgresql://sim2act:ab/cd+e?f@db.lab:5432/mlflow") == "postgresql://sim2act:***@db.lab:5432/mlflow"


def test_a_process_killed_while_making_the_mlflow_store_leaves_nothing_that_stops_the_next(tmp_path, monkeypatch):
    """MLflow makes its SQLite store through ~100 migrations; a run killed among them once left a store no later
    run could open. Now the migrated store is made aside, once per host (the cache folder), and linked into place
    whole: killed mid-way, the next process makes it."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from mlflow import MlflowClient

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    cache = tmp_path / "cache"
    monkeypatch.setenv(CACHE_DIR_ENV, str(cache))
    workspace = Workspace.at(tmp_path / "workspace")
    maker = subprocess.Popen([sys.executable, "-c", "import sys; from schemas.settings import tracking_uri; "
                              "from schemas.workspace import Workspace; tracking_uri(Workspace.at(sys.argv[1]))",
                              str(workspace.root)], env={**os.environ, "PYTHONPATH": os.getcwd()})
    deadline = time.monotonic() + 120
    while not list(cache.glob("mlflow/*.db.making-*")) and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(0.5)  # among the migrations (they take seconds)
    maker.send_signal(signal.SIGKILL)
    maker.wait()
    assert not (workspace.mlflow / "mlflow.db").exists() and not list(cache.glob("mlflow/*.db"))
    assert list(cache.glob("mlflow/*.db.making-*"))
    uri = tracking_uri(workspace)
    assert sorted(p.name for p in workspace.mlflow.iterdir()) == ["mlflow.db"]
    [template] = (cache / "mlflow").iterdir()  # the killed one's file removed
    assert template.name.startswith("empty-store-") and template.suffix == ".db"
    client = MlflowClient(tracking_uri=uri, registry_uri=uri)
    run = client.create_run(client.create_experiment("after-the-kill"))
    client.log_metric(run.info.run_id, "loss", 0.5)
    assert client.get_run(run.info.run_id).data.metrics == {"loss": 0.5}
    assert tracking_uri(workspace) == uri  # made once: the next call finds it

    # the next workspace's store is a copy of the migrated one: its own Default experiment, under its own folder
    other = Workspace.at(tmp_path / "other")
    copied = MlflowClient(tracking_uri=tracking_uri(other))
    assert [e.name for e in copied.search_experiments()] == ["Default"]
    assert copied.get_experiment("0").artifact_location == (other.artifact_root / "0").as_uri()
    assert client.get_experiment("0").artifact_location == (workspace.artifact_root / "0").as_uri()


def test_without_a_cache_folder_to_write_each_workspace_migrates_its_own_store(tmp_path, monkeypatch):
    from mlflow import MlflowClient

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    (tmp_path / "a-file").write_text("not a folder")
    monkeypatch.setenv(CACHE_DIR_ENV, str(tmp_path / "a-file" / "cache"))
    workspace = Workspace.at(tmp_path / "workspace")
    client = MlflowClient(tracking_uri=tracking_uri(workspace))
    assert client.get_experiment("0").artifact_location == (workspace.artifact_root / "0").as_uri()
    assert sorted(p.name for p in workspace.mlflow.iterdir()) == ["mlflow.db"]


def test_scenes_per_worker_is_a_whole_number_of_at_least_one(monkeypatch):
    monkeypatch.delenv(SCENES_PER_WORKER_ENV, raising=False)
    assert scenes_per_worker() == 16
    monkeypatch.setenv(SCENES_PER_WORKER_ENV, " 3 ")
    assert scenes_per_worker() == 3
    for bad in ["0", "-2", "two", "1.5"]:
        monkeypatch.setenv(SCENES_PER_WORKER_ENV, bad)
        with pytest.raises(SettingError, match=f"SIM2ACT_SCENES_PER_WORKER: expected a whole number of scenes, at least 1, got '{bad}'"):
            scenes_per_worker()


def test_a_moved_or_copied_workspace_keeps_its_mlflow_artifacts_in_its_own_folder(tmp_path, monkeypatch):
    """MLflow names artifacts by absolute path: a moved workspace could not download its registered models,
    and a copy's runs wrote their artifacts into the original's folder."""
    import shutil

    import mlflow.artifacts
    from mlflow import MlflowClient

    from stages.redeploy import _fluent_tracking

    for name in ("MLFLOW_TRACKING_URI", "MLFLOW_REGISTRY_URI"):
        monkeypatch.delenv(name, raising=False)
    first = Workspace.at(tmp_path / "first")
    uri = tracking_uri(first)
    client = MlflowClient(tracking_uri=uri, registry_uri=uri)
    run = client.create_run(client.create_experiment("sim2act", artifact_location=first.artifact_root.as_uri()))
    (tmp_path / "policy.pt").write_bytes(b"weights")
    client.log_artifact(run.info.run_id, str(tmp_path / "policy.pt"), "policy")
    client.create_registered_model("policy")
    client.create_model_version("policy", f"{run.info.artifact_uri}/policy", run.info.run_id)

    shutil.move(first.root, tmp_path / "moved")  # the original folder is gone
    moved = Workspace.at(tmp_path / "moved")
    with _fluent_tracking(moved):
        download = mlflow.artifacts.download_artifacts("models:/policy/1", dst_path=str(tmp_path / "download"))
    assert (Path(download) / "policy.pt").read_bytes() == b"weights"

    shutil.copytree(moved.root, tmp_path / "copy")  # both folders in use
    copy = Workspace.at(tmp_path / "copy")
    (tmp_path / "notes.txt").write_text("the copy's")
    from mlflow.tracking._tracking_service import utils

    utils._artifact_repos_cache.clear()  # MLflow's per-process cache, by run id: a command on the copy starts without
    MlflowClient(tracking_uri=tracking_uri(copy)).log_artifact(run.info.run_id, str(tmp_path / "notes.txt"))
    MlflowClient(tracking_uri=tracking_uri(moved)).get_run(run.info.run_id)  # the moved one's store: still its own
    run_folder = Path(run.info.run_id) / "artifacts"
    assert (copy.artifact_root / run_folder / "notes.txt").read_text() == "the copy's"
    assert sorted(p.name for p in (moved.artifact_root / run_folder).iterdir()) == ["policy"]
    assert MlflowClient(tracking_uri=tracking_uri(moved)).get_experiment_by_name("sim2act").artifact_location \
        == moved.artifact_root.as_uri()
