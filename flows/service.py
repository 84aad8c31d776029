"""The local stack behind `sim2act up / down / status`: a Prefect server and an MLflow server on
the workspace's own SQLite databases (the ones the embedded default writes) or on the databases the
environment names (PostgreSQL: docs/scale-out.md), the dashboard, and the process serving the
bootstrap deployments. Loopback ports; one record file says what runs.

Each process runs in its own session, so `down` stops it with everything it started.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from urllib.parse import urlsplit
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from flows.lifetime import LINEAGE_ENV
from schemas.config import CampaignConfig
from schemas.errors import Sim2ActError
from schemas.service import HOST, ServiceConfig
from schemas.settings import (ARTIFACTS_DESTINATION_ENV, BACKEND_STORE_ENV, PREFECT_DATABASE_ENV, SECRETS_FILE_ENV,
                             TRACKING_URI_ENV, whole_sqlite_store)
from schemas.workspace import Workspace, write_text_atomically

STARTUP_TIMEOUT_S = 180.0  # a first Prefect start migrates its database: ~10-40 s on 2 cores
STOP_TIMEOUT_S = 20.0
# CLI runs and the served flows find the running stack through these (MLFLOW_UI_ENV: where the
# iteration artifacts' links point).
PREFECT_API_ENV, MLFLOW_UI_ENV = "PREFECT_API_URL", "SIM2ACT_MLFLOW_UI"


class ServiceError(Sim2ActError, RuntimeError):
    pass


@dataclass(frozen=True)
class ProcessSpec:
    name: str
    command: list[str]
    env: dict[str, str]
    health_url: str  # answers 200 once the process is ready
    url: str  # what the user opens
    tracking: bool = False  # the MLflow server that runs log through (it has a database of its own)


def _bin(name: str) -> str:
    return str(Path(sys.executable).with_name(name))


def stack(workspace: Workspace, service: ServiceConfig) -> list[ProcessSpec]:
    """In start order: the deployments' process needs the Prefect server up.

    The servers' databases are the environment's (schemas/settings.py): Prefect reads its own
    PREFECT_SERVER_DATABASE_CONNECTION_URL; MLflow's server takes MLFLOW_BACKEND_STORE_URI from the
    environment, never from its command line (where `ps` would show the password). Without them both
    use SQLite files in the workspace, which runs on this machine also write directly. With a database
    of its own, the MLflow server proxies the artifacts and every run logs through it."""
    # each server gets its own database URL and no other; the dashboard and the deployments' process neither
    databases = {PREFECT_DATABASE_ENV, BACKEND_STORE_ENV, ARTIFACTS_DESTINATION_ENV}
    # and no run's lineage (flows/lifetime.py): the stack outlives whatever started it, by design
    base = {k: v for k, v in os.environ.items() if k not in (PREFECT_API_ENV, LINEAGE_ENV) and k not in databases}
    prefect, mlflow, dashboard = (service.url(s) for s in ("prefect", "mlflow", "dashboard"))
    own_database = bool(os.environ.get(BACKEND_STORE_ENV))
    mlflow_command = [_bin("mlflow"), "server", "--host", HOST, "--port", str(service.mlflow_port), "--workers", "1"]
    mlflow_env = {**base, **{k: os.environ[k] for k in (BACKEND_STORE_ENV, ARTIFACTS_DESTINATION_ENV) if k in os.environ}}
    prefect_env = {**base, **{k: os.environ[k] for k in (PREFECT_DATABASE_ENV,) if k in os.environ}}
    if own_database:
        mlflow_env.setdefault(ARTIFACTS_DESTINATION_ENV, workspace.artifact_root.as_uri())
    else:
        whole_sqlite_store(workspace)  # made whole here, not migrated by a server that may be stopped mid-way
        mlflow_command += ["--backend-store-uri", workspace.tracking_uri,
                           "--default-artifact-root", workspace.artifact_root.as_uri()]
    linked = {**{k: v for k, v in base.items() if k != SECRETS_FILE_ENV}, PREFECT_API_ENV: f"{prefect}/api",
              MLFLOW_UI_ENV: mlflow}
    if own_database:
        linked.setdefault(TRACKING_URI_ENV, mlflow)
    return [
        # The UI asks its API at PREFECT_UI_API_URL, which otherwise assumes port 4200.
        # Cross-origin calls from its own UI only. Prefect allows any origin by default: a page open in the same
        # browser could read the deployments and start a bootstrap run with a workspace and config of its
        # choosing. A write's JSON body needs the browser's preflight, which now fails for other origins (and
        # its FastAPI refuses JSON sent as text/plain), so raw API clients (curl, docs/service.md) need no token.
        ProcessSpec("prefect", [_bin("prefect"), "server", "start", "--host", HOST, "--port", str(service.prefect_port)],
                    {**prefect_env, "PREFECT_UI_API_URL": f"{prefect}/api", "PREFECT_SERVER_CORS_ALLOWED_ORIGINS":
                     f"{prefect},{prefect.replace(HOST, 'localhost')}"},
                    f"{prefect}/api/health", prefect),
        ProcessSpec("mlflow", mlflow_command, mlflow_env, f"{mlflow}/health", mlflow, tracking=own_database),
        ProcessSpec("dashboard", [_bin("sim2act"), "dashboard", "--workspace", str(workspace.root),
                                  "--host", HOST, "--port", str(service.dashboard_port)],
                    linked, f"{dashboard}/health", dashboard),
        ProcessSpec("deployments", [sys.executable, "-m", "flows.deployments", "--workspace", str(workspace.root),
                                    "--service", service.model_dump_json()],
                    linked, f"{prefect}/api/deployments/name/bootstrap/nightly", f"{prefect}/deployments"),
    ]


def answers(url: str, timeout: float = 2.0) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=timeout) as response:
            return response.status == 200
    except OSError:
        return False


def is_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    # A zombie still answers kill(0): it has exited, its parent has not reaped it.
    import psutil

    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False
    except psutil.Error:
        return True


def started_at(pid: int) -> float | None:
    """When process `pid` started (seconds since the epoch), None where there is none."""
    import psutil

    try:
        return psutil.Process(pid).create_time()
    except psutil.Error:
        return None


def is_recorded_process(record: dict) -> bool:
    """The process a state record names is alive and is the one recorded: after a reboot its PID can be
    another program's (a record without its start time, written before it was kept, is taken at its PID)."""
    if not is_alive(record["pid"]):
        return False
    started = record.get("started")
    now = started_at(record["pid"]) if started is not None else None
    return started is None or (now is not None and abs(now - started) < 1.0)


def _port_free(port: int) -> bool:
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the servers bind: TIME_WAIT is no conflict
        try:
            sock.bind((HOST, port))
        except OSError:
            return False
    return True


def read_state(workspace: Workspace) -> dict:
    """The stack recorded for this workspace; {} where none is, or the file came with a copy of another
    workspace (its processes are the original's: a copy must neither use nor stop them)."""
    path = workspace.service_state
    try:
        state = json.loads(path.read_text()) if path.exists() else {}
        processes = state.get("processes", {})
        # a pid of 0 or below would make `down` signal its own process group
        whole = all(isinstance(r, dict) and type(r.get("pid")) is int and r["pid"] > 0
                    and isinstance(r.get("health_url", ""), str) for r in processes.values())
    except (ValueError, AttributeError) as exc:  # not JSON (a torn or edited file), not an object, no processes map
        whole, why = False, f"{type(exc).__name__}: {exc}"
    else:
        why = "a process recorded without its pid"
    if not whole:
        raise ServiceError(f"{path}: not a stack record sim2act wrote ({why}); if no `sim2act up` runs for "
                           f"{workspace.root}, delete it (its processes, if any, are the ones to stop by hand)")
    return state if state.get("workspace", str(workspace.root)) == str(workspace.root) else {}


def process_status(workspace: Workspace) -> list[dict]:
    """Each recorded process: name, pid, url, log, and state up / unhealthy / exited."""
    rows = []
    for name, record in read_state(workspace).get("processes", {}).items():
        state = "exited" if not is_recorded_process(record) else "up" if answers(record["health_url"]) else "unhealthy"
        rows.append({"name": name, **record, "state": state})
    return rows


def running_urls(workspace: Workspace) -> dict[str, str]:
    """The env a CLI run needs to report to the running stack; empty when it is not up."""
    up = {row["name"]: row for row in process_status(workspace) if row["state"] == "up"}
    if "prefect" not in up or "mlflow" not in up:
        return {}
    urls = {PREFECT_API_ENV: f"{up['prefect']['url']}/api", MLFLOW_UI_ENV: up["mlflow"]["url"]}
    if up["mlflow"].get("tracking"):
        urls[TRACKING_URI_ENV] = up["mlflow"]["url"]
    return urls


def log_to_running_stack(workspace: Workspace) -> None:
    """Where `sim2act up` runs on this workspace with an MLflow server of its own, this process logs
    there unless MLFLOW_TRACKING_URI says otherwise: a flow run a Prefect worker started, as the CLI."""
    if TRACKING_URI_ENV in os.environ:  # chosen already (the CLI links to the stack before the flow starts)
        return
    if tracking := running_urls(workspace).get(TRACKING_URI_ENV):
        os.environ[TRACKING_URI_ENV] = tracking


def updated_since(url: str, since: datetime) -> bool:
    """Prefect's object at `url` (a deployment) was written at or after `since`: the deployments' process
    started again has served its own, not found the last one's."""
    try:
        with urllib.request.urlopen(url, timeout=2.0) as response:
            return datetime.fromisoformat(json.loads(response.read())["updated"]) >= since
    except (OSError, ValueError, KeyError, TypeError):
        return False


def _wait_healthy(spec: ProcessSpec, process: subprocess.Popen, log: Path) -> None:
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    started = datetime.now(timezone.utc)  # the server runs on this host: one clock
    healthy = (lambda: updated_since(spec.health_url, started)) if spec.name == "deployments" else (
        lambda: answers(spec.health_url))
    while not healthy():
        if process.poll() is not None or time.monotonic() > deadline:
            why = f"exited with {process.returncode}" if process.poll() is not None else "did not answer in time"
            tail = "\n".join(log.read_text(errors="replace").splitlines()[-15:])
            raise ServiceError(f"{spec.name} {why} ({spec.health_url}); the end of {log}:\n{tail}")
        time.sleep(0.5)


def deployments_settings(campaign: CampaignConfig, service: ServiceConfig) -> str:
    """What the deployments' process serves: the default campaign and the nightly schedule."""
    return json.dumps({"campaign": campaign.model_dump(mode="json"), "nightly_cron": service.nightly_cron,
                       "timezone": service.timezone}, sort_keys=True)


def up(workspace: Workspace, service: ServiceConfig, campaign: CampaignConfig, on_ready=print) -> list[dict]:
    """Start what is not running, wait until each answers its health check; -> process_status.
    `campaign` is the deployments' default. A failed start stops what this call started, so
    nothing is left half up."""
    running = {row["name"] for row in process_status(workspace) if row["state"] != "exited"}
    state = read_state(workspace) or {"service": service.model_dump(), "processes": {}}
    if running:  # a stack that is up keeps its ports: what starts now joins it there
        service = service.model_copy(update={name: port for name, port in state["service"].items()
                                             if name.endswith("_port")})
    # the deployments' process reads its campaign and schedule once, as it starts: another one asked for
    # restarts it (the servers and the dashboard keep running as they were)
    serves = deployments_settings(campaign, service)
    recorded = state["processes"].get("deployments", {})
    if "deployments" in running and recorded.get("serves") != serves:
        down(workspace, only=["deployments"])
        running.discard("deployments")
        on_ready("deployments  stopped: it served another campaign or schedule; starting it again")
    specs = [spec for spec in stack(workspace, service) if spec.name not in running]
    ports = {spec.name: urlsplit(spec.url).port for spec in specs if spec.name != "deployments"}  # it binds none
    taken = [f"{name} port {port}" for name, port in ports.items() if not _port_free(port)]
    if taken:
        raise ServiceError(f"in use by another program: {', '.join(taken)}; choose others (sim2act up --help)")
    workspace.service.mkdir(parents=True, exist_ok=True)
    write_text_atomically(workspace.deployment_config, campaign.model_dump_json(indent=1))
    state = read_state(workspace) or {"service": service.model_dump(), "processes": {}}  # (down may have changed it)
    state["service"], state["workspace"] = service.model_dump(), str(workspace.root)
    started: list[str] = []
    try:
        for spec in specs:
            log = workspace.service_log(spec.name)
            with log.open("a") as out:
                process = subprocess.Popen(spec.command, env=spec.env, stdout=out, stderr=subprocess.STDOUT,
                                           stdin=subprocess.DEVNULL, start_new_session=True)
            started.append(spec.name)
            state["processes"][spec.name] = {"pid": process.pid, "started": started_at(process.pid),
                                             "url": spec.url, "health_url": spec.health_url,
                                             "log": str(log), "tracking": spec.tracking,
                                             **({"serves": serves} if spec.name == "deployments" else {})}
            write_text_atomically(workspace.service_state, json.dumps(state, indent=1))
            _wait_healthy(spec, process, log)
            on_ready(f"{spec.name:<12} {spec.url}")
    except BaseException:
        down(workspace, only=started)
        raise
    return process_status(workspace)


def _stop(record: dict) -> None:
    """End a recorded process's group (its leader gone, children may hold its ports still), never another
    program's that took the leader's PID after a reboot."""
    pid = record["pid"]
    if is_alive(pid) and not is_recorded_process(record):
        return
    try:
        os.killpg(pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    # the whole group, not its leader alone: a leader gone first left its server's workers exiting for a
    # moment after `down` returned (a CI run saw five of MLflow's or Prefect's still running)
    deadline = time.monotonic() + STOP_TIMEOUT_S
    while group_members(pid) and time.monotonic() < deadline:
        time.sleep(0.2)
    if group_members(pid):
        try:
            os.killpg(pid, signal.SIGKILL)
        except ProcessLookupError:
            return
        deadline = time.monotonic() + 5.0  # what SIGKILL leaves is in uninterruptible sleep: said, not waited on
        while (left := group_members(pid)) and time.monotonic() < deadline:
            time.sleep(0.1)
        if left:
            print(f"sim2act: process group {pid}: {left} still there after SIGKILL", file=sys.stderr)


def group_members(pgid: int) -> list[int]:
    """The processes of group `pgid` that have not exited (a zombie has: its parent has yet to reap it)."""
    import psutil

    members = []
    for process in psutil.process_iter():
        try:
            if os.getpgid(process.pid) == pgid and process.status() != psutil.STATUS_ZOMBIE:
                members.append(process.pid)
        except (ProcessLookupError, psutil.Error):  # gone while looked at
            continue
    return members


def down(workspace: Workspace, only: list[str] | None = None) -> list[str]:
    """Stop the recorded processes (the last started first); -> the names stopped."""
    state = read_state(workspace)
    processes = state.get("processes", {})
    names = [name for name in reversed(list(processes)) if only is None or name in only]
    for name in names:
        _stop(processes.pop(name))
    if processes:
        write_text_atomically(workspace.service_state, json.dumps(state, indent=1))
    elif workspace.service_state.exists():
        workspace.service_state.unlink()
    return names
