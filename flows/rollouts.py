"""Explore shards as Prefect tasks: one task run per shard, on local worker processes by default
or on a Dask cluster (explore.dask_address) through prefect-dask.

Locally, each task run is a thread of the flow that hands its shard to a long-lived worker
process and waits: a worker that dies fails only that task run, which Prefect retries on a
fresh worker. On Dask, the task runs inside a Dask worker process and the scheduler re-runs
the shards of a worker that died. Either way the flow registers each shard as it completes.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

from prefect import task
from prefect.cache_policies import NO_CACHE
from prefect.futures import as_completed
from prefect.task_runners import TaskRunner, ThreadPoolTaskRunner

from schemas.config import ExploreConfig
from stages.explore import Completed, Execute, ExploreUnit, run_explore_unit, unit_label
from stages.pool import RETRIES, WorkerPool
from warehouse.shard_writer import ShardFile

# The worker processes of the explore flow running in this process (None on a Dask worker).
_local_workers: WorkerPool | None = None


@task(
    name="explore-shard", task_run_name="{unit.task.task_id}-shard-{unit.shard}", retries=RETRIES,
    retry_delay_seconds=1, cache_policy=NO_CACHE, persist_result=False,
)
def explore_shard(unit: ExploreUnit, on_local_workers: bool) -> tuple[list[ShardFile], float]:
    """(shard files, seconds the rollouts took) for one unit."""
    if on_local_workers:
        if _local_workers is None:
            raise RuntimeError("explore-shard was asked for local workers outside the explore flow")
        return _local_workers.run(run_explore_unit, unit, unit_label(unit))
    started = time.monotonic()
    return run_explore_unit(unit), time.monotonic() - started


def rollout_task_runner(explore: ExploreConfig) -> TaskRunner:
    if explore.dask_address:
        from prefect_dask import DaskTaskRunner

        return DaskTaskRunner(address=explore.dask_address)
    # threads that wait on worker processes: as many as there are workers
    return ThreadPoolTaskRunner(max_workers=explore.workers)


def as_prefect_tasks(explore: ExploreConfig) -> Execute:
    """Submit every unit as an explore-shard task run (inside a flow using rollout_task_runner)."""

    def execute(units: list[ExploreUnit]) -> Completed:
        global _local_workers
        local = explore.dask_address is None
        if local and units:
            _local_workers = WorkerPool(min(explore.workers, len(units)))
        try:
            yield from _completed(units, local)
        finally:
            if _local_workers is not None:
                _local_workers.close()
                _local_workers = None

    return execute


def _completed(units: list[ExploreUnit], local: bool) -> Iterator[tuple[ExploreUnit, list[ShardFile], float]]:
    futures = [explore_shard.submit(unit, local) for unit in units]
    by_run = {future.task_run_id: unit for future, unit in zip(futures, units)}
    for future in as_completed(futures):
        shards, seconds = future.result()
        yield by_run[future.task_run_id], shards, seconds
