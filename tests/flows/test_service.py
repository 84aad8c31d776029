"""The local stack for real: `sim2act up` starts a Prefect server, an MLflow server, the dashboard
and the deployments' serve process over a finished smoke campaign, compacted (`sim2act warehouse
compact`, as one would before leaving it to the nights); the nightly deployment is triggered from
Prefect's CLI and continues the campaign on the compacted warehouse; a bad parameter sent through the API is
refused with its field named; `sim2act down` stops everything."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from datetime import datetime, timedelta
from pathlib import Path
from zoneinfo import ZoneInfo

import pytest

from flows.service import answers, is_alive
from schemas.config import load_config
from schemas.workspace import Workspace
from tests.conftest import SIM2ACT, _free_port
from warehouse.catalog import Catalog

pytestmark = pytest.mark.timeout(900)
PREFECT = str(Path(sys.executable).with_name("prefect"))


def cron_hours_from_now(hours: int, minute: int, timezone: str = "UTC") -> str:
    """A daily cron line at `minute` past the hour `hours` from now in `timezone`, so a stack a test starts never
    meets its nightly run (the default, 02:00 UTC, once fired inside CI's PostgreSQL stack test and added an
    iteration to its campaign). Never 2 o'clock: the night a zone's clocks go forward that hour does not exist,
    and Prefect moves that night's run an hour back."""
    hour = (datetime.now(ZoneInfo(timezone)) + timedelta(hours=hours)).hour
    return f"{minute} {3 if hour == 2 else hour} * * *"


NIGHTLY, NIGHTLY_AGAIN = cron_hours_from_now(12, 30, "Europe/Berlin"), cron_hours_from_now(13, 45, "Europe/Berlin")


def sim2act(*args: str, env: dict[str, str] | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([SIM2ACT, *args], capture_output=True, text=True, timeout=timeout,
                          env={k: v for k, v in (env or os.environ).items() if k != "PREFECT_API_URL"})


def get_json(url: str) -> dict:
    with urllib.request.urlopen(url, timeout=10) as response:
        return json.loads(response.read())


def post_json(url: str, body: dict) -> tuple[int, dict]:
    request = urllib.request.Request(url, json.dumps(body).encode(), {"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read() or b"{}")


@pytest.fixture(scope="module")
def stack(finished_campaign, tmp_path_factory):
    workspace = tmp_path_factory.mktemp("stack") / "workspace"  # a copy: the nightly run adds an iteration
    shutil.copytree(finished_campaign[0], workspace)
    compacted = sim2act("warehouse", "compact", "--workspace", str(workspace))
    assert compacted.returncode == 0 and "compacted into" in compacted.stdout, compacted.stderr[-3000:]
    ports = {"prefect": _free_port(), "mlflow": _free_port(), "dashboard": _free_port()}
    started = sim2act("up", "--preset", "smoke", "--workspace", str(workspace), "--nightly-cron", NIGHTLY,
                      "--timezone", "Europe/Berlin", *(f"--{name}-port={port}" for name, port in ports.items()))
    try:
        assert started.returncode == 0, started.stdout[-3000:] + started.stderr[-3000:]
        yield workspace, {name: f"http://127.0.0.1:{port}" for name, port in ports.items()}
    finally:
        stopped = sim2act("down", "--workspace", str(workspace))
        assert stopped.returncode == 0, stopped.stderr


def test_up_starts_every_service_and_status_reports_them(stack):
    workspace, urls = stack
    status = sim2act("status", "--workspace", str(workspace))
    assert status.returncode == 0, status.stdout + status.stderr
    lines = status.stdout.splitlines()
    assert [line.split()[:2] for line in lines] == [[name, "up"] for name in ("prefect", "mlflow", "dashboard",
                                                                               "deployments")]
    assert get_json(f"{urls['prefect']}/api/health") is True
    # the MLflow server reads the workspace's own tracking database: the campaign's runs are there
    runs = post_json(f"{urls['mlflow']}/api/2.0/mlflow/runs/search", {"experiment_ids": ["1"], "max_results": 50})[1]
    assert {run["info"]["run_name"] for run in runs["runs"]} >= {"smoke", "smoke-iteration-0", "smoke-iteration-1"}
    nightly = get_json(f"{urls['prefect']}/api/deployments/name/bootstrap/nightly")
    [schedule] = nightly["schedules"]
    assert schedule["schedule"]["cron"] == NIGHTLY and schedule["schedule"]["timezone"] == "Europe/Berlin"
    assert nightly["parameters"]["continue_campaign"] is True
    assert nightly["parameters"]["workspace"] == str(Workspace.at(workspace).root)
    # the typed form: the config's fields, nested, with their types and bounds
    schema = nightly["parameter_openapi_schema"]
    assert schema["definitions"]["TrainConfig"]["properties"]["lr"]["type"] == "number"


def test_a_bad_parameter_through_the_api_is_refused_with_its_field_named(stack):
    workspace, urls = stack
    deployment = get_json(f"{urls['prefect']}/api/deployments/name/bootstrap/on-demand")
    before = Catalog(Workspace.at(workspace).catalog).query("SELECT count(*) FROM stage_runs")
    status, body = post_json(f"{urls['prefect']}/api/deployments/{deployment['id']}/create_flow_run",
                             {"parameters": {"config": {"train": {"lr": "fast"}}}})
    assert status == 409, body
    assert "lr" in body["detail"] and "fast" in body["detail"], body
    assert Catalog(Workspace.at(workspace).catalog).query("SELECT count(*) FROM stage_runs") == before
    # a web page elsewhere cannot: its browser's preflight for a JSON POST is refused that origin (Prefect's
    # default allowed any), while the stack's own UI keeps it
    for origin, allowed in (("https://attacker.example", False), (urls["prefect"], True)):
        preflight = urllib.request.Request(
            f"{urls['prefect']}/api/deployments/{deployment['id']}/create_flow_run", method="OPTIONS",
            headers={"Origin": origin, "Access-Control-Request-Method": "POST",
                     "Access-Control-Request-Headers": "content-type"})
        try:
            with urllib.request.urlopen(preflight, timeout=10) as response:
                granted = response.headers.get("access-control-allow-origin")
        except urllib.error.HTTPError as exc:
            granted = exc.headers.get("access-control-allow-origin")
        assert (granted in (origin, "*")) is allowed, (origin, granted)


def test_a_bad_value_in_the_prefect_ui_form_is_refused_with_its_field_named(stack, browser):
    """The deployment's run form in Prefect's own UI (it reaches its API on the stack's port)."""
    workspace, urls = stack
    deployment = get_json(f"{urls['prefect']}/api/deployments/name/bootstrap/on-demand")
    # its own runs only: the scheduler adds the nightly deployment's meanwhile
    of_this = {"deployments": {"id": {"any_": [deployment["id"]]}}}
    runs_before = post_json(f"{urls['prefect']}/api/flow_runs/count", of_this)[1]
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    page.goto(f"{urls['prefect']}/deployments/deployment/{deployment['id']}/run", wait_until="networkidle")
    # the form is typed from the config model: nested sections down to train.lr, a number input
    lr = page.locator("xpath=//span[@class='schema-form-property__label' and text()='Lr (Optional)']"
                      "/ancestor::div[contains(concat(' ', @class, ' '), ' schema-form-property ')][1]//input")
    assert lr.get_attribute("type") == "number" and float(lr.input_value()) == 3e-4
    lr.fill("-1")
    page.get_by_role("button", name="Submit").click()
    refusal = page.get_by_text("Validation failed for field 'config.train.lr'").first  # a toast, maybe twice
    refusal.wait_for(timeout=20_000)
    assert "less than or equal to the minimum of 0" in refusal.inner_text()
    page.screenshot(path=str(workspace.parent / "prefect-form-refused.png"))
    assert post_json(f"{urls['prefect']}/api/flow_runs/count", of_this)[1] == runs_before
    page.close()


def test_the_nightly_deployment_continues_the_campaign(stack):
    workspace, urls = stack
    env = {**os.environ, "PREFECT_API_URL": f"{urls['prefect']}/api"}
    triggered = subprocess.run([PREFECT, "deployment", "run", "bootstrap/nightly", "--watch"], env=env,
                               capture_output=True, text=True, timeout=800)
    assert triggered.returncode == 0, triggered.stdout[-3000:] + triggered.stderr[-3000:]
    catalog = Catalog(Workspace.at(workspace).catalog)
    assert catalog.query("SELECT iteration FROM deployments ORDER BY 1") == [(0,), (1,), (2,)]
    # over the compacted iterations: none of their units ran again; iteration 2 explored, filtered and
    # trained on their rows and its own
    assert catalog.query("SELECT DISTINCT iteration FROM stage_runs WHERE finished_at > (SELECT max(compacted_at) "
                         "FROM compacted)") == [(2,)]
    assert {stage for (stage,) in catalog.query("SELECT DISTINCT stage FROM stage_runs WHERE iteration = 2")} == {
        "explore", "filter", "index", "train", "evaluate", "redeploy"}
    [(triplets_2, triplets_1)] = catalog.query(
        "SELECT max(triplets) FILTER (WHERE iteration = 2), max(triplets) FILTER (WHERE iteration = 1) FROM iterations")
    assert triplets_2 > triplets_1
    status, runs = post_json(f"{urls['prefect']}/api/flow_runs/filter",
                             {"flow_runs": {"name": {"any_": ["smoke-iteration-2"]}}})
    assert status == 200 and [run["state_type"] for run in runs] == ["COMPLETED"]
    # its artifacts: every stage's summary, success per task, the link to the MLflow run
    status, artifacts = post_json(f"{urls['prefect']}/api/artifacts/filter",
                                  {"artifacts": {"flow_run_id": {"any_": [runs[0]["id"]]}}})
    by_key = {a["key"]: a for a in artifacts}
    assert {"smoke-iteration-2-summary", "smoke-iteration-2-success", "smoke-iteration-2-mlflow"} <= set(by_key)
    summary = by_key["smoke-iteration-2-summary"]["data"]
    assert "# smoke, iteration 2" in summary and all(f"| {stage} |" in summary for stage in (
        "generate_tasks", "explore", "filter", "index", "train", "evaluate", "redeploy"))
    table = json.loads(by_key["smoke-iteration-2-success"]["data"])
    tasks = catalog.query("SELECT count(*) FROM evaluations WHERE iteration = 2 AND suite = 'campaign'")[0][0]
    assert len(table) == tasks and {"task", "split", "success", "wilson_95"} <= set(table[0])
    [link] = re.findall(r"\]\((http[^)]+)\)", by_key["smoke-iteration-2-mlflow"]["data"])
    assert link.startswith(f"{urls['mlflow']}/#/experiments/")
    # the link opens: the MLflow run exists on that server
    run_id = link.rsplit("/", 1)[1]
    assert get_json(f"{urls['mlflow']}/api/2.0/mlflow/runs/get?run_id={run_id}")["run"]["info"]["run_name"] == \
        "smoke-iteration-2"


def test_the_scheduler_queues_the_nightly_run_at_its_local_time(stack):
    """Prefect's scheduler (a loop of the server, every 60 s) puts the next nightly runs in the
    queue the serve process polls: at its time in Berlin (NIGHTLY), whatever the server's timezone."""
    workspace, urls = stack
    nightly = get_json(f"{urls['prefect']}/api/deployments/name/bootstrap/nightly")
    query = {"deployments": {"id": {"any_": [nightly["id"]]}}, "flow_runs": {"state": {"type": {"any_": ["SCHEDULED"]}}}}
    deadline = time.monotonic() + 150
    while not (queued := post_json(f"{urls['prefect']}/api/flow_runs/filter", query)[1]):
        assert time.monotonic() < deadline, "no nightly run was scheduled"
        time.sleep(2)
    starts = [datetime.fromisoformat(run["expected_start_time"]).astimezone(ZoneInfo("Europe/Berlin")) for run in queued]
    assert all(f"{start.minute} {start.hour} * * *" == NIGHTLY for start in starts), (starts, NIGHTLY)
    assert all(run["parameters"]["continue_campaign"] is True for run in queued)


def test_up_again_with_another_schedule_restarts_only_the_deployments(stack):
    """The deployments' process reads its campaign and schedule as it starts: `sim2act up` with another
    schedule (no port flags: the stack keeps its own) restarts it alone; the servers keep their processes."""
    workspace, urls = stack
    before = json.loads(Workspace.at(workspace).service_state.read_text())["processes"]
    again = sim2act("up", "--preset", "smoke", "--workspace", str(workspace), "--nightly-cron", NIGHTLY_AGAIN,
                    "--timezone", "Europe/Berlin")
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    assert "deployments  stopped: it served another campaign or schedule" in again.stdout
    after = json.loads(Workspace.at(workspace).service_state.read_text())["processes"]
    assert {name: p["pid"] for name, p in after.items() if name != "deployments"} == {
        name: p["pid"] for name, p in before.items() if name != "deployments"}
    assert after["deployments"]["pid"] != before["deployments"]["pid"] and not is_alive(before["deployments"]["pid"])
    [schedule] = get_json(f"{urls['prefect']}/api/deployments/name/bootstrap/nightly")["schedules"]
    assert schedule["schedule"]["cron"] == NIGHTLY_AGAIN
    same = sim2act("up", "--preset", "smoke", "--workspace", str(workspace), "--nightly-cron", NIGHTLY_AGAIN,
                   "--timezone", "Europe/Berlin")
    assert same.returncode == 0 and "stopped" not in same.stdout, same.stdout[-3000:] + same.stderr[-3000:]
    assert json.loads(Workspace.at(workspace).service_state.read_text())["processes"] == after


def test_down_stops_every_process(stack):
    """The last test on the stack: the fixture's own `down` then finds nothing to stop."""
    workspace, urls = stack
    pids = [p["pid"] for p in json.loads(Workspace.at(workspace).service_state.read_text())["processes"].values()]
    stopped = sim2act("down", "--workspace", str(workspace))
    assert stopped.returncode == 0 and "stopped deployments, dashboard, mlflow, prefect" in stopped.stdout
    # each process led its own session: nothing it started (Prefect's API worker, MLflow's job
    # consumers, flow-run subprocesses) outlives it
    groups = subprocess.run(["ps", "-eo", "pgid=,stat="], capture_output=True, text=True).stdout.split("\n")
    assert not [line for line in groups if line.split() and int(line.split()[0]) in pids and "Z" not in line.split()[1]]
    assert not any(is_alive(pid) for pid in pids)
    assert not any(answers(f"{url}/") for url in urls.values())
    status = sim2act("status", "--workspace", str(workspace))
    assert status.returncode == 1 and "not up" in status.stdout


def test_a_worker_in_another_process_runs_the_prefect_yaml_deployment(finished_campaign, prefect_api, tmp_path):
    """The scale-out path (docs/scale-out.md): prefect.yaml deployed to a process work pool, a
    worker polling it from another process, a run triggered through the API."""
    workspace = tmp_path / "workspace"
    shutil.copytree(finished_campaign[0], workspace)
    env = {**os.environ, "PREFECT_API_URL": prefect_api}
    repo = Path(__file__).resolve().parents[2]

    def prefect(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
        done = subprocess.run([PREFECT, *args], env=env, cwd=repo, capture_output=True, text=True, timeout=timeout)
        assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
        return done

    prefect("work-pool", "create", "sim2act", "--type", "process", "--overwrite")
    parameters = {"workspace": str(workspace), "config": load_config("smoke").model_dump(mode="json")}
    prefect("--no-prompt", "deploy", "--name", "on-demand", "--params", json.dumps(parameters))
    log = (tmp_path / "worker.log").open("w")
    worker = subprocess.Popen([PREFECT, "worker", "start", "--pool", "sim2act"], env=env, cwd=tmp_path,
                              stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        prefect("deployment", "run", "bootstrap/on-demand", "--watch", timeout=600)
    finally:
        # Prefect 3.8.8's worker, with the dependencies pip resolves today, ignores SIGTERM and SIGINT once
        # started (docs/scale-out.md; a 20 s grace period always ran out): its whole group is killed
        os.killpg(worker.pid, signal.SIGKILL)
        worker.wait(timeout=60)
    output = (tmp_path / "worker.log").read_text()
    # the worker ran the finished campaign again: every stage found its units registered
    assert output.count("stages that ran: 0/7") == 2, output[-3000:]


def test_a_recorded_pid_another_program_took_after_a_reboot_is_neither_counted_up_nor_stopped(tmp_path):
    """The state file outlives a reboot; its PIDs may then be other programs'. A record whose process started
    at another time reads exited, and `down` leaves that process alone (it sent SIGTERM, then SIGKILL, to its
    group)."""
    from flows.service import down, process_status, started_at

    workspace = Workspace.at(tmp_path / "ws").create()
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"], start_new_session=True)
    try:
        record = {"pid": other.pid, "url": "http://127.0.0.1:9/", "health_url": "http://127.0.0.1:9/",
                  "log": "x", "tracking": None}
        for started, state in ((started_at(other.pid) - 3600, "exited"), (started_at(other.pid), "unhealthy")):
            workspace.service.mkdir(parents=True, exist_ok=True)
            workspace.service_state.write_text(json.dumps({"service": {}, "processes": {
                "prefect": {**record, "started": started}}}))
            assert [row["state"] for row in process_status(workspace)] == [state]
            if state == "exited":
                down(workspace)
                assert other.poll() is None  # not ours: left running
        down(workspace)  # ours: stopped
        assert other.wait(timeout=30) == -signal.SIGTERM
    finally:
        if other.poll() is None:
            other.kill()


def test_a_copied_workspace_neither_uses_nor_stops_the_originals_stack(tmp_path):
    """service/state.json travels with a `cp -r`: its processes are the original's."""
    from flows.service import down, process_status, started_at

    copy = Workspace.at(tmp_path / "copy").create()
    original = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"], start_new_session=True)
    try:
        copy.service.mkdir(parents=True, exist_ok=True)
        copy.service_state.write_text(json.dumps({"service": {}, "workspace": str(tmp_path / "original"), "processes": {
            "prefect": {"pid": original.pid, "started": started_at(original.pid), "url": "http://127.0.0.1:9/",
                        "health_url": "http://127.0.0.1:9/", "log": "x", "tracking": None}}}))
        assert process_status(copy) == []
        down(copy)
        assert original.poll() is None and not copy.service_state.exists()
    finally:
        original.kill()


@pytest.mark.parametrize("text", ['{"processes": {"prefect": {"pid": 12', "[]", '{"processes": {"prefect": {"pid": "abc"}}}',
                                  '{"processes": {"prefect": {"pid": 0}}}'])  # down would signal its own group
def test_a_state_file_sim2act_did_not_write_is_one_line(tmp_path, capsys, text):
    """A torn, edited or foreign service/state.json: `status` (and `run`, which reads it for the stack's URLs)
    gave a JSONDecodeError, AttributeError or TypeError traceback."""
    from flows.cli import main

    workspace = Workspace.at(tmp_path / "ws").create()
    workspace.service.mkdir(parents=True, exist_ok=True)
    workspace.service_state.write_text(text)
    assert main(["status", "--workspace", str(workspace.root)]) == 2
    [line] = capsys.readouterr().err.splitlines()
    assert line.startswith(f"sim2act: {workspace.service_state}: not a stack record sim2act wrote ("), line


def test_stopping_a_process_waits_for_its_whole_group(tmp_path):
    """A leader that ends at once on SIGTERM while a child it started takes a second to: `_stop` returns only once
    the child is gone too (CI once saw `down` return with five of a server's processes still exiting)."""
    from flows.service import _stop, group_members

    ready = tmp_path / "trapped"
    child = f"trap 'sleep 1; exit 0' TERM; touch {ready}; while :; do sleep 0.1; done"
    leader = subprocess.Popen(["bash", "-c", f'bash -c "{child}" & exec sleep 60'], start_new_session=True)
    try:
        deadline = time.monotonic() + 10
        while not ready.exists() and time.monotonic() < deadline:  # the child holds its trap
            time.sleep(0.05)
        assert ready.exists() and len(group_members(leader.pid)) >= 2
        started = time.monotonic()
        _stop({"pid": leader.pid})  # the leader, this test's child, is a zombie at once: not a member
        assert group_members(leader.pid) == [] and time.monotonic() - started >= 0.9
    finally:
        try:
            os.killpg(leader.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        leader.wait(timeout=5)
