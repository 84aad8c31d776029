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

STAGE, VERSION = "evaluate", 2
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
    uncertainty: float  # the policy's, per step, averaged over the episodes (policies.model.uncertainty)
    media_path: str | None

    @property
    def success_rate(self) -> float:
        return self.successes / self.episodes


class Promotion(BaseModel):
    """The evaluation's decision on the registry alias: the alias moves only when this says so."""

    promote: bool
    reason: str
    success: float  # mean success of the new model over the evaluation cases
    champion_success: float | None  # the current champion's over the same cases; None without one


class EvaluateResult(BaseModel):
    model_key: str
    tasks: list[TaskEvaluation]
    skipped_units: int
    promotion: Promotion


def decide_promotion(catalog: Catalog, campaign: str, model_key: str, evaluations: list[TaskEvaluation]) -> Promotion:
    """Promote when there is no champion, or when the new model's mean success over every
    evaluation case (seen, unseen, held-out paraphrases; same seeds) beats the champion's."""
    success = float(np.mean([t.success_rate for t in evaluations]))
    champion = catalog.query(
        "SELECT champion_model_key FROM deployments WHERE campaign = ? AND model_key <> ? "
        "ORDER BY iteration DESC LIMIT 1", [campaign, model_key],
    )
    if not champion:
        return Promotion(promote=True, reason="no champion yet", success=success, champion_success=None)
    rows = dict(
        ((task_id, split), rate) for task_id, split, rate in catalog.query(
            "SELECT task_id, split, success_rate FROM evaluations WHERE model_key = ?", [champion[0][0]])
    )
    shared = [t for t in evaluations if (t.task_id, t.split) in rows]
    if not shared:
        return Promotion(promote=True, reason="the champion was never evaluated on these tasks", success=success,
                         champion_success=None)
    success = float(np.mean([t.success_rate for t in shared]))
    before = float(np.mean([rows[(t.task_id, t.split)] for t in shared]))
    better = success > before
    reason = f"success {success:.0%} {'beats' if better else 'does not beat'} the champion's {before:.0%} on {len(shared)} cases"
    return Promotion(promote=better, reason=reason, success=success, champion_success=before)


def evaluate_unit(unit: EvalUnit) -> TaskEvaluation:
    """Worker: the policy's mean (or most likely) action, episodes until success or the horizon;
    its uncertainty at every step."""
    import imageio.v3 as iio

    from envs.randomisation import sample_randomisation
    from policies.policy import Policy

    policy = Policy.load(Path(unit.checkpoint), {unit.instruction: np.asarray(unit.embedding, dtype=np.float32)})
    env = worker_env(unit.task, unit.render)
    successes, returns, lengths, uncertainties = 0, [], [], []

    def act(obs):
        decision = policy.act(obs, unit.instruction, unit.task.family)
        uncertainties.append(decision.uncertainty)
        return decision.action

    for index, seed in enumerate(unit.seeds):
        rows, final, success = rollout(
            env, unit.task, seed, act, sample_randomisation(unit.randomise, seed, env.RANDOMISES),
        )
        successes += success
        returns.append(sum(r["reward"] for r in rows))
        lengths.append(len(rows))
        if index == 0 and unit.gif_path:
            frames = np.stack([r["image"] for r in rows] + [final.image])
            Path(unit.gif_path).parent.mkdir(parents=True, exist_ok=True)
            tmp = Path(unit.gif_path + ".tmp.gif")
            iio.imwrite(tmp, frames, duration=50, loop=0)
            tmp.replace(unit.gif_path)
    return TaskEvaluation(
        task_id=unit.task.task_id, split=unit.split, instruction=unit.instruction, episodes=len(unit.seeds),
        successes=successes, mean_return=float(np.mean(returns)), mean_length=float(np.mean(lengths)),
        uncertainty=float(np.mean(uncertainties)), media_path=unit.gif_path,
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
        "SELECT task_id, split, instruction, episodes, successes, mean_return, mean_length, uncertainty, media_path "
        "FROM evaluations WHERE list_contains(?, unit_key) ORDER BY task_id, split",
        [[u.unit_key for u in units]],
    )
    evaluations = [
        TaskEvaluation(task_id=r[0], split=r[1], instruction=r[2], episodes=r[3], successes=r[4], mean_return=r[5],
                       mean_length=r[6], uncertainty=r[7], media_path=r[8])
        for r in rows
    ]
    promotion = decide_promotion(catalog, config.name, model_key, evaluations)
    log.info("evaluate it%d: %s: %s", iteration, "promote" if promotion.promote else "keep the champion", promotion.reason)
    return EvaluateResult(model_key=model_key, tasks=evaluations, skipped_units=len(done), promotion=promotion)
