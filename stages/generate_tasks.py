"""generate_tasks: language tasks from environment metadata by a template generator.

Each task is an environment plus object colours, said at least three ways. Deterministic for
a seed. The instruction embeddings are computed here once and stored in the warehouse.
"""

from __future__ import annotations

import itertools
import json
import logging
import time

import numpy as np
import pyarrow as pa
from pydantic import BaseModel

from envs.robosuite_env import ENV_METADATA
from schemas.config import CampaignConfig, ConfigError, TasksConfig
from schemas.keys import derive_seed, unit_key
from schemas.tables import INSTRUCTIONS
from schemas.tasks import TaskRecord
from schemas.workspace import Workspace
from warehouse.catalog import Catalog
from warehouse.shard_writer import write_shard

STAGE, VERSION = "generate_tasks", 1
log = logging.getLogger("sim2act.stages.generate_tasks")


class TasksResult(BaseModel):
    unit_key: str
    task_ids: list[str]
    instructions: int
    skipped: bool


def _colourings(env_name: str, colours: list[str]) -> list[dict[str, str]]:
    roles = list(ENV_METADATA[env_name].objects)
    return [dict(zip(roles, combo)) for combo in itertools.permutations(colours, len(roles))]


def generate_tasks(config: TasksConfig, seed: int) -> list[TaskRecord]:
    """Pure: the concrete tasks a tasks config describes. Raises ConfigError for unknown ids."""
    tasks = []
    for env_name in config.envs:
        meta = ENV_METADATA[env_name]
        colourings = _colourings(env_name, config.colours)[: config.max_tasks_per_env]
        for colouring in colourings:
            task_id = "-".join([env_name.lower(), *colouring.values()])
            rng = np.random.default_rng(derive_seed(seed, task_id, "paraphrases"))
            order = [0, *(1 + rng.permutation(len(meta.templates) - 1))]
            instructions = [meta.templates[i].format(**colouring) for i in order[: config.paraphrases]]
            if len(instructions) < config.paraphrases:
                raise ConfigError(
                    f"tasks.paraphrases: {env_name} has {len(meta.templates)} templates, {config.paraphrases} asked"
                )
            unseen = any(c in config.unseen_colours for c in colouring.values())
            tasks.append(
                TaskRecord(
                    task_id=task_id,
                    family="robosuite",
                    env_name=env_name,
                    object_colours=colouring,
                    instructions=instructions,
                    split="unseen" if unseen else "seen",
                    horizon=config.horizon[env_name],
                )
            )
    if config.include is not None:
        known = {t.task_id for t in tasks}
        unknown = sorted(set(config.include) - known)
        if unknown:
            raise ConfigError(f"tasks.include: unknown task {unknown[0]!r} (known: {', '.join(sorted(known))})")
        tasks = [t for t in tasks if t.task_id in config.include]
    if not tasks:
        raise ConfigError("tasks: the config yields no task")
    return tasks


def tasks_unit_key(config: CampaignConfig) -> str:
    return unit_key(STAGE, VERSION, {"tasks": config.tasks, "seed": config.seed, "campaign": config.name})


def run_generate_tasks(workspace: Workspace, config: CampaignConfig) -> TasksResult:
    from policies.language import encode  # loading the encoder is slow: only when there is work

    catalog = Catalog(workspace.catalog)
    key = tasks_unit_key(config)
    tasks = generate_tasks(config.tasks, config.seed)
    ids = [t.task_id for t in tasks]
    if catalog.is_registered(key):
        log.info("generate_tasks: %d tasks already registered (%s), skipped", len(tasks), key)
        return TasksResult(unit_key=key, task_ids=ids, instructions=0, skipped=True)
    started = time.monotonic()
    pairs = [(t.task_id, text) for t in tasks for text in t.instructions]
    encoder = config.train.model.language_encoder
    log.info("generate_tasks: %d tasks, %d instructions; embedding them with %s", len(tasks), len(pairs), encoder)
    embeddings = encode(encoder, [text for _, text in pairs])
    shard = write_shard(
        "instructions",
        pa.table(
            {
                "task_id": [task_id for task_id, _ in pairs],
                "instruction": [text for _, text in pairs],
                "encoder": [encoder] * len(pairs),
                "embedding": [row.tolist() for row in embeddings],
            },
            schema=INSTRUCTIONS,
        ),
        workspace.shard_path("instructions", 0, key),
    )
    rows = [
        {
            "campaign": config.name,
            "task_id": t.task_id,
            "family": t.family,
            "env_name": t.env_name,
            "instruction": t.instruction,
            "instructions": t.instructions,
            "object_colours": json.dumps(t.object_colours),
            "split": t.split,
            "horizon": t.horizon,
            "unit_key": key,
        }
        for t in tasks
    ]
    catalog.register_unit(
        unit_key=key, stage=STAGE, campaign=config.name, iteration=0,
        summary={"tasks": len(tasks), "instructions": len(pairs)},
        wall_s=time.monotonic() - started, shards=[shard], rows={"tasks": rows},
    )
    log.info("generate_tasks: registered %d tasks: %s", len(tasks), ", ".join(ids))
    return TasksResult(unit_key=key, task_ids=ids, instructions=len(pairs), skipped=False)


def load_tasks(workspace: Workspace, task_unit_key: str) -> list[TaskRecord]:
    rows = Catalog(workspace.catalog).query(
        "SELECT task_id, family, env_name, object_colours, instructions, split, horizon FROM tasks "
        "WHERE unit_key = ? ORDER BY task_id",
        [task_unit_key],
    )
    return [
        TaskRecord(
            task_id=r[0], family=r[1], env_name=r[2], object_colours=json.loads(r[3]),
            instructions=list(r[4]), split=r[5], horizon=r[6],
        )
        for r in rows
    ]


def load_embeddings(workspace: Workspace, task_unit_key: str, encoder: str) -> dict[str, np.ndarray]:
    """instruction -> embedding for every instruction of the tasks generated by `task_unit_key`."""
    table = Catalog(workspace.catalog).query_arrow(
        "SELECT DISTINCT instruction, embedding FROM instructions "
        "WHERE encoder = ? AND task_id IN (SELECT task_id FROM tasks WHERE unit_key = ?)",
        [encoder, task_unit_key],
    )
    return {
        text: np.asarray(vector, dtype=np.float32)
        for text, vector in zip(table["instruction"].to_pylist(), table["embedding"].to_pylist())
    }
