"""Shared fixtures. One real Prefect server per test session (it takes ~10 s to start), which
every `sim2act run` subprocess talks to through PREFECT_API_URL."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pytest

QUIET_ENV = {
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "DO_NOT_TRACK": "1",
    "MLFLOW_DISABLE_TELEMETRY": "true",
    "MUJOCO_GL": "egl",
    "HF_HUB_OFFLINE": "1",
    "TOKENIZERS_PARALLELISM": "false",
}
# Prefect's workers and serve processes look for runs to start every 10 s by default: every deployment
# run a test triggers waited ~5 s for nothing. Every process the tests start inherits these.
FAST_POLLING_ENV = {"PREFECT_WORKER_QUERY_SECONDS": "2", "PREFECT_RUNNER_POLL_FREQUENCY": "2"}
os.environ.update(QUIET_ENV)
os.environ.update(FAST_POLLING_ENV)
# The developer's shell may point at a lab's services (docs/scale-out.md: a tracking server, a shard store, S3
# keys, a secrets file naming them): the suite's campaigns would register models there, move their aliases and
# write shards into the bucket. Every test starts from this machine alone; a test that wants a service sets it.
LAB_ENV = ("MLFLOW_TRACKING_URI", "MLFLOW_REGISTRY_URI", "MLFLOW_BACKEND_STORE_URI", "MLFLOW_ARTIFACTS_DESTINATION",
           "MLFLOW_TRACKING_USERNAME", "MLFLOW_TRACKING_PASSWORD", "PREFECT_API_URL", "PREFECT_HOME",
           "PREFECT_SERVER_DATABASE_CONNECTION_URL", "SIM2ACT_SECRETS_FILE", "SIM2ACT_SHARD_STORE",
           "SIM2ACT_WORKSPACE", "SIM2ACT_LINEAGE", "SIM2ACT_CACHE_DIR", "AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY",
           "AWS_SESSION_TOKEN", "AWS_ENDPOINT_URL", "AWS_ENDPOINT_URL_S3", "AWS_PROFILE", "AWS_DEFAULT_REGION",
           "AWS_REGION")
for name in LAB_ENV:
    os.environ.pop(name, None)
# `make test` runs the suite on 2 pytest-xdist workers, each a process that may run torch beside the other's.
# torch's OpenMP threads spin while they wait at each op's end, as if they had the cores to themselves. Measured
# here (tests/policies/test_model.py's training, 7-10 s alone on 2 threads): two at once took 52-56 s each on 2
# threads, 155 s with GOMP_SPINCOUNT=30000, 24 s with 1000, 11 s on one thread each. So a worker's processes
# default to one torch thread (a training's `train.threads` still sets its own), and a thread that waits spins
# GOMP's throttled 1,000 turns before it sleeps. Set before anything imports torch; inherited by every process
# the tests start.
if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1:
    os.environ.update({"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "GOMP_SPINCOUNT": "1000"})
SIM2ACT = str(Path(sys.executable).with_name("sim2act"))
CHROMIUM = "/usr/bin/chromium"  # Debian's (scripts/setup.sh installs it)


# The end-to-end tier (`pytest -m e2e`; `make check` runs the rest): tests that start servers, browsers or the
# `sim2act` command, run benchmarks or whole campaigns. Marked by the fixtures they use, or by module.
E2E_FIXTURES = {"prefect_api", "finished_campaign", "browser"}
E2E_MODULES = {"tests.flows.test_drills", "tests.flows.test_lifetime", "tests.flows.test_service",
               "tests.flows.test_run_lock", "tests.stages.test_train", "tests.bench.test_bench_envs",
               "tests.bench.test_bench_rollout", "tests.bench.test_bench_train", "tests.bench.test_bench_warehouse",
               "tests.dashboards.test_dashboard", "tests.stages.test_adapt"}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    e2e_count: Counter[str] = Counter()
    for item in items:
        if E2E_FIXTURES & set(getattr(item, "fixturenames", ())) or item.module.__name__ in E2E_MODULES:
            item.add_marker(pytest.mark.e2e)
            e2e_count[item.module.__name__] += 1
    # Modules with the most end-to-end tests first, each module's tests together and in their order (the sort is
    # stable): `make test` hands whole modules to its 2 workers as they free up (--dist loadfile), so the long
    # modules start early and the short unit-test modules fill the end, instead of one worker running a campaign
    # module alone last.
    items.sort(key=lambda item: -e2e_count[item.module.__name__])


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """Close the environments tests made in this process (envs.rollout's cache) while their GL display
    is still up: at the interpreter's exit the display's own atexit end may come first (its first
    context was made after the cache's close was registered), and each context then printed a traceback."""
    from envs.rollout import close_envs

    close_envs()


@pytest.fixture(autouse=True)
def _mlflow_tracking_restored() -> Iterator[None]:
    """MLflow's fluent API writes the URI it is given into MLFLOW_TRACKING_URI, which the settings read
    as the user's choice (schemas.settings.tracking_uri): a test that calls mlflow.set_tracking_uri would
    send every later test's runs, and the `sim2act` children they start, to its workspace (CI caught
    four tests logging into the campaign fixture's store). Each test gets the process's setting back."""
    from stages.redeploy import kept_tracking

    with kept_tracking():
        yield


@pytest.fixture(autouse=True)
def _sim2act_logger_restored() -> Iterator[None]:
    """A command run in-process (`main([...])`) may give the "sim2act" logger its stderr handler
    (envs.pool.log_stages_to_stderr): every later test in that xdist worker then saw the stages' warnings on
    its own stderr, or not, by the order tests were dealt (CI: a refusal test counted 99 lines where one
    is said). That handler goes with the test that added it; Prefect's (PREFECT_LOGGING_EXTRA_LOGGERS, added
    once per process, after which the stages' handler is not added at all) stay, as does the logger's level
    (flows/bootstrap.py sets INFO when imported, once per process)."""
    import logging

    from envs.pool import StagesToStderr

    logger = logging.getLogger("sim2act")
    before = logger.handlers[:]
    yield
    for handler in [h for h in logger.handlers if h not in before and isinstance(h, StagesToStderr)]:
        logger.removeHandler(handler)
        handler.close()


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="session")
def prefect_api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    home = tmp_path_factory.mktemp("prefect-home")
    port = _free_port()
    env = {**os.environ, "PREFECT_HOME": str(home), "PREFECT_SERVER_API_PORT": str(port)}
    env.pop("PREFECT_API_URL", None)
    log = (home / "server.log").open("w")
    server = subprocess.Popen(
        [str(Path(sys.executable).with_name("prefect")), "server", "start", "--host", "127.0.0.1", "--port", str(port)],
        env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
    )
    url = f"http://127.0.0.1:{port}/api"
    deadline = time.monotonic() + 120
    while True:
        try:
            with urllib.request.urlopen(f"{url}/health", timeout=2) as response:
                if response.status == 200:
                    break
        except OSError:
            pass
        if server.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"prefect server did not start: {(home / 'server.log').read_text()[-2000:]}")
        time.sleep(0.5)
    yield url
    os.killpg(server.pid, signal.SIGTERM)
    server.wait(timeout=30)


def sim2act_env(prefect_api: str) -> dict[str, str]:
    return {**os.environ, "PREFECT_API_URL": prefect_api}


@pytest.fixture(scope="session")
def finished_campaign(tmp_path_factory: pytest.TempPathFactory, prefect_api: str) -> tuple[Path, str, float]:
    """One uninterrupted smoke campaign per test session -> (workspace, output, seconds). Tests that
    change a workspace copy it first."""
    from tests.campaign import run_campaign

    workspace = tmp_path_factory.mktemp("campaign")
    output, seconds = run_campaign(workspace, prefect_api)
    return workspace, output, seconds


@pytest.fixture(scope="module")
def browser():
    """Headless Chromium driven by Playwright, for the dashboard's and the Prefect UI's pages. Per
    module, never longer: Playwright's sync API runs an event loop in this thread while it lives,
    and Prefect then answers a flow called in-process with a coroutine (tests/flows/test_rollouts)."""
    if not Path(CHROMIUM).exists():
        pytest.fail(f"no {CHROMIUM}: `apt-get install chromium` (scripts/setup.sh does it as root)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=CHROMIUM, headless=True)
        yield chromium
        chromium.close()


@pytest.fixture
def serve_chat():
    """serve_chat(*replies) -> a started ScriptedServer; a reply is content or (content, status, delay)."""
    from tests.chat_server import ScriptedServer

    servers = []

    def start(*script) -> ScriptedServer:
        server = ScriptedServer([s if isinstance(s, tuple) else (s, 200, 0.0) for s in script])
        threading.Thread(target=server.serve_forever, daemon=True).start()
        servers.append(server)
        return server

    yield start
    for server in servers:
        server.shutdown()
        server.server_close()
