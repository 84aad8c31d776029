"""What `sim2act` says when a run fails for a reason outside the project (tests/flows/test_postgres_stack.py
stops the database behind a real Prefect server for a few seconds: the client's retries carry the run)."""

from __future__ import annotations

import argparse
import re

import httpx
import pytest
from prefect.exceptions import PrefectHTTPStatusError

import flows.cli as cli


def test_a_prefect_server_failing_past_its_clients_retries_is_one_line_and_other_errors_are_not_hidden(
        monkeypatch, capsys):
    request = httpx.Request("POST", "http://127.0.0.1:4200/api/task_runs/1/set_state")

    def explore(args: argparse.Namespace) -> int:
        try:
            raise PrefectHTTPStatusError("Server error '500 Internal Server Error'", request=request,
                                         response=httpx.Response(500, request=request))
        except PrefectHTTPStatusError as exc:  # as the engine raises it: wrapped by the flow that failed
            raise RuntimeError("Flow run encountered an exception") from exc

    parser = argparse.ArgumentParser()
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    parser.set_defaults(handler=explore)
    assert cli.main([]) == 2
    assert capsys.readouterr().err == (
        "sim2act: the Prefect server answered 500 to POST /api/task_runs/1/set_state after its client's retries: "
        "check the server and its database, then run the same command again to resume\n")
    parser.set_defaults(handler=lambda args: 1 / 0)  # a bug stays a traceback
    with pytest.raises(ZeroDivisionError):
        cli.main([])


def test_a_temporary_server_that_died_while_it_started_is_one_line(monkeypatch, capsys):
    """Killed before `ends_with_its_server` could follow it (a soak's server kill on a loaded machine), Prefect's
    client raised its bare RuntimeError and the run ended in a traceback."""
    import importlib

    importlib.import_module("prefect.exceptions")  # the CLI looks at Prefect's errors only once Prefect is imported

    def run(args: argparse.Namespace) -> int:
        raise RuntimeError("Timed out while attempting to connect to ephemeral Prefect API server. "
                           "Ephemeral server process exited with code -9.")

    parser = argparse.ArgumentParser()
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    parser.set_defaults(handler=run)
    assert cli.main([]) == 2
    assert capsys.readouterr().err == (
        "sim2act: Prefect's temporary API server died while it started (exit -9); nothing ran against it. Run the "
        "same command again to resume (finished units are kept)\n")


@pytest.mark.parametrize("name", ["MLFLOW_TRACKING_URI", "MLFLOW_REGISTRY_URI", "MLFLOW_BACKEND_STORE_URI"])
def test_a_tracking_uri_of_a_scheme_mlflow_refuses_is_one_line_without_its_password(monkeypatch, tmp_path, name):
    """`postgres://` (MLflow takes `postgresql://`): MLflow's own refusal printed the whole URL, password too,
    into the terminal, the flow run's state in Prefect and the MLflow server's log."""
    from flows.cli.common import TrackingUnreachable, check_tracking_server
    from schemas.workspace import Workspace

    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://127.0.0.1:1")  # a server named, where the store is
    monkeypatch.setenv(name, "postgres://sim2act:hunter2@db.lab/mlflow")
    with pytest.raises(TrackingUnreachable, match=rf"^{name}: expected a URI of sqlite, postgresql") as error:
        check_tracking_server(Workspace.at(tmp_path))
    assert "hunter2" not in str(error.value) and "sim2act:***@db.lab" in str(error.value)
    # MLflow 3's file store refuses to start (a 39-line traceback mid-command)
    for value, shown in (("file:///data/mlruns", "file:///data/mlruns"), ("/data/mlruns", "/data/mlruns")):
        monkeypatch.setenv(name, value)
        with pytest.raises(TrackingUnreachable, match=rf"^{name}: expected a URI of sqlite, .*got {re.escape(shown)}$"):
            check_tracking_server(Workspace.at(tmp_path))


def test_a_registry_server_that_does_not_answer_is_one_line_before_any_work(monkeypatch, tmp_path):
    """MLFLOW_REGISTRY_URI apart from the tracking store: models are registered there after the first
    training, hours in; a server that is not there is named before the campaign starts."""
    from flows.cli.common import TrackingUnreachable, check_tracking_server
    from schemas.workspace import Workspace

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)  # runs in the workspace's SQLite file
    monkeypatch.setenv("MLFLOW_REGISTRY_URI", "http://lab:hunter2@127.0.0.1:1")
    with pytest.raises(TrackingUnreachable, match=r"^MLFLOW_REGISTRY_URI=http://lab:\*\*\*@127.0.0.1:1: no MLflow server "
                                                  r"answers at http://127.0.0.1:1/health") as error:
        check_tracking_server(Workspace.at(tmp_path))
    assert "hunter2" not in str(error.value)
    monkeypatch.setenv("MLFLOW_REGISTRY_URI", f"sqlite:///{tmp_path / 'registry.db'}")  # a file: nothing to ask
    check_tracking_server(Workspace.at(tmp_path))


def test_a_reader_that_stops_reading_ends_the_command_without_a_traceback():
    """`sim2act tasks list | head`: head exits after its lines and the next write fails (EPIPE)."""
    import subprocess

    from tests.conftest import SIM2ACT

    command = subprocess.Popen([SIM2ACT, "tasks", "list"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    command.stdout.close()  # before its first line: the reader is gone while it still imports
    _, stderr = command.communicate(timeout=300)
    assert command.returncode == 1 and b"Traceback" not in stderr and b"BrokenPipe" not in stderr, stderr.decode()[-2000:]


def test_a_tracking_database_that_does_not_answer_is_one_line_before_any_work(monkeypatch, tmp_path):
    """MLFLOW_TRACKING_URI naming a database directly: MLflow's client retried for minutes, then 212 lines
    ending in SQLAlchemy's traceback; a dialect without its driver, a ModuleNotFoundError traceback."""
    from flows.cli.common import TrackingUnreachable, check_tracking_server
    from schemas.workspace import Workspace
    from tests.chat_server import closed_port

    port = closed_port()
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"postgresql://sim2act:hunter2@127.0.0.1:{port}/mlflow")
    with pytest.raises(TrackingUnreachable, match=rf"^MLFLOW_TRACKING_URI=postgresql://sim2act:\*\*\*@127.0.0.1:{port}/mlflow: "
                                                  r"the database does not answer \(.*Connection refused"):
        check_tracking_server(Workspace.at(tmp_path))
    # a "/" in the password, as SQLAlchemy reads it: the password's, hidden; the database asked all the same
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"postgresql://sim2act:ab/cd@127.0.0.1:{port}/mlflow")
    with pytest.raises(TrackingUnreachable, match=r"sim2act:\*\*\*@127.0.0.1.*the database does not answer") as error:
        check_tracking_server(Workspace.at(tmp_path))
    assert "ab/cd" not in str(error.value)
    import importlib.util

    if importlib.util.find_spec("MySQLdb") is None:  # the driver MySQL's URLs default to
        monkeypatch.setenv("MLFLOW_TRACKING_URI", "mysql://sim2act:hunter2@127.0.0.1/mlflow")
        with pytest.raises(TrackingUnreachable, match=r"its database driver is not installed \(no module 'MySQLdb'\)") as error:
            check_tracking_server(Workspace.at(tmp_path))
        assert "hunter2" not in str(error.value)


def test_uris_mlflow_documents_pass_and_a_token_is_not_shown(monkeypatch, tmp_path):
    """Databricks' bare profile names and Unity Catalog's registry URIs are MLflow's own; a query's token stayed
    in the health URL of the "does not answer" line."""
    from flows.cli.common import TrackingUnreachable, check_tracking_uris, check_tracking_server
    from schemas.workspace import Workspace

    for tracking, registry in (("databricks", "databricks-uc"), ("databricks://scope:prefix", "databricks-uc://profile"),
                               ("http://127.0.0.1:5000", "uc:http://127.0.0.1:5001")):
        monkeypatch.setenv("MLFLOW_TRACKING_URI", tracking)
        monkeypatch.setenv("MLFLOW_REGISTRY_URI", registry)
        check_tracking_uris()
    monkeypatch.delenv("MLFLOW_REGISTRY_URI")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://127.0.0.1:1/?token=hunter2")
    with pytest.raises(TrackingUnreachable, match=r"=http://127.0.0.1:1/\?\*\*\*: no MLflow server answers at "
                                                  r"http://127.0.0.1:1/health \(") as error:
        check_tracking_server(Workspace.at(tmp_path))
    assert "hunter2" not in str(error.value)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://lab:ab/cd@127.0.0.1:1")  # urllib would read "ab" as the port
    with pytest.raises(TrackingUnreachable, match=r"http://lab:\*\*\*@127.0.0.1:1: not a URL \(its password holds") as error:
        check_tracking_server(Workspace.at(tmp_path))
    assert "ab/cd" not in str(error.value) and "'ab'" not in str(error.value)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "https://sim2act:hunter2@[::1")  # a ValueError traceback from urlsplit
    with pytest.raises(TrackingUnreachable, match=r"https://sim2act:\*\*\*@\[::1: not a URL \(urllib cannot read"):
        check_tracking_server(Workspace.at(tmp_path))
