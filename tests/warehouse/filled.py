"""A small real warehouse for tests: synthetic explore units (real Parquet, frames stored raw as campaigns store
them), registered through the catalog, decided by the real filter stage."""

from __future__ import annotations

import json

from bench.synthetic import TASKS, register_explore_unit
from schemas.config import CampaignConfig, FilterConfig
from schemas.workspace import Workspace
from stages.filter import run_filter
from warehouse.catalog import Catalog

CONFIG = CampaignConfig(name="bench", filter=FilterConfig(min_return=5.0))


def register_tasks(workspace: Workspace) -> None:
    rows = [
        {"campaign": CONFIG.name, "task_id": t, "spec": t.split("-")[0], "family": "metaworld" if t.startswith("mw") else "robosuite",
         "env_name": "Lift", "instruction": f"do {t}", "instructions": [f"do {t}"], "unseen_instructions": [],
         "object_colours": json.dumps({}), "split": "seen", "horizon": 50, "unit_key": "tasks-test"}
        for t in TASKS
    ]
    Catalog(workspace.catalog).register_unit(
        unit_key="tasks-test", stage="generate_tasks", campaign=CONFIG.name, iteration=0, summary={}, rows={"tasks": rows}
    )


def register_explore(workspace: Workspace, key: str, iteration: int, seed: int, **sizes) -> bool:
    return register_explore_unit(workspace, key, campaign=CONFIG.name, iteration=iteration, seed=seed, **sizes)


def fill(workspace: Workspace, iterations: int = 2, units: int = 2, **sizes) -> dict[int, list[str]]:
    """-> explore unit keys by iteration; every unit also filtered."""
    Catalog(workspace.catalog).initialise()
    register_tasks(workspace)
    keys: dict[int, list[str]] = {}
    for iteration in range(iterations):
        keys[iteration] = [f"explore-i{iteration}u{u}" for u in range(units)]
        for u, key in enumerate(keys[iteration]):
            register_explore(workspace, key, iteration, seed=iteration * 100 + u, **sizes)
        run_filter(workspace, CONFIG, iteration, keys[iteration])
    return keys
