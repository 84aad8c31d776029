"""A smoke campaign whose shards live on a real S3 server (SeaweedFS on loopback, tests/s3.py), its keys
in a secrets file: the rollout workers write objects, the flow registers them, and `sim2act sql`
(with --as-of-iteration), `warehouse verify`, `export lerobot`, `replay` and the dashboard read them
there. The warehouse folder holds the catalog and nothing else; the secret key is in no file of the
workspace, no MLflow param or tag, and no command's output."""

from __future__ import annotations

import json
import sqlite3
import subprocess
import time
import urllib.request

import pytest

from schemas.workspace import Workspace
from tests.conftest import SIM2ACT, _free_port, sim2act_env
from tests.flows.test_service import post_json
from tests.s3 import s3_server
from warehouse.catalog import Catalog

pytestmark = pytest.mark.timeout(900)
STORE = "s3://lab/sim2act"


def test_a_smoke_campaign_keeps_its_shards_on_s3_and_every_reader_follows(tmp_path, prefect_api, monkeypatch):
    workspace = tmp_path / "workspace"
    ws = str(workspace)
    with s3_server(("lab",)) as s3:
        secrets_file = tmp_path / "secrets.env"
        secrets_file.write_text("".join(f"{name}={value}\n" for name, value in s3.environ(STORE).items()))
        secrets_file.chmod(0o600)
        env = {k: v for k, v in sim2act_env(prefect_api).items() if not k.startswith(("AWS_", "SIM2ACT_SHARD"))}
        env["SIM2ACT_SECRETS_FILE"] = str(secrets_file)
        outputs = []

        def sim2act(*args: str) -> subprocess.CompletedProcess:
            done = subprocess.run([SIM2ACT, *args], env=env, capture_output=True, text=True, timeout=600)
            outputs.append(done.stdout + done.stderr)
            assert done.returncode == 0, f"sim2act {' '.join(args)}: {done.stdout[-2000:]}{done.stderr[-3000:]}"
            return done

        sim2act("run", "--preset", "smoke", "--workspace", ws, "--set", "train.epochs=1")
        for name, value in s3.environ(STORE).items():  # this process reads the catalog too
            monkeypatch.setenv(name, value)
        catalog = Catalog(Workspace.at(workspace).catalog)
        assert catalog.store.url == STORE
        # every registered shard is an object under the prefix; the folder has the catalog, no shard
        registered = [path for (path,) in catalog.query("SELECT path FROM shards ORDER BY path")]
        assert {table for (table,) in catalog.query("SELECT DISTINCT table_name FROM shards")} == {
            "instructions", "episodes", "steps", "filter_decisions"}
        assert [key for key in s3.keys("lab") if key.startswith("sim2act/shards/")] == [f"sim2act/{path}" for path in registered]
        # iteration 1's rollout workers read the champion's checkpoint from the store, not the flow's folder
        assert "sim2act/models/sim2act-smoke/1/policy.pt" in s3.keys("lab")
        assert catalog.query("SELECT count(*) FROM episodes WHERE explorer LIKE 'policy:%'")[0][0] > 0
        assert not [p for p in (workspace / "warehouse").rglob("*.parquet")]

        [(steps, steps_0, episodes)] = catalog.query(
            "SELECT count(*), count(*) FILTER (WHERE iteration = 0), count(DISTINCT episode_id) FROM steps")
        counted = sim2act("sql", "--workspace", ws, "--format", "csv", "SELECT count(*) AS n FROM steps")
        assert counted.stdout.split() == ["n", str(steps)]
        as_of = sim2act("sql", "--workspace", ws, "--format", "csv", "--as-of-iteration", "0", "SELECT count(*) AS n FROM steps")
        assert as_of.stdout.split() == ["n", str(steps_0)] and 0 < steps_0 < steps
        verified = sim2act("warehouse", "verify", "--workspace", ws, "--full")
        assert verified.stdout.startswith(f"{len(registered)} registered shard(s) verified (sha256 too), 0 quarantined "
                                          f"to {STORE}/quarantine")
        exported = sim2act("export", "lerobot", "--workspace", ws, str(tmp_path / "lerobot"))
        info = json.loads((tmp_path / "lerobot" / "meta" / "info.json").read_text())
        [(kept,)] = catalog.query("SELECT count(DISTINCT episode_id) FROM kept_steps")
        assert info["total_episodes"] == kept > 0 and list((tmp_path / "lerobot").rglob("*.mp4")), exported.stdout
        [(episode,)] = catalog.query("SELECT episode_id FROM episodes WHERE success ORDER BY episode_id LIMIT 1")
        replayed = sim2act("replay", episode, "--workspace", ws, "--out", str(tmp_path / "replay.mp4"))
        assert (tmp_path / "replay.mp4").stat().st_size > 0, replayed.stdout

        # the dashboard's panels and episode video, from the objects
        port = _free_port()
        server = subprocess.Popen([SIM2ACT, "dashboard", "--workspace", ws, "--port", str(port)], env=env,
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            base, deadline = f"http://127.0.0.1:{port}", time.monotonic() + 60
            while True:
                try:
                    urllib.request.urlopen(f"{base}/health", timeout=2).close()
                    break
                except OSError:
                    assert server.poll() is None and time.monotonic() < deadline
                    time.sleep(0.2)
            with urllib.request.urlopen(f"{base}/api/panels/filter_pass_rates?campaign=smoke", timeout=60) as response:
                rows = json.loads(response.read())["rows"]  # over the filter_decisions shards
            [(decided,)] = catalog.query("SELECT count(*) FROM filter_decisions")
            assert sum(row["episodes"] for row in rows) == decided > 0, rows
            with urllib.request.urlopen(f"{base}/api/episodes/{episode}/video", timeout=120) as response:
                assert response.status == 200 and len(response.read()) > 1000
        finally:
            server.terminate()
            server.wait(timeout=30)

        # the secret key: in no workspace file, MLflow param or tag, or command output
        secret = s3.secret_key
        assert not [out for out in outputs if secret in out]
        assert not [p for p in workspace.rglob("*") if p.is_file() and secret.encode() in p.read_bytes()]
        with sqlite3.connect(Workspace.at(workspace).tracking_uri.removeprefix("sqlite:///")) as mlflow_db:
            for table in ("params", "tags"):
                assert not mlflow_db.execute(f"SELECT key FROM {table} WHERE value LIKE ?", [f"%{secret}%"]).fetchall()
        # ... nor in Prefect's flow runs (their parameters) or the log lines the flow sent it
        status, runs = post_json(f"{prefect_api}/flow_runs/filter", {"flow_runs": {"name": {"like_": "smoke"}}})
        assert status == 200 and runs and secret not in json.dumps(runs)
        status, logs = post_json(f"{prefect_api}/logs/filter", {"logs": {"flow_run_id": {"any_": [r["id"] for r in runs]}},
                                                               "limit": 200})
        assert status == 200 and logs and secret not in json.dumps(logs)
