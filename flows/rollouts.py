"""Explore shards as Prefect tasks: one task run per shard, on local worker processes by default
or on a Dask cluster (explore.dask_address) through prefect-dask.

Locally, each task run is a thread of the flow that hands its shard to a long-lived worker
process and waits: a worker that dies fails only that task run, which Prefect retries on a
fresh worker. On Dask, the task runs inside a Dask worker process and the scheduler re-runs
the shards of a worker that died. Either way the flow registers each shard as it completes.
"""

from __future__ import annotations

import time
import uuid

from prefect import task
from prefect.cache_policies import NO_CACHE
from prefect.futures import as_completed
from prefect.task_runners import TaskRunner, ThreadPoolTaskRunner

from envs.pool import RETRIES, PoolClosed, WorkerLost, WorkerPool, borrowed_pool
from schemas.config import ExploreConfig
from schemas.settings import apply_secrets_file
from stages.explore import Completed, Execute, ExploreUnit, run_explore_unit, unit_label
from warehouse.shard_writer import ShardFile
from warehouse.store import FOLDER

# The local worker pools of the explore flows running in this process, by id: a task run finds
# its flow's pool by the id it is given (a Dask worker process has none).
_local_pools: dict[str, WorkerPool] = {}


def _worker_died(task, task_run, state) -> bool:
    """Retry a shard only when its worker process died; a shard that raises fails the stage."""
    try:
        state.result()
    except WorkerLost:
        return True
    except Exception:
        return False
    return False


@task(
    name="explore-shard", task_run_name="{unit.task.task_id}-shard-{unit.shard}", retries=RETRIES,
    retry_delay_seconds=1, retry_condition_fn=_worker_died, cache_policy=NO_CACHE, persist_result=False,
)
def explore_shard(unit: ExploreUnit, local_pool: str | None) -> tuple[list[ShardFile], float]:
    """(shard files, seconds the rollouts took) for one unit: on the flow's local pool, or here
    (a Dask worker process)."""
    if local_pool is not None:
        pool = _local_pools.get(local_pool)
        if pool is None:  # its flow was stopped (a signal) and closed the pool while this run waited for a thread
            raise PoolClosed(f"the pool was closed before {unit_label(unit)} started")
        return pool.run(run_explore_unit, unit, unit_label(unit))
    _check_one_thread_per_dask_worker()
    # A Dask worker is started by the lab, not by sim2act (whose local workers inherit its environment):
    if unit.shard_store != FOLDER:
        apply_secrets_file()  # the host's keys to the shard store
    if unit.policy is not None:
        import torch

        # one torch thread, as in the local pool's workers (envs/pool.py): a policy's actions, hence the
        # episode's bytes, come out the same on any host, whatever cores this worker process sees
        torch.set_num_threads(1)
    started = time.monotonic()
    return run_explore_unit(unit), time.monotonic() - started


def _check_one_thread_per_dask_worker() -> None:
    """A worker process keeps one environment (and GL context) per scene: two threads would step
    and draw the same one."""
    from distributed import get_worker

    worker = get_worker()
    if worker.state.nthreads != 1:
        raise RuntimeError(f"Dask worker {worker.address} runs {worker.state.nthreads} threads; rollouts need "
                           "one per process: start workers with `dask worker ... --nthreads 1`")


def rollout_task_runner(explore: ExploreConfig) -> TaskRunner:
    if explore.dask_address:
        from prefect_dask import DaskTaskRunner

        return DaskTaskRunner(address=explore.dask_address)
    # threads that wait on worker processes: as many as there are workers
    return ThreadPoolTaskRunner(max_workers=explore.workers)


def _submitted(units: list[ExploreUnit], pool_id: str | None) -> Completed:
    futures = [explore_shard.submit(unit, pool_id) for unit in units]
    by_run = {future.task_run_id: unit for future, unit in zip(futures, units)}
    handed: set = set()
    try:
        for future in as_completed(futures):
            try:
                shards, seconds = future.result()
            except Exception:  # a failed shard (a signal's interrupt ends the stage at once)
                # shards that finished while the caller was registering are its to register before the
                # failure ends the stage (those still running are left as they are)
                for other in futures:
                    if other.task_run_id not in handed and other is not future and other.state.is_completed():
                        done, other_seconds = other.result()
                        yield by_run[other.task_run_id], done, other_seconds
                raise
            handed.add(future.task_run_id)
            yield by_run[future.task_run_id], shards, seconds
    finally:
        # stopped early (a signal, a failed unit): the units still queued for a thread never start,
        # rather than each failing on the closed pool (a killed generalist run logged ~100 of those);
        # the running ones and the finished ones are left as they are
        for future in futures:
            if not future.wrapped_future.done():
                future.wrapped_future.cancel()


def as_prefect_tasks(explore: ExploreConfig) -> Execute:
    """Submit every unit as an explore-shard task run (inside a flow using rollout_task_runner)."""

    def execute(units: list[ExploreUnit]) -> Completed:
        if explore.dask_address is not None or not units:
            yield from _submitted(units, None)
            return
        with borrowed_pool(min(explore.workers, len(units))) as pool:  # the campaign's, under keep_workers
            pool_id = uuid.uuid4().hex
            _local_pools[pool_id] = pool
            try:
                yield from _submitted(units, pool_id)
            finally:
                del _local_pools[pool_id]

    return execute
