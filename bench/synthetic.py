"""Synthetic explore units: episodes and steps of the real schemas, with real frames, at any
size. The warehouse benchmark and tests fill warehouses with them without running a simulator."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pyarrow as pa

from schemas.frames import encode_frame
from schemas.tables import EPISODES, STEPS
from schemas.workspace import Workspace
from warehouse.catalog import Catalog
from warehouse.shard_writer import write_shard

TASKS = ("lift-red", "lift-blue", "stack-red-on-green", "door-yellow", "nut-square-red", "mw-pick-place")


def frame(image_size: int, colour: Sequence[int], step: int) -> np.ndarray:
    """A table-top-like frame: a textured background and a coloured block that moves each step.
    Its coarse texture compresses about as well as a rendered robosuite frame does."""
    y, x = np.mgrid[0:image_size, 0:image_size]
    coarse = np.random.default_rng(step).integers(0, 8, (image_size // 4 + 1, image_size // 4 + 1, 3))
    texture = np.repeat(np.repeat(coarse, 4, axis=0), 4, axis=1)[:image_size, :image_size]
    image = (np.stack([90 + x // 3, 110 + y // 4, np.full_like(x, 130)], axis=-1) + texture).astype(np.uint8)
    corner = (step * 2) % (image_size - 12)
    image[corner : corner + 12, 20:32] = colour
    return image


def explore_unit(
    unit_key: str, *, campaign: str = "bench", iteration: int = 0, episodes: int = 4, steps: int = 50,
    image_size: int = 84, tasks: Sequence[str] = TASKS, seed: int = 0, unique_frames: int = 8,
) -> dict[str, pa.Table]:
    """One unit's `episodes` and `steps` tables. Frames cycle through `unique_frames` frames per
    episode (drawing them dominates otherwise); every other column is drawn per step."""
    rng = np.random.default_rng(seed)
    episode_rows, step_rows = [], []
    for e in range(episodes):
        task = tasks[(seed + e) % len(tasks)]
        episode_id = f"{campaign}-i{iteration}-{unit_key}-e{e:03d}"
        colour = rng.integers(0, 256, 3).tolist()
        frames = [encode_frame(frame(image_size, colour, s)) for s in range(unique_frames)]
        rewards = rng.random(steps).astype(np.float32)
        success = bool(rng.random() < 0.5)
        for s in range(steps):
            last = s == steps - 1
            step_rows.append({
                "campaign": campaign, "iteration": iteration, "episode_id": episode_id, "task_id": task, "step": s,
                "instruction": f"do {task}", "image": frames[s % unique_frames],
                "proprio": rng.normal(size=9).astype(np.float32).tolist(),
                "action": rng.uniform(-1, 1, 7).astype(np.float32).tolist(), "reward": float(rewards[s]),
                "done": last, "success": success and last, "next_image": frames[0] if last else None,
                "qpos": rng.normal(size=16).tolist(), "qvel": rng.normal(size=15).tolist(), "act": [],
                "mocap": [], "sim_time": s * 0.05,
            })
        episode_rows.append({
            "campaign": campaign, "iteration": iteration, "episode_id": episode_id, "task_id": task,
            "instruction": f"do {task}", "explorer": "expert", "seed": seed * 1000 + e, "shard_key": unit_key,
            "num_steps": steps, "episode_return": float(rewards.sum()), "success": success, "error": None,
            "randomisation": None,
        })
    return {
        "episodes": pa.Table.from_pylist(episode_rows, schema=EPISODES),
        "steps": pa.Table.from_pylist(step_rows, schema=STEPS),
    }


def register_explore_unit(workspace: Workspace, key: str, *, campaign: str = "bench", iteration: int = 0,
                          seed: int = 0, **sizes) -> bool:
    """Write one synthetic unit's shards and register them as an explore unit (False: already was)."""
    tables = explore_unit(key, campaign=campaign, iteration=iteration, seed=seed, **sizes)
    catalog = Catalog(workspace.catalog)
    shards = [write_shard(name, table, workspace.shard_path(name, iteration, key), catalog.store)
              for name, table in tables.items()]
    return catalog.register_unit(
        unit_key=key, stage="explore", campaign=campaign, iteration=iteration, summary={}, shards=shards
    )
