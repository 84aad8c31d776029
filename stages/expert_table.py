"""How well each task's scripted expert does: the table that decides which tasks a default
campaign may use (target: >= 90% success per task)."""

from __future__ import annotations

import datetime

import numpy as np
from pydantic import BaseModel

from schemas.config import RandomiseConfig
from schemas.keys import derive_seed
from schemas.tasks import TaskRecord
from stages.explore import rollout, worker_env
from stages.pool import run_in_pool

TARGET = 0.9


class ExpertCheck(BaseModel):
    task: TaskRecord
    episodes: int
    noise: float
    randomise: RandomiseConfig


class ExpertRow(BaseModel):
    task_id: str
    family: str
    split: str
    episodes: int
    successes: int
    mean_length: float

    @property
    def success_rate(self) -> float:
        return self.successes / self.episodes


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
    return ExpertRow(task_id=check.task.task_id, family=check.task.family, split=check.task.split,
                     episodes=check.episodes, successes=successes, mean_length=float(np.mean(lengths)))


def measure_experts(tasks: list[TaskRecord], episodes: int, noise: float, randomise: RandomiseConfig, workers: int,
                    progress=None) -> list[ExpertRow]:
    checks = [ExpertCheck(task=t, episodes=episodes, noise=noise, randomise=randomise) for t in tasks]
    rows = []
    for _, row, _ in run_in_pool(check_expert, checks, workers):
        rows.append(row)
        if progress:
            progress(row)
    order = {t.task_id: i for i, t in enumerate(tasks)}
    return sorted(rows, key=lambda r: order[r.task_id])


def markdown(rows: list[ExpertRow], command: str, noise: float, randomised: bool) -> str:
    below = [r for r in rows if r.success_rate < TARGET]
    lines = [
        "# Scripted expert success per task",
        "",
        f"Made by `{command}` on {datetime.date.today().isoformat()}, expert action noise σ={noise}, "
        f"{'the default domain randomisation (RandomiseConfig)' if randomised else 'no domain randomisation'}, "
        f"episode seeds derived per task. Target: ≥{TARGET:.0%}; {len(below)} of {len(rows)} tasks are below "
        "and are flagged here.",
        "",
        "| task | family | split | success | episodes | mean length | flag |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        flag = "below target" if r.success_rate < TARGET else ""
        lines.append(f"| {r.task_id} | {r.family} | {r.split} | {r.success_rate:.0%} | {r.episodes} | "
                     f"{r.mean_length:.0f} | {flag} |")
    return "\n".join(lines) + "\n"

