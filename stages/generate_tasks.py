"""generate_tasks: language tasks from environment metadata by a template generator.

Each task is an environment plus object colours, said at least three ways. Deterministic for
a seed. The instruction embeddings are computed here once and stored in the warehouse.
"""

from __future__ import annotations

import itertools
import json
import logging
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
from pydantic import BaseModel

from schemas.config import CampaignConfig, ConfigError, TasksConfig
from schemas.experts import load_expert_table
from schemas.keys import derive_seed, unit_key
from schemas.tables import INSTRUCTIONS
from schemas.task_spec import SuiteEntry, TaskSpec, load_specs
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
    proposals_valid: int = 0
    proposals_rejected: dict[str, int] = {}


def _bindings(spec: TaskSpec, allowed: list[str] | None) -> list[dict[str, str]]:
    """Every assignment of distinct colours to the spec's object roles, in spec order."""
    roles = list(spec.objects)
    choices = [[c for c in spec.objects[r].colours if allowed is None or c in allowed] for r in roles]
    return [dict(zip(roles, combo)) for combo in itertools.product(*choices) if len(set(combo)) == len(combo)]


def task_id_of(spec: TaskSpec, colouring: dict[str, str]) -> str:
    return "-".join([spec.name, *colouring.values()])


def bind_task(spec: TaskSpec, colouring: dict[str, str], instructions: list[str], config: TasksConfig) -> TaskRecord:
    """The task one binding of colours to a spec's roles makes, said with `instructions`: its
    split, horizon and held-out paraphrases follow from the spec and the config alone."""
    task_id = task_id_of(spec, colouring)
    unseen_colours = set(spec.split.unseen_colours) | set(config.unseen_colours)
    unseen = task_id in spec.split.unseen_tasks or any(c in unseen_colours for c in colouring.values())
    return TaskRecord(
        task_id=task_id, spec=spec.name, family=spec.family, env_name=spec.env, object_colours=colouring,
        instructions=instructions, split="unseen" if unseen else "seen",
        horizon=config.horizon.get(spec.name, spec.horizon),
        unseen_instructions=[template.format(**colouring) for template in spec.split.unseen_templates],
    )


def expand_spec(spec: TaskSpec, config: TasksConfig, seed: int, skip: frozenset[str] = frozenset()) -> list[TaskRecord]:
    """Pure: the concrete tasks one spec yields under a tasks config, leaving out `skip` ids
    before max_tasks_per_spec counts."""
    if len(spec.templates) < config.paraphrases:
        raise ConfigError(f"tasks.paraphrases: spec {spec.name} has {len(spec.templates)} templates, "
                          f"{config.paraphrases} asked")
    tasks = []
    kept = [b for b in _bindings(spec, config.colours) if task_id_of(spec, b) not in skip]
    for colouring in kept[: config.max_tasks_per_spec]:
        rng = np.random.default_rng(derive_seed(seed, task_id_of(spec, colouring), "paraphrases"))
        order = [0, *(1 + rng.permutation(len(spec.templates) - 1))]
        said = [spec.templates[i].format(**colouring) for i in order[: config.paraphrases]]
        tasks.append(bind_task(spec, colouring, said, config))
    return tasks


def generate_tasks(config: TasksConfig, seed: int) -> list[TaskRecord]:
    """Pure: the concrete tasks a tasks config describes. Raises ConfigError for what does not exist."""
    from envs.registry import check_spec

    suite = load_specs(config.spec_files)
    flagged = frozenset(load_expert_table().flagged() if config.weak_experts == "skip" else ())
    weak = sorted(set(config.include or ()) & flagged)
    if weak:
        raise ConfigError(f"tasks.include: {weak[0]!r} has a scripted expert below target (docs/experts.md); "
                          "set tasks.weak_experts: keep to use it")
    tasks = []
    for name in config.specs:
        if name not in suite:
            raise ConfigError(f"tasks.specs: unknown spec {name!r} (`sim2act tasks list` shows the suite)")
        check_spec(suite[name].spec, suite[name].origin)
        tasks.extend(expand_spec(suite[name].spec, config, seed, skip=flagged))
    unknown_horizons = sorted(set(config.horizon) - set(config.specs))
    if unknown_horizons:
        raise ConfigError(f"tasks.horizon: {unknown_horizons[0]!r} is not one of tasks.specs")
    if config.include is not None:
        known = {t.task_id for t in tasks}
        unknown = sorted(set(config.include) - known)
        if unknown:
            raise ConfigError(f"tasks.include: unknown task {unknown[0]!r} (known: {', '.join(sorted(known))})")
        tasks = [t for t in tasks if t.task_id in config.include]
    if not tasks:
        raise ConfigError("tasks: the config yields no task")
    return tasks


def subtask_instructions(task: TaskRecord, suite: dict[str, SuiteEntry]) -> list[str]:
    """A long-horizon task's sub-tasks, said canonically with its colours, in order ([]: not long-horizon,
    or a spec the suite does not hold, such as a proposer's)."""
    entry = suite.get(task.spec)
    subtasks = entry.spec.subtasks if entry else []
    return [suite[sub.spec].spec.templates[0].format(**{role: task.object_colours[mine] for role, mine in sub.objects.items()})
            for sub in subtasks]


def suite_tasks(spec_files: list[Path] = (), seed: int = 0) -> list[TaskRecord]:
    """Every task of the built-in suite and the given files, all colours bound."""
    names = list(load_specs(list(spec_files)))
    return generate_tasks(TasksConfig(specs=names, spec_files=list(spec_files), weak_experts="keep"), seed)


def tasks_unit_key(config: CampaignConfig, tasks: list[TaskRecord]) -> str:
    """Keyed by the template tasks themselves (editing a spec file makes new tasks) and the
    proposer settings: an LLM is asked once per key, and its answer is what gets registered."""
    reads = {"campaign": config.name, "encoder": config.train.model.language_encoder,
             "proposer": config.tasks.proposer}
    return unit_key(STAGE, VERSION, reads, [t.model_dump_json() for t in tasks])


def run_generate_tasks(workspace: Workspace, config: CampaignConfig) -> TasksResult:
    from policies.language import encode  # loading the encoder is slow: only when there is work

    catalog = Catalog(workspace.catalog)
    tasks = generate_tasks(config.tasks, config.seed)
    key = tasks_unit_key(config, tasks)
    if catalog.is_registered(key):
        ids = [t.task_id for t in load_tasks(workspace, key)]
        log.info("generate_tasks: %d tasks already registered (%s), skipped", len(ids), key)
        return TasksResult(unit_key=key, task_ids=ids, instructions=0, skipped=True)
    started = time.monotonic()
    proposals = None
    if config.tasks.proposer is not None:
        from stages.llm_proposer import propose

        suite = load_specs(config.tasks.spec_files)
        proposals = propose(config.tasks, {n: suite[n].spec for n in config.tasks.specs}, tasks)
        tasks = proposals.tasks
    ids = [t.task_id for t in tasks]
    pairs = [(t.task_id, text) for t in tasks for text in [*t.instructions, *t.unseen_instructions]]
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
    catalog.register_unit(
        unit_key=key, stage=STAGE, campaign=config.name, iteration=0,
        summary={"tasks": len(tasks), "instructions": len(pairs),
                 **({"proposals": proposals.model_dump(exclude={"tasks"})} if proposals else {})},
        wall_s=time.monotonic() - started, shards=[shard], rows={"tasks": task_rows(tasks, config.name, key)},
    )
    log.info("generate_tasks: registered %d tasks: %s", len(tasks), ", ".join(ids))
    return TasksResult(unit_key=key, task_ids=ids, instructions=len(pairs), skipped=False,
                       proposals_valid=proposals.valid if proposals else 0,
                       proposals_rejected=proposals.rejected if proposals else {})


def task_rows(tasks: list[TaskRecord], campaign: str, unit_key: str) -> list[dict]:
    """The `tasks` table rows of a tasks unit."""
    return [
        {
            "campaign": campaign,
            "task_id": t.task_id,
            "spec": t.spec,
            "family": t.family,
            "env_name": t.env_name,
            "instruction": t.instruction,
            "instructions": t.instructions,
            "unseen_instructions": t.unseen_instructions,
            "object_colours": json.dumps(t.object_colours),
            "split": t.split,
            "horizon": t.horizon,
            "unit_key": unit_key,
        }
        for t in tasks
    ]


_TASK_COLUMNS = "task_id, spec, family, env_name, object_colours, instructions, split, horizon, unseen_instructions"


def _task_record(r: tuple) -> TaskRecord:
    return TaskRecord(
        task_id=r[0], spec=r[1], family=r[2], env_name=r[3], object_colours=json.loads(r[4]),
        instructions=list(r[5]), split=r[6], horizon=r[7], unseen_instructions=list(r[8]),
    )


def load_tasks(workspace: Workspace, task_unit_key: str) -> list[TaskRecord]:
    rows = Catalog(workspace.catalog).query(
        f"SELECT {_TASK_COLUMNS} FROM tasks WHERE unit_key = ? ORDER BY task_id", [task_unit_key]
    )
    return [_task_record(r) for r in rows]


def find_task(catalog: Catalog, campaign: str, task_id: str) -> TaskRecord | None:
    """A campaign's task by id (the lowest unit key's, should several tasks units name it), or None."""
    rows = catalog.query(
        f"SELECT {_TASK_COLUMNS} FROM tasks WHERE campaign = ? AND task_id = ? ORDER BY unit_key LIMIT 1",
        [campaign, task_id],
    )
    return _task_record(rows[0]) if rows else None


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
