"""How well each task's scripted expert does, measured in worker processes without a camera under a
domain randomisation; and, for a campaign whose randomisation moves what an expert feels (object
sizes, masses, frictions) away from the default that schemas/task_specs/experts.json was measured
under, each task's expert under the campaign's own, measured once per workspace and cached there."""

from __future__ import annotations

import datetime
import logging
from collections.abc import Callable

import numpy as np
from pydantic import BaseModel

from envs.pool import Progress, run_in_pool
from envs.rollout import rollout, worker_env
from schemas.config import RandomiseConfig
from schemas.experts import ExpertRow
from schemas.keys import derive_seed, unit_key
from schemas.tasks import TaskRecord
from schemas.workspace import Workspace, write_text_atomically

EPISODES, NOISE = 10, 0.1  # per task, as the shipped table was measured (`sim2act tasks experts` defaults)
FELT = ("enabled", "size", "mass", "friction")  # a camera-less expert cannot see light, camera, tint or colour
VERSION = 1  # of the check: a new version measures again
log = logging.getLogger("sim2act.envs.expert_check")


class ExpertCheck(BaseModel):
    task: TaskRecord
    episodes: int
    noise: float
    randomise: RandomiseConfig
    command: str


def check_expert(check: ExpertCheck) -> ExpertRow:
    """Worker: the expert's episodes on one task, without a camera."""
    from envs.randomisation import sample_randomisation
    from envs.registry import make_expert

    env = worker_env(check.task, None)
    successes, lengths = 0, []
    for episode in range(check.episodes):
        seed = derive_seed("expert-check", check.task.task_id, episode)
        expert = make_expert(check.task, check.noise, np.random.default_rng(seed))
        randomisation = sample_randomisation(check.randomise, seed, env.RANDOMISES)
        rows, _, success = rollout(env, check.task, seed, expert, randomisation)
        successes += success
        lengths.append(len(rows))
    return ExpertRow(
        task_id=check.task.task_id, family=check.task.family, split=check.task.split, episodes=check.episodes,
        successes=successes, mean_length=float(np.mean(lengths)), noise=check.noise,
        randomised=check.randomise.enabled, command=check.command, measured_on=datetime.date.today().isoformat(),
    )


def measure_experts(tasks: list[TaskRecord], episodes: int, noise: float, randomise: RandomiseConfig, workers: int,
                    command: str, progress: Callable[[ExpertRow], None] | None = None) -> list[ExpertRow]:
    """Every task's expert row, in the order of `tasks`; `progress` sees each row as its worker returns it."""
    checks = [ExpertCheck(task=t, episodes=episodes, noise=noise, randomise=randomise, command=command) for t in tasks]
    rows = []
    for _, row, _ in run_in_pool(check_expert, checks, workers, label=lambda check: check.task.task_id):
        rows.append(row)
        if progress:
            progress(row)
    order = {t.task_id: i for i, t in enumerate(tasks)}
    return sorted(rows, key=lambda r: order[r.task_id])


def checks_experts(weak_experts: str, randomise: RandomiseConfig) -> bool:
    """Whether a campaign measures its experts under its own randomisation: it leaves weak ones out
    (tasks.weak_experts: skip) and an expert feels its randomisation apart from the shipped table's."""
    return weak_experts == "skip" and bool(felt_apart(randomise))


def felt_apart(randomise: RandomiseConfig) -> dict[str, object]:
    """The randomisation an expert feels, where it is not the shipped table's (the default's): field -> value,
    {} where the shipped table holds (light, camera, tint and colour alone apart: the expert sees none of them)."""
    if not randomise.enabled:
        return {"enabled": False}
    default = RandomiseConfig()
    return {name: getattr(randomise, name) for name in FELT if getattr(randomise, name) != getattr(default, name)}


def said(apart: dict[str, object]) -> str:
    """`{"mass": (100.0, 100.0)}` -> 'randomise.mass=[100.0, 100.0]'."""
    return ", ".join(f"randomise.{name}={list(value) if isinstance(value, tuple) else str(value).lower()}"
                     for name, value in apart.items())


def check_key(task: TaskRecord, randomise: RandomiseConfig) -> str:
    """One task's check under the felt randomisation: keyed by what the environment and its expert read of the task
    (a spec edited is measured again; another seed's wordings or split are not) and of the randomisation."""
    felt = {"enabled": False} if not randomise.enabled else {name: getattr(randomise, name) for name in FELT}
    conditions = {"randomise": felt, "episodes": EPISODES, "noise": NOISE}
    return unit_key("expert_check", VERSION, conditions,
                    [task.model_dump_json(include={"task_id", "spec", "family", "env_name", "object_colours", "horizon"})])


def experts_under(workspace: Workspace, tasks: list[TaskRecord], randomise: RandomiseConfig, workers: int,
                  measure: bool, progress: Callable[[ExpertRow], None] | None = None) -> dict[str, ExpertRow]:
    """task_id -> its expert's row under `randomise`: those this workspace holds, and with `measure` the others
    measured now, each written as its worker returns it (a kill loses only the tasks in flight).

    Args:
        workspace: where the rows are cached (Workspace.expert_check).
        tasks: the tasks to know.
        randomise: the campaign's randomisation (FELT fields matter).
        workers: worker processes for the measurement.
        measure: False reads the cache alone (a task never measured has no row).
        progress: sees each row measured now.
    """
    rows = {}
    for task in tasks:
        path = workspace.expert_check(check_key(task, randomise))
        if path.is_file():
            rows[task.task_id] = ExpertRow.model_validate_json(path.read_text())
    missing = [t for t in tasks if t.task_id not in rows]
    if not (measure and missing):
        return rows
    by_id = {t.task_id: t for t in missing}
    bar = Progress(log, "experts under the campaign's randomisation", len(missing), "tasks", "episodes")

    def keep(row: ExpertRow) -> None:
        write_text_atomically(workspace.expert_check(check_key(by_id[row.task_id], randomise)), row.model_dump_json())
        rows[row.task_id] = row
        bar.advance(1, row.episodes)
        if progress:
            progress(row)

    command = f"a campaign's check under {said(felt_apart(randomise)) or 'the default randomisation'}"
    try:
        measure_experts(missing, EPISODES, NOISE, randomise, workers, command, keep)
    finally:
        bar.close()
    return rows
