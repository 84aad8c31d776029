"""The stack on PostgreSQL and S3, for real (tests/postgres.py and tests/s3.py start them on loopback):
`sim2act up` with a secrets file naming Prefect's and MLflow's databases and an S3 bucket for MLflow's
artifacts; a training and an evaluation started from a shell that has no secrets log through the
MLflow server into PostgreSQL, their artifacts proxied into the bucket; the deployments live in
Prefect's PostgreSQL database; and neither the password nor the S3 secret key shows in any file of the
workspace, command output, MLflow param or tag, Prefect parameter, or process command line."""

from __future__ import annotations

import os
import re
import shutil

import psutil
import pytest

from flows.service import read_state
from schemas.workspace import Workspace
from tests.conftest import _free_port
from tests.flows.test_service import get_json, post_json, sim2act
from tests.postgres import postgres_server
from tests.s3 import s3_server

pytestmark = pytest.mark.timeout(900)


def test_the_stack_on_postgresql_keeps_runs_there_and_the_password_nowhere(finished_campaign, tmp_path):
    workspace = tmp_path / "workspace"
    shutil.copytree(finished_campaign[0], workspace)
    ws = str(workspace)
    with postgres_server(("mlflow", "prefect")) as postgres, s3_server(("lab",)) as s3:
        secrets_file = tmp_path / "secrets.env"
        secrets_file.write_text(
            "# the stack's databases (schemas/settings.py), and the bucket MLflow's server keeps artifacts in\n"
            f"PREFECT_SERVER_DATABASE_CONNECTION_URL={postgres.url('prefect', 'postgresql+asyncpg')}\n"
            f"MLFLOW_BACKEND_STORE_URI='{postgres.url('mlflow')}'\n"
            "MLFLOW_ARTIFACTS_DESTINATION=s3://lab/mlflow\n"
            f"MLFLOW_S3_ENDPOINT_URL={s3.endpoint}\nAWS_ACCESS_KEY_ID={s3.access_key}\n"
            f"AWS_SECRET_ACCESS_KEY={s3.secret_key}\n")
        secrets_file.chmod(0o644)
        env = {k: v for k, v in os.environ.items() if not k.startswith(("PREFECT_API", "MLFLOW_TRACKING"))}
        refused = sim2act("up", "--workspace", ws, env={**env, "SIM2ACT_SECRETS_FILE": str(secrets_file)})
        assert refused.returncode == 2 and refused.stderr.strip() == (
            f"sim2act: secrets file {secrets_file}: expected mode 600 (only its owner reads it), got 644: "
            f"chmod 600 {secrets_file}"), refused.stderr
        secrets_file.chmod(0o600)
        ports = {"prefect": _free_port(), "mlflow": _free_port(), "dashboard": _free_port()}
        urls = {name: f"http://127.0.0.1:{port}" for name, port in ports.items()}
        outputs = [refused.stdout + refused.stderr]
        up = sim2act("up", "--preset", "smoke", "--workspace", ws, *(f"--{name}-port={port}" for name, port in ports.items()),
                     env={**env, "SIM2ACT_SECRETS_FILE": str(secrets_file)})
        outputs.append(up.stdout + up.stderr)
        try:
            assert up.returncode == 0, up.stdout[-3000:] + up.stderr[-3000:]
            processes = read_state(Workspace.at(workspace))["processes"]
            assert processes["mlflow"]["tracking"] is True
            # each server has its own database's URL and no other; the dashboard and the deployments neither
            environ = {name: psutil.Process(record["pid"]).environ() for name, record in processes.items()}
            databases = {"PREFECT_SERVER_DATABASE_CONNECTION_URL", "MLFLOW_BACKEND_STORE_URI"}
            assert {name: sorted(databases & set(env)) for name, env in environ.items()} == {
                "prefect": ["PREFECT_SERVER_DATABASE_CONNECTION_URL"], "mlflow": ["MLFLOW_BACKEND_STORE_URI"],
                "dashboard": [], "deployments": []}
            assert environ["deployments"]["MLFLOW_TRACKING_URI"] == urls["mlflow"]
            # from a shell without the secrets: the commands find the stack, and log through its MLflow server
            trained = sim2act("train", "--preset", "smoke", "--workspace", ws, "--set", "train.steps=2",
                              "--set", "train.seed=7", env=env)
            outputs.append(trained.stdout + trained.stderr)
            assert trained.returncode == 0, trained.stdout[-3000:] + trained.stderr[-3000:]
            [model_key] = re.findall(r"^model (train-[0-9a-f]+):", trained.stdout, re.MULTILINE)
            evaluated = sim2act("eval", "--preset", "smoke", "--workspace", ws, "--model", model_key,
                                "--split", "seen", "--episodes", "1", env=env)
            outputs.append(evaluated.stdout + evaluated.stderr)
            assert evaluated.returncode == 0, evaluated.stdout[-3000:] + evaluated.stderr[-3000:]

            # MLflow's runs are in PostgreSQL (the workspace's SQLite store never heard of them) ...
            runs = dict(postgres.query("mlflow", "SELECT name, status FROM runs"))
            assert runs["smoke"] == "RUNNING" and runs["smoke-iteration-1"] == "RUNNING", runs
            assert [name for name in runs if name.startswith("eval ")] and set(runs.values()) <= {"RUNNING", "FINISHED"}
            [(metric_count,)] = postgres.query("mlflow", "SELECT count(*) FROM metrics WHERE key LIKE 'train.%'")
            assert metric_count > 0
            # ... their artifacts went through the server into its store: the bucket
            [(location,)] = postgres.query("mlflow", "SELECT artifact_location FROM experiments WHERE name = 'sim2act'")
            assert location.startswith("mlflow-artifacts:"), location
            [(eval_run,)] = postgres.query("mlflow", "SELECT run_uuid FROM runs WHERE name LIKE 'eval %'")
            videos = [key for key in s3.keys("lab") if f"/{eval_run}/artifacts/evaluation/" in key and "/seen/" in key]
            assert videos and all(key.startswith("mlflow/") and key.endswith(".mp4") for key in videos), s3.keys("lab")
            assert not list(Workspace.at(workspace).artifact_root.glob(f"*/{eval_run}"))
            # Prefect's deployments are in its PostgreSQL database
            assert {"nightly", "on-demand"} <= {name for (name,) in postgres.query("prefect", "SELECT name FROM deployment")}
            nightly = get_json(f"{urls['prefect']}/api/deployments/name/bootstrap/nightly")

            # the password: in none of what the stack and the commands wrote, logged or showed
            searched = post_json(f"{urls['mlflow']}/api/2.0/mlflow/runs/search",
                                 {"experiment_ids": [str(i) for i in range(0, 5)], "max_results": 500})[1]
            assert len(searched["runs"]) == len(runs)
            for secret in (postgres.password, s3.secret_key):
                assert not [out for out in outputs if secret in out]
                assert not [p for p in workspace.rglob("*") if p.is_file() and secret.encode() in p.read_bytes()]
                assert secret not in str(searched) and secret not in str(nightly)
                assert not [p.pid for p in psutil.process_iter(["cmdline"]) if secret in " ".join(p.info["cmdline"] or [])]
        finally:
            stopped = sim2act("down", "--workspace", ws, env=env)
            assert stopped.returncode == 0, stopped.stderr
    assert not [p.pid for p in psutil.process_iter(["cmdline"]) if ws in " ".join(p.info["cmdline"] or [])]


def test_an_mlflow_server_that_does_not_answer_is_one_line_before_any_work(finished_campaign, tmp_path):
    workspace = tmp_path / "workspace"
    shutil.copytree(finished_campaign[0], workspace)
    before = sorted(p.relative_to(workspace) for p in workspace.rglob("*"))
    url = f"http://sim2act:hunter2@127.0.0.1:{_free_port()}"
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("PREFECT_API")}, "MLFLOW_TRACKING_URI": url}
    done = sim2act("train", "--preset", "smoke", "--workspace", str(workspace), "--set", "train.steps=2", env=env)
    assert done.returncode == 2 and done.stdout == "", done.stdout
    [line] = done.stderr.strip().splitlines()
    assert line.startswith(f"sim2act: MLFLOW_TRACKING_URI={url.replace('hunter2', '***')}: no MLflow server answers"), line
    assert "hunter2" not in line and "Connection refused" in line, line
    assert sorted(p.relative_to(workspace) for p in workspace.rglob("*")) == before
    # a stack database named, but no server to log through (the stack is down): refused, not SQLite
    env = {**env, "MLFLOW_BACKEND_STORE_URI": "postgresql://sim2act:hunter2@127.0.0.1:1/mlflow"}
    del env["MLFLOW_TRACKING_URI"]
    done = sim2act("train", "--preset", "smoke", "--workspace", str(workspace), "--set", "train.steps=2", env=env)
    assert done.returncode == 2 and done.stderr.strip() == (
        f"sim2act: MLFLOW_BACKEND_STORE_URI names the stack's tracking database, but no MLflow server runs for "
        f"{Workspace.at(workspace).root}: start it (`sim2act up`) or set MLFLOW_TRACKING_URI"), done.stderr
    assert sorted(p.relative_to(workspace) for p in workspace.rglob("*")) == before
