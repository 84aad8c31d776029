"""The whole topology of docs/scale-out.md, for real, on loopback: PostgreSQL for Prefect's and MLflow's
databases (tests/postgres.py), a SeaweedFS S3 server (tests/s3.py) for MLflow's artifacts and the
warehouse's shards. `sim2act up` reads the databases and keys from a secrets file; a smoke campaign
started from a shell holding only the object store's keys runs through the stack: its flow runs in
Prefect's PostgreSQL, its runs and metrics in MLflow's, its videos in the bucket, its shards in the
bucket (rollout workers write them, the flow registers them), and `sim2act sql`, --as-of-iteration,
`warehouse verify`, `export lerobot`, `replay` and the stack's dashboard read them there. Neither the
database password nor the S3 secret key shows in any workspace file, command output, MLflow param or
tag, Prefect flow run, log or deployment, or process command line."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

import psutil
import pytest

from flows.service import read_state
from schemas.config import load_config
from schemas.settings import SECRETS_FILE_ENV
from schemas.workspace import Workspace
from tests.campaign import snapshot
from tests.conftest import _free_port
from tests.dask_hosts import dask_hosts
from tests.flows.test_service import PREFECT, cron_hours_from_now, get_json, post_json, sim2act
from tests.postgres import postgres_server
from tests.s3 import s3_server
from warehouse.catalog import Catalog

pytestmark = pytest.mark.timeout(900)
STORE = "s3://lab/sim2act"
REPO = Path(__file__).resolve().parents[2]


def _get(url: str, timeout: float = 120) -> bytes:
    import urllib.request

    with urllib.request.urlopen(url, timeout=timeout) as response:
        assert response.status == 200
        return response.read()


def _run_across_two_hosts(ws: str, prefect_api: str, postgres, root: Path, host_env: dict[str, str]) -> dict:
    """The smoke campaign across two "hosts" (tests/dask_hosts.py: own folder and HOME, the object store's keys
    from their own secrets file, no workspace), each running a Dask worker and a Prefect worker on its own work
    queue of the process pool `sim2act`. The campaign is deployed to host A's queue (host A holds the workspace,
    hence the catalog) with its rollouts on the Dask scheduler, and triggered through the API. Once iteration 1's
    explore has given host B a shard, host B is SIGKILLed and the database under Prefect and MLflow is stopped
    for 5 s. A flow run that then fails is triggered again (it resumes). -> what happened."""
    from dask.distributed import Client

    env = {**host_env, "PREFECT_API_URL": prefect_api}

    def prefect(*args: str) -> str:
        done = subprocess.run([PREFECT, *args], env=env, cwd=REPO, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
        return done.stdout

    def flow_run_state(run_id: str) -> str:
        try:
            return get_json(f"{prefect_api}/flow_runs/{run_id}")["state_type"]
        except OSError:  # the database (hence the server) may not answer this second
            return "UNKNOWN"

    happened: dict = {"runs": 0}
    prefect("work-pool", "create", "sim2act", "--type", "process", "--overwrite")
    for host in ("host-a", "host-b"):
        prefect("work-queue", "create", host, "--pool", "sim2act")
    with dask_hosts(root, ("host-a", "host-b"), env, prefect_pool="sim2act") as hosts, \
            Client(hosts.address, timeout=60) as client:
        config = load_config("smoke", None, {"explore": {"dask_address": hosts.address}}).model_dump(mode="json")
        prefect("--no-prompt", "deploy", "flows/bootstrap.py:bootstrap", "--name", "campaign", "--pool", "sim2act",
                "--work-queue", "host-a", "--params", json.dumps({"workspace": ws, "config": config}),
                "--job-variable", json.dumps({"env": {"PREFECT_CLIENT_RETRY_EXTRA_CODES": "500"}}))  # as prefect.yaml
        log = hosts.roots["host-a"] / "prefect-worker.log"
        began = time.monotonic()
        while True:
            happened["runs"] += 1
            [run_id] = re.findall(r"UUID: ([0-9a-f-]{36})", prefect("deployment", "run", "bootstrap/campaign"))
            deadline = time.monotonic() + 600
            while (state := flow_run_state(run_id)) not in ("COMPLETED", "FAILED", "CRASHED"):
                assert time.monotonic() < deadline, f"{happened}{hosts.logs()}"
                if "killed_at" not in happened and re.search(r"explore it1: \d+ shards", log.read_text()):
                    happened["held"] = hosts.wait_until_holding(client, "host-b")
                    address, killed = hosts.address_of(client, "host-b"), time.time()
                    hosts.kill("host-b")
                    happened["killed_at"] = time.monotonic() - began
                    postgres.stop()
                    time.sleep(5)
                    postgres.start()
                    happened["host_b_gone"] = hosts.dropped(address, killed)
                time.sleep(0.2)
            if state == "COMPLETED":
                break
            happened.setdefault("stopped", get_json(f"{prefect_api}/flow_runs/{run_id}")["state"]["message"])
            assert happened["runs"] < 3, f"{happened}{hosts.logs()}"
        happened["output"] = "".join(p.read_text() for p in root.glob("host-*/*.log"))
    happened["wall"] = time.monotonic() - began
    assert happened["held"] and "campaign smoke done" in happened["output"], happened["output"][-5000:]
    print(f"two-host campaign: host B killed {happened['killed_at']:.1f} s in, holding {len(happened['held'])} "
          f"shard(s) of iteration 1; the database down 5 s; {happened['runs']} flow run(s) "
          f"({happened.get('stopped', 'no stop')}); {happened['wall']:.1f} s in all; {happened['host_b_gone']}")
    return happened


def test_a_smoke_campaign_on_postgresql_and_s3_keeps_everything_there_and_the_secrets_nowhere(
        finished_campaign, tmp_path, monkeypatch):
    workspace = tmp_path / "workspace"
    ws = str(workspace)
    expected = snapshot(finished_campaign[0])  # (read before this process's environment names the S3 store)
    with postgres_server(("mlflow", "prefect")) as postgres, s3_server(("lab",)) as s3:
        keys = {**s3.environ(STORE), "MLFLOW_S3_ENDPOINT_URL": s3.endpoint}
        secrets_file, worker_secrets = tmp_path / "secrets.env", tmp_path / "worker.env"
        secrets_file.write_text(
            "# the stack's databases (schemas/settings.py), the bucket MLflow keeps artifacts in, the shard store\n"
            f"PREFECT_SERVER_DATABASE_CONNECTION_URL={postgres.url('prefect', 'postgresql+asyncpg')}\n"
            f"MLFLOW_BACKEND_STORE_URI='{postgres.url('mlflow')}'\nMLFLOW_ARTIFACTS_DESTINATION=s3://lab/mlflow\n"
            + "".join(f"{name}={value}\n" for name, value in keys.items()))
        worker_secrets.write_text("".join(f"{name}={value}\n" for name, value in keys.items()))  # no database
        worker_secrets.chmod(0o600)
        secrets_file.chmod(0o644)
        env = {k: v for k, v in os.environ.items()
               if not k.startswith(("PREFECT_API", "MLFLOW_TRACKING", "AWS_", "SIM2ACT_SHARD"))}
        refused = sim2act("up", "--workspace", ws, env={**env, "SIM2ACT_SECRETS_FILE": str(secrets_file)})
        assert refused.returncode == 2 and refused.stderr.strip() == (
            f"sim2act: secrets file {secrets_file}: expected mode 600 (only its owner reads it), got 644: "
            f"chmod 600 {secrets_file}"), refused.stderr
        secrets_file.chmod(0o600)
        ports = {"prefect": _free_port(), "mlflow": _free_port(), "dashboard": _free_port()}
        urls = {name: f"http://127.0.0.1:{port}" for name, port in ports.items()}
        outputs = [refused.stdout + refused.stderr]
        up = sim2act("up", "--preset", "smoke", "--workspace", ws, "--nightly-cron", cron_hours_from_now(12, 0),
                     *(f"--{name}-port={port}" for name, port in ports.items()),
                     env={**env, "SIM2ACT_SECRETS_FILE": str(secrets_file)})
        outputs.append(up.stdout + up.stderr)
        shell = {**env, "SIM2ACT_SECRETS_FILE": str(worker_secrets)}

        def command(*args: str) -> str:
            done = sim2act(*args, env=shell, timeout=600)
            outputs.append(done.stdout + done.stderr)
            assert done.returncode == 0, f"sim2act {' '.join(args)}: {done.stdout[-2000:]}{done.stderr[-3000:]}"
            return done.stdout

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

            # the campaign, by a Prefect worker on a host with the object store's keys only: it finds the stack and
            # runs through it; its rollouts on two hosts' Dask workers (host B SIGKILLed holding an iteration-1 shard,
            # which rolls the champion out from the store's copy), the database stopped for 5 s, then started again
            drill = _run_across_two_hosts(ws, f"{urls['prefect']}/api", postgres, tmp_path,
                                          {**env, SECRETS_FILE_ENV: str(worker_secrets)})
            outputs.append(drill["output"])

            # Prefect's flow runs and deployments are in its PostgreSQL database
            flow_runs = {name for (name,) in postgres.query("prefect", "SELECT name FROM flow_run")}
            assert {"smoke", "smoke-iteration-0", "smoke-iteration-1"} <= flow_runs, flow_runs
            assert {"nightly", "on-demand"} <= {name for (name,) in postgres.query("prefect", "SELECT name FROM deployment")}
            # MLflow's runs and metrics are in its PostgreSQL database (the workspace's SQLite never heard of them) ...
            runs = dict(postgres.query("mlflow", "SELECT name, status FROM runs"))
            assert {"smoke", "smoke-iteration-0", "smoke-iteration-1"} <= set(runs), runs
            [(metric_count,)] = postgres.query("mlflow", "SELECT count(*) FROM metrics WHERE key LIKE 'train.%'")
            assert metric_count > 0
            # ... their artifacts went through the server into the bucket, none into the workspace
            [(location,)] = postgres.query("mlflow", "SELECT artifact_location FROM experiments WHERE name = 'sim2act'")
            assert location.startswith("mlflow-artifacts:"), location
            videos = [key for key in s3.keys("lab") if key.startswith("mlflow/") and key.endswith(".mp4")]
            assert any("/artifacts/evaluation/" in key for key in videos), s3.keys("lab")
            assert not list(Workspace.at(workspace).artifact_root.rglob("*.mp4"))

            for name, value in keys.items():  # this process reads the catalog too
                monkeypatch.setenv(name, value)
            catalog = Catalog(Workspace.at(workspace).catalog)
            assert catalog.store.url == STORE
            # the rows and digests of the uninterrupted campaign on one machine (a folder, SQLite, local workers)
            assert snapshot(workspace) == expected
            # every registered shard is an object under the prefix; the folder has the catalog, no shard
            registered = [path for (path,) in catalog.query("SELECT path FROM shards ORDER BY path")]
            assert {table for (table,) in catalog.query("SELECT DISTINCT table_name FROM shards")} == {
                "instructions", "episodes", "steps", "filter_decisions"}
            assert [key for key in s3.keys("lab") if key.startswith("sim2act/shards/")] == [
                f"sim2act/{path}" for path in registered]
            assert not list((workspace / "warehouse").rglob("*.parquet"))
            # iteration 1's rollout workers read the champion's checkpoint from the store, not the flow's folder
            [(champion,)] = catalog.query("SELECT champion_model_key FROM deployments WHERE iteration = 0")
            assert f"sim2act/models/{champion}/policy.pt" in s3.keys("lab")
            assert catalog.query("SELECT count(*) FROM episodes WHERE explorer LIKE 'policy:%'")[0][0] > 0

            # every reader reads the objects
            [(steps, steps_0)] = catalog.query("SELECT count(*), count(*) FILTER (WHERE iteration = 0) FROM steps")
            assert command("sql", "--workspace", ws, "--format", "csv", "SELECT count(*) AS n FROM steps").split() == [
                "n", str(steps)]
            assert command("sql", "--workspace", ws, "--format", "csv", "--as-of-iteration", "0",
                           "SELECT count(*) AS n FROM steps").split() == ["n", str(steps_0)] and 0 < steps_0 < steps
            assert command("warehouse", "verify", "--workspace", ws, "--full").startswith(
                f"{len(registered)} registered file(s) verified (sha256 too), 0 quarantined to {STORE}/quarantine")
            command("export", "lerobot", "--workspace", ws, str(tmp_path / "lerobot"))
            info = json.loads((tmp_path / "lerobot" / "meta" / "info.json").read_text())
            [(kept,)] = catalog.query("SELECT count(DISTINCT episode_id) FROM kept_steps")
            assert info["total_episodes"] == kept > 0 and list((tmp_path / "lerobot").rglob("*.mp4"))
            [(episode,)] = catalog.query("SELECT episode_id FROM episodes WHERE success ORDER BY episode_id LIMIT 1")
            command("replay", episode, "--workspace", ws, "--out", str(tmp_path / "replay.mp4"))
            assert (tmp_path / "replay.mp4").stat().st_size > 0
            # the stack's dashboard: a panel over the filter_decisions shards, an episode's video from its frames
            rows = json.loads(_get(f"{urls['dashboard']}/api/panels/filter_pass_rates?campaign=smoke"))["rows"]
            [(decided,)] = catalog.query("SELECT count(*) FROM filter_decisions")
            assert sum(row["episodes"] for row in rows) == decided > 0, rows
            assert len(_get(f"{urls['dashboard']}/api/episodes/{episode}/video")) > 1000

            # the secrets: in none of what the stack and the commands wrote, logged or showed
            searched = post_json(f"{urls['mlflow']}/api/2.0/mlflow/runs/search",
                                 {"experiment_ids": [str(i) for i in range(0, 5)], "max_results": 500})[1]
            assert len(searched["runs"]) == len(runs)
            nightly = get_json(f"{urls['prefect']}/api/deployments/name/bootstrap/nightly")
            status, prefect_runs = post_json(f"{urls['prefect']}/api/flow_runs/filter", {})
            assert status == 200 and prefect_runs
            status, logs = post_json(f"{urls['prefect']}/api/logs/filter", {"limit": 200})
            assert status == 200 and logs
            for secret in (postgres.password, s3.secret_key):
                assert not [out for out in outputs if secret in out]
                assert not [p for p in workspace.rglob("*") if p.is_file() and secret.encode() in p.read_bytes()]
                for answer in (searched, nightly, prefect_runs, logs):
                    assert secret not in json.dumps(answer)
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
