"""How well each task's scripted expert does, measured in worker processes without a camera,
under the campaign's domain randomisation; and the docs table made from the record
(schemas.experts) that decides which tasks campaigns may use (target: >= 90% per task)."""

from __future__ import annotations

import datetime

import numpy as np
from pydantic import BaseModel

from envs.pool import run_in_pool
from envs.rollout import rollout, worker_env
from schemas.config import RandomiseConfig
from schemas.experts import TARGET, ExpertRow, ExpertTable
from schemas.keys import derive_seed
from schemas.tasks import TaskRecord


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
                    command: str, progress=None) -> list[ExpertRow]:
    checks = [ExpertCheck(task=t, episodes=episodes, noise=noise, randomise=randomise, command=command) for t in tasks]
    rows = []
    for _, row, _ in run_in_pool(check_expert, checks, workers):
        rows.append(row)
        if progress:
            progress(row)
    order = {t.task_id: i for i, t in enumerate(tasks)}
    return sorted(rows, key=lambda r: order[r.task_id])


def markdown(table: ExpertTable, suite_order: list[str], record: str) -> str:
    rows = sorted(table.rows.values(), key=lambda r: (r.task_id not in suite_order,
                                                       suite_order.index(r.task_id) if r.task_id in suite_order else 0,
                                                       r.task_id))
    below = [r for r in rows if r.below_target]
    made_by = sorted({(r.command, r.measured_on, r.noise, r.randomised) for r in rows})
    lines = ["# Scripted expert success per task", ""]
    for command, day, noise, randomised in made_by:
        conditions = "the default domain randomisation" if randomised else "no domain randomisation"
        lines.append(f"- `{command}` on {day}: expert action noise σ={noise}, {conditions}")
    lines += [
        "",
        f"Episode seeds are derived per task. Target: ≥{TARGET:.0%}; {len(below)} of {len(rows)} tasks are below "
        "it, flagged here, and left out of campaigns unless a config sets `tasks.weak_experts: keep`. "
        f"The record behind this page is `{record}`.",
        "",
        "| task | family | split | success | episodes | mean length | flag |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        flag = "below target" if r.below_target else ""
        lines.append(f"| {r.task_id} | {r.family} | {r.split} | {r.success_rate:.0%} | {r.episodes} | "
                     f"{r.mean_length:.0f} | {flag} |")
    return "\n".join(lines) + "\n"
