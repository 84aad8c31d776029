"""A workspace whose iteration 0 is explored for real, in this process, unit by unit (no flow, no
Prefect): for tests that read stored episodes (replay, the label audit)."""

from __future__ import annotations

from pathlib import Path

from envs.suite import generate_tasks
from schemas.config import CampaignConfig
from schemas.workspace import Workspace
from stages.explore import plan_explore, run_explore_unit
from warehouse.catalog import Catalog
from warehouse.tasks import task_rows


def explored_workspace(root: Path, config: CampaignConfig) -> Workspace:
    """`config`'s tasks generated and its iteration 0 explored into a new workspace at `root`, registered."""
    workspace = Workspace.at(root).create()
    catalog = Catalog(workspace.catalog)
    catalog.initialise()
    tasks = generate_tasks(config.tasks, config.seed)
    catalog.register_unit(unit_key="tasks", stage="generate_tasks", campaign=config.name, iteration=0, summary={},
                          rows={"tasks": task_rows(tasks, config.name, "tasks")})
    for unit in plan_explore(config, 0, tasks, None, {}, workspace):
        catalog.register_unit(unit_key=unit.unit_key, stage="explore", campaign=config.name, iteration=0,
                              summary={}, shards=run_explore_unit(unit))
    return workspace
