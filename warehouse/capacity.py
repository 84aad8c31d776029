"""Will the campaign's exploration fit on the disk? Estimated before any work, so a million-triplet
preset on a small disk costs one line instead of a run that stops hours in with the disk full.

Explored steps: each seen task's episodes at each iteration not yet indexed (explore.episodes_at:
first_episodes_per_task at iteration 0, episodes_per_task after) times its scripted expert's measured
mean episode length (schemas/task_specs/experts.json, docs/experts.md; the task's horizon where it has no
record); episodes cut short (explore.policy_steps) are counted whole, so that is an upper bound. Bytes
per step: this warehouse's own steps shards of this campaign where it has some, else the figure measured
on 84 px frames scaled by the frame's area.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from pydantic import BaseModel

from schemas.config import CampaignConfig
from schemas.errors import Sim2ActError
from schemas.experts import ExpertTable, load_expert_table
from schemas.tasks import TaskRecord
from warehouse.catalog import Catalog
from warehouse.store import FOLDER

# Bytes per steps row at 84 px RGB (zstd level 3), measured 2026-11-26: 2,855 (quality campaign, Lift,
# 5,848 rows) and 2,867 (smoke, Lift and Stack, 1,086 rows). Nearly all of it is the frame.
BYTES_PER_STEP_84PX = 2_900
DEPTH_FACTOR = 1.5  # a depth map beside each frame (an upper bound until measured)
MARGIN = 1.2  # episodes, filter decisions, the catalog, and estimates that run short


class InsufficientDisk(Sim2ActError, OSError):
    pass


class ExploreEstimate(BaseModel):
    iterations: int  # left to explore
    steps: int  # explored steps over those iterations
    bytes_per_step: float
    measured_here: bool  # bytes per step from this warehouse's own shards

    @property
    def bytes(self) -> int:
        return int(self.steps * self.bytes_per_step * MARGIN)


def bytes_per_step(config: CampaignConfig, catalog: Catalog | None) -> tuple[float, bool]:
    """(bytes per steps row, measured on this warehouse's shards of this campaign)."""
    if catalog is not None and catalog.path.exists():
        [(size, rows)] = catalog.query("SELECT sum(num_bytes), sum(num_rows) FROM shards WHERE table_name = 'steps' "
                                       "AND campaign = ?", [config.name])  # its own frames: another may differ in size
        if rows:
            return size / rows, True
    scale = (config.render.image_size / 84) ** 2 * config.render.views * (DEPTH_FACTOR if config.render.depth else 1.0)
    return BYTES_PER_STEP_84PX * scale, False


def expected_steps(config: CampaignConfig, task: TaskRecord, experts: ExpertTable | None = None,
                   iteration: int = 0) -> float:
    """The steps `iteration` explores in a seen task: its episodes (explore.episodes_at) x its expert's
    mean episode length (the horizon where the table has no row)."""
    experts = experts or load_expert_table()
    row = experts.rows.get(task.task_id)
    return config.explore.episodes_at(iteration) * (row.mean_length if row else task.horizon)


def explore_estimate(config: CampaignConfig, tasks: list[TaskRecord], catalog: Catalog | None = None,
                     experts: ExpertTable | None = None) -> ExploreEstimate:
    """The steps the campaign's remaining iterations will explore, and their bytes."""
    experts = experts or load_expert_table()
    done = 0
    if catalog is not None and catalog.path.exists():
        [(done,)] = catalog.query("SELECT count(DISTINCT iteration) FROM iterations WHERE campaign = ?", [config.name])
    left = max(0, config.iterations - done)
    steps = sum(expected_steps(config, t, experts, i) for i in range(done, config.iterations) for t in tasks
                if t.split == "seen")
    size, measured = bytes_per_step(config, catalog)
    return ExploreEstimate(iterations=left, steps=round(steps), bytes_per_step=size, measured_here=measured)


def check_disk(root: Path, config: CampaignConfig, tasks: list[TaskRecord], catalog: Catalog | None = None) -> ExploreEstimate:
    """The estimate, if the disk under `root` (or its nearest existing parent) holds it.

    Raises:
        InsufficientDisk: the estimate exceeds the free space; the line says both and what to change.
    """
    estimate = explore_estimate(config, tasks, catalog)
    if catalog is not None and catalog.store.url != FOLDER:
        return estimate  # shards go to an object store: this disk holds only the catalog
    where = root
    while not where.exists():
        where = where.parent
    free = shutil.disk_usage(where).free
    if estimate.bytes > free:
        basis = "as measured on this warehouse" if estimate.measured_here else f"at {config.render.image_size} px"
        raise InsufficientDisk(
            f"explore: campaign {config.name!r} needs about {estimate.bytes / 1e9:.1f} GB for {estimate.iterations} more "
            f"iteration(s) ({estimate.steps:,} steps x {estimate.bytes_per_step / 1e3:.1f} KB {basis}, +20%), but "
            f"{where} has {free / 1e9:.1f} GB free: free space, choose another --workspace, or lower "
            "explore.episodes_per_task"
        )
    return estimate
