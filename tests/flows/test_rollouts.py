"""Explore shards as real Prefect task runs: on local worker processes, on a real Dask
LocalCluster of two worker processes, and with a worker SIGKILLed mid-run. Seeds derive from
(campaign, iteration, task, shard, episode), so every way of running writes the same bytes."""

from __future__ import annotations

import contextvars
import multiprocessing
import os
import signal
import threading
import time

import pytest
from prefect import flow, get_client
from prefect.settings import PREFECT_API_URL, temporary_settings

import flows.rollouts
from envs.suite import generate_tasks
from flows.rollouts import as_prefect_tasks, rollout_task_runner
from schemas.config import CampaignConfig, ExploreConfig, TasksConfig
from schemas.workspace import Workspace
from stages.explore import ExploreResult, run_explore
from warehouse.catalog import Catalog

pytestmark = pytest.mark.timeout(600)

CONFIG = CampaignConfig(
    name="rollouts",
    tasks=TasksConfig(specs=["nav-room"], colours=["red", "green"], horizon={"nav-room": 12}),
    explore=ExploreConfig(episodes_per_task=4, episodes_per_shard=2, workers=2),
)


@flow(name="explore-test")
def explore_here(workspace: str, config: CampaignConfig) -> ExploreResult:
    ws = Workspace.at(workspace)
    tasks = generate_tasks(config.tasks, config.seed)
    return run_explore(ws, config, 0, tasks, None, {}, execute=as_prefect_tasks(config.explore))


def explore(workspace, config: CampaignConfig) -> tuple[ExploreResult, str]:
    ws = Workspace.at(workspace).create()
    Catalog(ws.catalog).initialise()
    state = explore_here.with_options(task_runner=rollout_task_runner(config.explore))(
        str(ws.root), config, return_state=True
    )
    return state.result(), str(state.state_details.flow_run_id)


def shard_bytes(workspace) -> dict[str, str]:
    rows = Catalog(Workspace.at(workspace).catalog).query("SELECT path, sha256 FROM shards ORDER BY 1")
    return dict(rows)


def shard_task_runs(flow_run_id: str) -> list[tuple[str, list[str]]]:
    """(name, state names in order) of each explore-shard task run of the flow run."""
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId

    with get_client(sync_client=True) as client:
        runs = client.read_task_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=[flow_run_id])))
        return [(run.name, [s.name for s in sorted(client.read_task_run_states(run.id), key=lambda s: s.timestamp)])
                for run in runs]


@pytest.fixture(scope="module")
def prefect_here(prefect_api):
    os.environ["PREFECT_API_URL"] = prefect_api  # Dask workers are other processes: they read it there
    with temporary_settings({PREFECT_API_URL: prefect_api}):
        yield prefect_api
    del os.environ["PREFECT_API_URL"]


@pytest.fixture(scope="module")
def reference(prefect_here, tmp_path_factory):
    workspace = tmp_path_factory.mktemp("local")
    result, flow_run_id = explore(workspace, CONFIG)
    return workspace, result, flow_run_id


def test_each_shard_is_a_prefect_task_run_on_local_workers(reference):
    workspace, result, flow_run_id = reference
    assert (result.episodes, len(result.unit_keys), result.skipped_units) == (8, 4, 0)
    runs = shard_task_runs(flow_run_id)
    assert sorted(name for name, _ in runs) == [f"nav-room-{c}-shard-{s}" for c in ("green", "red") for s in (0, 1)]
    assert all(states[-1] == "Completed" for _, states in runs)
    assert len(shard_bytes(workspace)) == 8  # episodes + steps per shard
    again, _ = explore(workspace, CONFIG)  # a finished explore does no work
    assert (again.episodes, again.skipped_units) == (0, 4)


def test_a_dask_cluster_of_two_processes_writes_the_same_bytes(reference, tmp_path):
    from dask.distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        config = CONFIG.model_copy(update={"explore": CONFIG.explore.model_copy(
            update={"dask_address": cluster.scheduler_address})})
        result, flow_run_id = explore(tmp_path, config)
        with Client(cluster) as client:
            envs_per_worker = client.run(lambda: len(__import__("envs.rollout").rollout._ENVS))
    assert result.episodes == 8
    assert sum(1 for count in envs_per_worker.values() if count) == 2  # both worker processes rolled out
    assert all(states[-1] == "Completed" for _, states in shard_task_runs(flow_run_id))
    assert shard_bytes(tmp_path) == shard_bytes(reference[0])


def test_a_worker_killed_mid_run_costs_one_retried_shard_and_the_same_bytes(reference, tmp_path):
    outcome = {}
    here = contextvars.copy_context()  # Prefect's settings (its API URL) live in context variables
    run = threading.Thread(target=lambda: outcome.update(result=here.run(explore, tmp_path, CONFIG)))
    run.start()
    deadline = time.monotonic() + 60
    while not flows.rollouts._local_pools and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.5)  # the units are sent; the workers are still importing
    victim = next(p for p in multiprocessing.active_children() if p.name == "sim2act-worker")
    os.kill(victim.pid, signal.SIGKILL)
    run.join(timeout=300)
    result, flow_run_id = outcome["result"]
    assert result.episodes == 8
    retried = [name for name, states in shard_task_runs(flow_run_id) if "Retrying" in states]
    assert len(retried) == 1, shard_task_runs(flow_run_id)
    assert shard_bytes(tmp_path) == shard_bytes(reference[0])


def test_only_a_dead_worker_earns_a_shard_a_retry():
    from prefect.states import Failed

    from envs.pool import PoolClosed, UnitFailed, WorkerLost
    from flows.rollouts import _worker_died

    assert _worker_died(None, None, Failed(data=WorkerLost("worker 1 died (killed by SIGKILL)")))
    assert not _worker_died(None, None, Failed(data=UnitFailed("lift-red shard 0 failed: OSError: disk full")))
    assert not _worker_died(None, None, Failed(data=PoolClosed("the pool was closed")))


def test_a_shard_queued_when_its_flow_stopped_says_the_pool_closed():
    """A SIGTERM closes the flow's pool while shards still wait for a thread of the task runner: each says
    so, rather than a KeyError naming the pool's id (a killed generalist run logged ~100 of those)."""
    from envs.pool import PoolClosed
    from flows.rollouts import explore_shard
    from stages.explore import plan_explore

    [unit, *_] = plan_explore(CONFIG, 0, generate_tasks(CONFIG.tasks, CONFIG.seed), None, {},
                              Workspace.at("unused"))
    with pytest.raises(PoolClosed, match=r"^the pool was closed before nav-room-\w+ shard 0 started$"):
        explore_shard.fn(unit, "a-closed-pool")


def test_a_stopped_explore_cancels_the_shards_still_queued(prefect_here, monkeypatch):
    """Stopping the stage (here: its consumer closes it after the first shard) starts no queued shard."""
    from prefect import task
    from prefect.task_runners import ThreadPoolTaskRunner

    from stages.explore import plan_explore

    started: list[str] = []

    @task(name="explore-shard-probe")
    def probe(unit, pool_id):
        started.append(unit.unit_key)
        time.sleep(0.3)
        return [], 0.3

    monkeypatch.setattr(flows.rollouts, "explore_shard", probe)
    config = CONFIG.model_copy(update={"explore": CONFIG.explore.model_copy(update={"episodes_per_shard": 1})})
    units = plan_explore(config, 0, generate_tasks(config.tasks, config.seed), None, {}, Workspace.at("unused"))

    @flow(name="explore-stopped", task_runner=ThreadPoolTaskRunner(max_workers=1))
    def stopped() -> int:
        shards = flows.rollouts._submitted(units, None)
        next(shards)
        shards.close()  # as a signal's exception or a failed unit leaves it
        time.sleep(1.0)  # long enough for a queued shard to have started, were it not cancelled
        return len(started)

    assert len(units) == 8 and stopped() <= 2  # the first, and at most the one a thread took meanwhile


def test_shards_that_finished_before_a_failed_one_is_handed_back_still_reach_the_stage(prefect_here, monkeypatch):
    """While the stage registered the first shard, the second failed and then the third finished: the third is
    handed back (and registered) before the failure ends the stage."""
    from prefect import task
    from prefect.task_runners import ThreadPoolTaskRunner

    from stages.explore import plan_explore

    config = CONFIG.model_copy(update={"explore": CONFIG.explore.model_copy(update={"episodes_per_shard": 1})})
    units = plan_explore(config, 0, generate_tasks(config.tasks, config.seed), None, {}, Workspace.at("unused"))[:3]
    delays = {units[0].unit_key: 0.0, units[1].unit_key: 0.5, units[2].unit_key: 1.0}

    @task(name="explore-shard-probe")
    def probe(unit, pool_id):
        time.sleep(delays[unit.unit_key])
        if unit.unit_key == units[1].unit_key:
            raise RuntimeError("a simulator failure")
        return [], delays[unit.unit_key]

    monkeypatch.setattr(flows.rollouts, "explore_shard", probe)

    @flow(name="explore-failed", task_runner=ThreadPoolTaskRunner(max_workers=3))
    def failed() -> list[str]:
        handed = []
        with pytest.raises(RuntimeError, match="a simulator failure"):
            for unit, _, _ in flows.rollouts._submitted(units, None):
                handed.append(unit.unit_key)
                time.sleep(2.5)  # registering it: meanwhile the second fails, then the third finishes
        return handed

    assert failed() == [units[0].unit_key, units[2].unit_key]


def test_two_hosts_sharing_no_folder_explore_into_s3_and_a_killed_host_costs_only_its_retried_shards(
        reference, tmp_path, monkeypatch):
    """The drill of docs/scale-out.md at small size: a Dask scheduler and one worker per "host" (its own
    working folder and HOME, none of them the flow's workspace), shards on a real S3 server. Host B's
    worker is SIGKILLed once it holds a shard, and the object store is down for 3 s mid-run: the
    shards end byte-identical to the uninterrupted local run, the workspace holds only the catalog."""
    from dask.distributed import Client

    from tests.dask_hosts import dask_hosts
    from tests.s3 import s3_server, start, stop

    expected = shard_bytes(reference[0])  # (read before the environment names a store the reference lacks)
    with s3_server(("lab",)) as s3:
        for name, value in s3.environ("s3://lab/drill").items():  # the flow's host: it registers the units
            monkeypatch.setenv(name, value)
        workers_env = {k: v for k, v in os.environ.items() if k != "SIM2ACT_SHARD_STORE"}  # the keys: units name the store
        with dask_hosts(tmp_path, ("host-a", "host-b"), workers_env) as hosts, Client(hosts.address, timeout=60) as client:
            workspace = tmp_path / "flow-host" / "workspace"
            config = CONFIG.model_copy(update={"explore": CONFIG.explore.model_copy(update={"dask_address": hosts.address})})
            outcome, here = {}, contextvars.copy_context()
            began = time.monotonic()
            run = threading.Thread(target=lambda: outcome.update(result=here.run(explore, workspace, config)))
            run.start()
            held = hosts.wait_until_holding(client, "host-b", alive=run.is_alive)
            hosts.kill("host-b")  # host B is gone, mid-explore
            killed_at = time.monotonic() - began
            stop(s3)  # and the object store, for 3 s
            threading.Timer(3.0, start, [s3]).start()
            run.join(timeout=400)
            assert not run.is_alive()
            wall = time.monotonic() - began
        result, flow_run_id = outcome["result"]
        assert result.episodes == 8 and held
        assert shard_bytes(workspace) == expected  # the same rows, the same bytes
        catalog = Catalog(Workspace.at(workspace).catalog)
        assert sorted(key.removeprefix("drill/") for key in s3.keys("lab") if "/shards/" in key) == sorted(
            shard_bytes(workspace))
        assert [p.name for p in (workspace / "warehouse").rglob("*") if p.is_file()] == ["catalog.duckdb"]
        assert catalog.store.url == "s3://lab/drill"
        assert all(states[-1] == "Completed" for _, states in shard_task_runs(flow_run_id))
        print(f"two-host drill: host B killed at {killed_at:.1f} s holding {len(held)} shard(s), the store down 3 s; "
              f"8 episodes in {wall:.1f} s")
