"""evaluate: roll the trained policy out on every task, seen and unseen, said canonically; and
on each seen task said with a held-out paraphrase (split `unseen_paraphrase`). Success per
(task, instruction) goes to the warehouse `evaluations` table, with a GIF of the first episode."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from pydantic import BaseModel

from schemas.config import CampaignConfig, RandomiseConfig, RenderConfig
from schemas.keys import derive_seed, unit_key
from schemas.tasks import UNSEEN_PARAPHRASE, TaskRecord
from schemas.workspace import Workspace
from stages.explore import rollout, worker_env
from stages.pool import Progress, run_in_pool
from warehouse.catalog import Catalog

STAGE, VERSION = "evaluate", 1
log = logging.getLogger("sim2act.stages.evaluate")


class EvalUnit(BaseModel):
    unit_key: str
    task: TaskRecord
    split: str
    instruction: str
    render: RenderConfig
    randomise: RandomiseConfig
    checkpoint: str
    seeds: list[int]
    embedding: list[float]  # of the instruction
    gif_path: str | None


class TaskEvaluation(BaseModel):
    task_id: str
    split: str
    instruction: str
    episodes: int
    successes: int
    mean_return: float
    mean_length: float
    media_path: str | None

    @property
    def success_rate(self) -> float:
        return self.successes / self.episodes


class EvaluateResult(BaseModel):
    model_key: str
    tasks: list[TaskEvaluation]
    skipped_units: int


def evaluate_unit(unit: EvalUnit) -> TaskEvaluation:
    """Worker: the policy's mean action, episodes until success or the horizon."""
    import imageio.v3 as iio

    from envs.randomisation import sample_randomisation
    from policies.policy import Policy

    policy = Policy.load(Path(unit.checkpoint))
    env = worker_env(unit.task, unit.render)
    embedding = np.asarray(unit.embedding, dtype=np.float32)
    successes, returns, lengths = 0, [], []
    for index, seed in enumerate(unit.seeds):
        rows, final_image, success = rollout(
            env, unit.task, seed, lambda obs: policy.act(obs.image, obs.proprio, embedding),
            sample_randomisation(unit.randomise, seed, env.RANDOMISES),
        )
        successes += success
        returns.append(sum(r["reward"] for r in rows))
        lengths.append(len(rows))
        if index == 0 and unit.gif_path:
            frames = np.stack([r["image"] for r in rows] + [final_image])
            Path(unit.gif_path).parent.mkdir(parents=True, exist_ok=True)
            tmp = Path(unit.gif_path + ".tmp.gif")
            iio.imwrite(tmp, frames, duration=50, loop=0)
            tmp.replace(unit.gif_path)
    return TaskEvaluation(
        task_id=unit.task.task_id, split=unit.split, instruction=unit.instruction, episodes=len(unit.seeds),
        successes=successes, mean_return=float(np.mean(returns)), mean_length=float(np.mean(lengths)),
        media_path=unit.gif_path,
    )


def evaluation_cases(tasks: list[TaskRecord]) -> list[tuple[TaskRecord, str, str]]:
    """(task, split, instruction): every task said canonically, and every seen task that has
    held-out paraphrases said with the first of them (same seeds, so only the words differ)."""
    cases = [(task, task.split, task.instruction) for task in tasks]
    cases += [(task, UNSEEN_PARAPHRASE, task.unseen_instructions[0])
              for task in tasks if task.split == "seen" and task.unseen_instructions]
    return cases


def run_evaluate(
    workspace: Workspace,
    config: CampaignConfig,
    iteration: int,
    model_key: str,
    checkpoint: str,
    tasks: list[TaskRecord],
    embeddings: dict[str, np.ndarray],
) -> EvaluateResult:
    catalog = Catalog(workspace.catalog)
    units = []
    reads = {"evaluate": config.evaluate.model_dump(exclude={"workers"}), "render": config.render,
             "randomise": config.randomise}
    for task, split, instruction in evaluation_cases(tasks):
        key = unit_key(STAGE, VERSION, reads, [model_key, task.model_dump_json(), instruction])
        seeds = [derive_seed(config.name, config.seed, "evaluate", task.task_id, e)
                 for e in range(config.evaluate.episodes_per_task)]
        gif = str(workspace.media / f"{key}.gif") if config.evaluate.gif else None
        units.append(EvalUnit(unit_key=key, task=task, split=split, instruction=instruction, render=config.render,
                              randomise=config.randomise, checkpoint=checkpoint, seeds=seeds,
                              embedding=embeddings[instruction].tolist(), gif_path=gif))
    done = catalog.registered_keys([u.unit_key for u in units])
    todo = [u for u in units if u.unit_key not in done]
    log.info("evaluate it%d: %d tasks (%d already evaluated), %d episodes each",
             iteration, len(units), len(done), config.evaluate.episodes_per_task)
    progress = Progress(log, f"evaluate it{iteration}", len(todo), "tasks", "episodes")
    try:
        for unit, result, seconds in run_in_pool(evaluate_unit, todo, config.evaluate.workers, lambda u: u.task.task_id):
            row = {
                "unit_key": unit.unit_key, "campaign": config.name, "iteration": iteration, "model_key": model_key,
                **result.model_dump(), "success_rate": result.success_rate,
            }
            catalog.register_unit(unit_key=unit.unit_key, stage=STAGE, campaign=config.name, iteration=iteration,
                                  summary=result.model_dump(), wall_s=seconds, rows={"evaluations": [row]})
            progress.advance(1, result.episodes)
            log.info("evaluate it%d: %s (%s, %r) success %d/%d", iteration, result.task_id, result.split,
                     result.instruction, result.successes, result.episodes)
    finally:
        progress.close()
    rows = catalog.query(
        "SELECT task_id, split, instruction, episodes, successes, mean_return, mean_length, media_path "
        "FROM evaluations WHERE list_contains(?, unit_key) ORDER BY task_id, split",
        [[u.unit_key for u in units]],
    )
    evaluations = [
        TaskEvaluation(task_id=r[0], split=r[1], instruction=r[2], episodes=r[3], successes=r[4], mean_return=r[5],
                       mean_length=r[6], media_path=r[7])
        for r in rows
    ]
    return EvaluateResult(model_key=model_key, tasks=evaluations, skipped_units=len(done))
