"""filter: validation, dedupe and rejection sampling. Every explored episode gets a decision and
its reason in `filter_decisions`."""

from __future__ import annotations

import hashlib
import logging
import math
import struct
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import pyarrow as pa

from envs.registry import action_bounds
from schemas.config import CampaignConfig, FilterConfig
from schemas.frames import depth_side, frame_shape
from schemas.keys import unit_key
from schemas.tables import FILTER_DECISIONS
from schemas.workspace import Workspace
from stages import StageResult, StageUnits, UnitOutput
from warehouse.catalog import Catalog
from warehouse.shard_writer import write_shard

STAGE, VERSION = "filter", 2
STEP_COLUMNS = ["episode_id", "image", "depth", "proprio", "action", "reward"]
log = logging.getLogger("sim2act.stages.filter")


class FilterResult(StageResult):
    unit_keys: list[str]
    reasons: dict[str, int]  # counts of this run's decisions by reason (empty when all skipped)
    skipped_units: int

    def did_work(self) -> bool:
        return self.skipped_units < len(self.unit_keys)

    def metrics(self) -> dict[str, float]:
        if not self.reasons:
            return {}
        return {"filter.pass_rate": self.reasons.get("kept", 0) / sum(self.reasons.values()),
                **{f"filter.{reason}": count for reason, count in self.reasons.items()}}


@dataclass(frozen=True)
class EpisodeFacts:
    """What validation and dedupe need from an episode's steps."""

    digest: str
    invalid: str | None  # the first non-finite value, named
    out_of_bounds: str | None  # the first action component outside the family's range
    bad_image: str | None  # the first frame (or depth map) that is not one of the campaign's size


def episode_facts(steps: list[dict], bounds: tuple[float, float], image_size: int, depth: bool = False,
                  views: int = 1) -> EpisodeFacts:
    """Pure: facts about one episode's steps (rows with STEP_COLUMNS, in step order); `depth`: the
    campaign records depth maps, so every step must carry one; `views`: square views side by side
    in each frame (render.views)."""
    digest = hashlib.blake2b(digest_size=16)
    invalid = out_of_bounds = bad_image = None
    low, high = bounds
    for index, row in enumerate(steps):
        digest.update(row["image"])
        digest.update(struct.pack(f"{len(row['action'])}f", *row["action"]))
        for column in ("proprio", "action", "reward"):
            values = row[column] if isinstance(row[column], list) else [row[column]]
            if invalid is None and not all(math.isfinite(v) for v in values):
                invalid = f"step {index}: non-finite {column}"
        if out_of_bounds is None and any(not low <= v <= high for v in row["action"]):
            out_of_bounds = f"step {index}: action {[round(v, 3) for v in row['action']]} outside [{low:g}, {high:g}]"
        if bad_image is None and frame_shape(row["image"]) != (image_size, views * image_size):
            bad_image = (f"step {index}: image of {len(row['image'])} bytes is not a {image_size}x{views * image_size} "
                         f"RGB frame")
        if bad_image is None and depth and (row["depth"] is None or depth_side(row["depth"]) != image_size):
            size = "no" if row["depth"] is None else f"{len(row['depth'])} bytes of"
            bad_image = f"step {index}: {size} depth map, not a {image_size}x{image_size} one"
    return EpisodeFacts(digest.hexdigest(), invalid, out_of_bounds, bad_image)


def decide(episode: dict, facts: EpisodeFacts, config: FilterConfig, kept_digests: dict[str, str]) -> tuple[str, str | None]:
    """Pure: ('kept', None) or the reason an episode is rejected and what exactly failed.
    `kept_digests` maps the digests of episodes already kept to their ids."""
    if episode["error"]:
        return "env_error", episode["error"]
    for reason, detail in (("invalid_values", facts.invalid), ("action_out_of_bounds", facts.out_of_bounds),
                           ("bad_image", facts.bad_image)):
        if detail:
            return reason, detail
    if facts.digest in kept_digests:
        return "duplicate", f"same actions and observations as {kept_digests[facts.digest]}"
    if config.require_success and not episode["success"]:
        return "not_successful", None
    if episode["episode_return"] < config.min_return:
        return "low_return", f"return {episode['episode_return']:.3f} < {config.min_return:g}"
    return "kept", None


def _steps_by_episode(steps: pa.Table) -> dict[str, list[dict]]:
    by_episode: dict[str, list[dict]] = {}
    for row in steps.to_pylist():
        by_episode.setdefault(row["episode_id"], []).append(row)
    return by_episode


def filter_unit_key(config: CampaignConfig, explore_key: str) -> str:
    """The filter unit deciding one explore unit's episodes under `config`: keyed by the filter settings, the
    frame size and the explore unit."""
    reads = {"filter": config.filter, "image_size": config.render.image_size, "depth": config.render.depth,
             **({"views": config.render.views} if config.render.views > 1 else {})}  # one view: keys as before
    return unit_key(STAGE, VERSION, reads, [explore_key])


def run_filter(workspace: Workspace, config: CampaignConfig, iteration: int, explore_keys: list[str],
               earlier_filter_keys: Sequence[str] = ()) -> FilterResult:
    """Unit of work: one explore shard's episodes, keyed by the filter settings, the frame size and
    the explore unit. Registers one `filter_decisions` shard: each episode kept or rejected, why.
    A duplicate is an episode the same as one kept in this dataset's lineage: these units or
    `earlier_filter_keys` (the earlier iterations' filter units, IndexResult.filter_units)."""
    catalog = Catalog(workspace.catalog)
    units = StageUnits(catalog, STAGE, config.name, iteration)
    keys = {explore_key: filter_unit_key(config, explore_key) for explore_key in explore_keys}
    pending = set(units.pending(keys.values()))
    families = dict(catalog.query("SELECT task_id, family FROM task_families WHERE campaign = ?", [config.name]))
    # Units are decided in a fixed order, so a resumed run dedupes exactly as an uninterrupted one. Only this
    # lineage's decisions: another filter setting's (a changed filter.*, earlier in the campaign) kept the same
    # episodes, and read here they would turn each one into a duplicate of itself.
    lineage = sorted(set(earlier_filter_keys) | set(keys.values()))
    kept_digests = dict(catalog.query(
        "SELECT episode_digest, min(episode_id) FROM filter_decisions "
        "WHERE kept AND campaign = ? AND list_contains(?, filter_key) GROUP BY 1",
        [config.name, lineage],
    ))
    reasons: Counter[str] = Counter()
    for explore_key, key in keys.items():
        if key not in pending:
            continue
        started = time.monotonic()
        steps = _steps_by_episode(catalog.read_unit_shard("steps", explore_key, STEP_COLUMNS))
        decisions = []
        for episode in catalog.read_unit_shard("episodes", explore_key).to_pylist():
            bounds = action_bounds(families[episode["task_id"]])
            facts = episode_facts(steps.get(episode["episode_id"], []), bounds, config.render.image_size,
                                  config.render.depth, config.render.views)
            reason, detail = decide(episode, facts, config.filter, kept_digests)
            if reason == "kept":
                kept_digests[facts.digest] = episode["episode_id"]
            reasons[reason] += 1
            decisions.append(
                {
                    "campaign": episode["campaign"], "iteration": episode["iteration"],
                    "episode_id": episode["episode_id"], "task_id": episode["task_id"], "kept": reason == "kept",
                    "reason": reason, "detail": detail, "episode_digest": facts.digest,
                    "episode_return": episode["episode_return"], "filter_key": key,
                }
            )
        shard = write_shard(
            "filter_decisions", pa.Table.from_pylist(decisions, schema=FILTER_DECISIONS),
            workspace.shard_path("filter_decisions", iteration, key), catalog.store,
        )
        units.register(key, UnitOutput(dict(Counter(d["reason"] for d in decisions)), [shard]),
                       time.monotonic() - started)
    kept = reasons.get("kept", 0)
    total = sum(reasons.values())
    log.info(
        "filter it%d: %d shards (%d already registered); this run kept %d/%d episodes %s",
        iteration, len(keys), len(keys) - len(pending), kept, total, dict(reasons),
    )
    return FilterResult(unit_keys=list(keys.values()), reasons=dict(reasons), skipped_units=len(keys) - len(pending))
