"""filter: rejection sampling. Every explored episode gets a decision and a reason."""

from __future__ import annotations

import logging
import time
from collections import Counter

import pyarrow as pa
from pydantic import BaseModel

from schemas.config import CampaignConfig, FilterConfig
from schemas.keys import unit_key
from schemas.tables import FILTER_DECISIONS
from schemas.workspace import Workspace
from warehouse.catalog import Catalog
from warehouse.shard_writer import read_shard, write_shard

STAGE, VERSION = "filter", 1
log = logging.getLogger("sim2act.stages.filter")


class FilterResult(BaseModel):
    unit_keys: list[str]
    reasons: dict[str, int]  # counts of this run's decisions by reason (empty when all skipped)
    skipped_units: int


def decide(episode: dict, config: FilterConfig) -> str:
    """Pure: 'kept' or the reason an episode is rejected."""
    if episode["error"]:
        return "env_error"
    if config.require_success and not episode["success"]:
        return "not_successful"
    if episode["episode_return"] < config.min_return:
        return "low_return"
    return "kept"


def run_filter(workspace: Workspace, config: CampaignConfig, iteration: int, explore_keys: list[str]) -> FilterResult:
    catalog = Catalog(workspace.catalog)
    keys = {explore_key: unit_key(STAGE, VERSION, config.filter, [explore_key]) for explore_key in explore_keys}
    done = catalog.registered_keys(list(keys.values()))
    reasons: Counter[str] = Counter()
    for explore_key, key in keys.items():
        if key in done:
            continue
        started = time.monotonic()
        [(path, _)] = catalog.shard_paths("episodes", "unit_key = ?", [explore_key])
        decisions = []
        for episode in read_shard("episodes", path).to_pylist():
            reason = decide(episode, config.filter)
            reasons[reason] += 1
            decisions.append(
                {
                    "campaign": episode["campaign"], "iteration": episode["iteration"],
                    "episode_id": episode["episode_id"], "task_id": episode["task_id"], "kept": reason == "kept",
                    "reason": reason, "episode_return": episode["episode_return"], "filter_key": key,
                }
            )
        shard = write_shard(
            "filter_decisions", pa.Table.from_pylist(decisions, schema=FILTER_DECISIONS),
            workspace.shard_path("filter_decisions", iteration, key),
        )
        catalog.register_unit(
            unit_key=key, stage=STAGE, campaign=config.name, iteration=iteration,
            summary=dict(Counter(d["reason"] for d in decisions)), wall_s=time.monotonic() - started, shards=[shard],
        )
    kept = reasons.get("kept", 0)
    total = sum(reasons.values())
    log.info(
        "filter it%d: %d shards (%d already registered); this run kept %d/%d episodes %s",
        iteration, len(keys), len(done), kept, total, dict(reasons),
    )
    return FilterResult(unit_keys=list(keys.values()), reasons=dict(reasons), skipped_units=len(done))
