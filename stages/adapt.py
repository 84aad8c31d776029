"""adapt: how many episodes of a shifted domain a Sim2Act model needs, against a model from scratch.

The shifted domain stands in for the proposal's real-robot transfer: the campaign's seen tasks
under `adapt.domain`, a randomisation outside what the campaign trained on (other light, scene
colours, camera pose, object size, mass and friction). It runs as its own campaign,
`<name>-adapt`, in the same workspace and with the same stages: the noisy expert explores every
seen task (or `adapt.tasks`) `max(adapt.episodes_per_task)` times in the shifted domain; for each n
in `adapt.episodes_per_task` models train on the first n episodes of every task, starting from the
source model (`train.init_from`) and from scratch, `adapt.seeds` trainings each (train.seed 0..),
`adapt.train_steps` steps each; every model, and the source model as it is (n = 0), is evaluated on
those tasks in the shifted domain. Every training and evaluation is a unit: a re-run does only
what is missing."""

from __future__ import annotations

import logging
import time
from typing import Literal

from pydantic import BaseModel

from envs.pool import keep_workers
from schemas.config import AdaptConfig, BaselinesConfig, CampaignConfig, ConfigError, RandomiseConfig
from schemas.keys import key_fields, unit_key
from schemas.tasks import TaskRecord
from schemas.workspace import Workspace
from stages import StageResult, StageUnits, UnitOutput
from stages.evaluate import Agent, TaskEvaluation, evaluate_model, evaluation_cases
from stages.explore import run_explore
from stages.filter import run_filter
from stages.generate_tasks import campaign_tasks, run_generate_tasks
from warehouse.catalog import Catalog
from warehouse.tasks import load_embeddings, load_tasks

STAGE, VERSION = "adapt", 1
LEGACY_VALUES = {"tasks": [], "seeds": 1}  # fields added since version 1, at the values that did what it did
SUITE = "adapt"
Start = Literal["source", "fine-tuned", "scratch"]
log = logging.getLogger("sim2act.stages.adapt")


class AdaptPoint(BaseModel):
    start: Start  # source: the source model as it is, at 0 episodes
    episodes_per_task: int
    episodes: int  # target-domain episodes its training saw, over all tasks
    model_key: str
    successes: int
    trials: int
    seed: int = 0  # train.seed of its training (adapt.seeds); the source model's: 0

    @property
    def success_rate(self) -> float:
        return self.successes / self.trials


class AdaptResult(StageResult):
    """Registered as the target campaign's `adapt` unit: what `sim2act report` tabulates."""

    campaign: str
    source_model: str
    domain: RandomiseConfig
    target_success: float
    points: list[AdaptPoint]
    tasks: list[str] = []  # the task ids adapted on (results registered before adapt.tasks: every seen task)

    def did_work(self) -> bool:  # its parts are the other stages' units
        return True

    def metrics(self) -> dict[str, float]:
        """adapt.<start>.success.<episodes>: success in the shifted domain after that many target
        episodes, the training seeds' episodes pooled."""
        return {f"adapt.{start}.success.{episodes}": successes / trials
                for (episodes, start), seeds in pooled(self.points).items() for successes, trials in [pooled_score(seeds)]}


def target_campaign(config: CampaignConfig) -> CampaignConfig:
    """The shifted domain's campaign: the same tasks, render and model, one iteration of the expert
    exploring as many episodes as the largest training takes, no baselines. What the source campaign's
    explore and evaluate settings would change about that is reset: a smaller first iteration
    (first_episodes_per_task: the largest trainings would get fewer episodes than they count), a curriculum
    (it skips tasks with sub-goals when no policy explores), a VLM explorer, relabelling, and a split-wide
    episode count (each task gets adapt.eval_episodes)."""
    adapt = config.adapt
    return config.model_copy(update={
        "name": f"{config.name}-adapt", "iterations": 1, "randomise": adapt.domain,
        "explore": config.explore.model_copy(update={
            "episodes_per_task": max(adapt.episodes_per_task), "first_episodes_per_task": None, "curriculum": False,
            "vlm": None, "relabel": False}),
        "evaluate": config.evaluate.model_copy(update={"episodes_per_task": adapt.eval_episodes,
                                                       "episodes_per_split": None}),
        "baselines": BaselinesConfig(), "adapt": AdaptConfig(),
    })


def first_episodes(campaign: str, per_task: int) -> str:
    """train.where: the steps of each task's first `per_task` explored episodes (by their index,
    the episode id's `-eNNN` suffix); a rejected episode is not replaced."""
    return (f"episode_id IN (SELECT episode_id FROM episodes WHERE campaign = '{campaign}' "
            f"AND CAST(regexp_extract(episode_id, '-e([0-9]+)$', 1) AS INTEGER) < {per_task})")


def pooled(points: list[AdaptPoint]) -> dict[tuple[int, Start], list[AdaptPoint]]:
    """(episodes, start) -> its points, one per training seed."""
    grouped: dict[tuple[int, Start], list[AdaptPoint]] = {}
    for point in points:
        grouped.setdefault((point.episodes, point.start), []).append(point)
    return grouped


def pooled_score(seeds: list[AdaptPoint]) -> tuple[int, int]:
    """(successes, trials) of a point's training seeds together."""
    return sum(p.successes for p in seeds), sum(p.trials for p in seeds)


def episodes_to_reach(points: list[AdaptPoint], start: Start, success: float) -> int | None:
    """The fewest target-domain episodes with which `start`'s models reached `success`, their seeds'
    episodes pooled (fine-tuning from no episodes is the source model as it is); None: never."""
    counted = {start, "source"} if start == "fine-tuned" else {start}
    reached = []
    for (episodes, at), seeds in pooled(points).items():
        successes, trials = pooled_score(seeds)
        if at in counted and successes >= success * trials:
            reached.append(episodes)
    return min(reached, default=None)


def points_of_family(points: list[AdaptPoint], scores: dict[str, tuple[int, int]], tasks: int) -> list[AdaptPoint]:
    """The points scored on one family's tasks alone: `scores` maps a model key to its successes and
    episodes on those `tasks` (its rows in `evaluations`); each point counts the target-domain episodes
    of those tasks only. A point whose model has no rows there is left out."""
    return [point.model_copy(update={"successes": scores[point.model_key][0], "trials": scores[point.model_key][1],
                                     "episodes": point.episodes_per_task * tasks})
            for point in points if point.model_key in scores]


def adapted_tasks(config: CampaignConfig, tasks: list[TaskRecord]) -> list[TaskRecord]:
    """The campaign's seen tasks the adaptation runs on: `adapt.tasks`, or every seen one.

    Raises:
        ConfigError: an id in `adapt.tasks` that is not one of the campaign's seen tasks."""
    seen = [task for task in tasks if task.split == "seen"]
    wanted = set(config.adapt.tasks)
    if not wanted:
        return seen
    unknown = sorted(wanted - {task.task_id for task in seen})
    if unknown:
        raise ConfigError(f"adapt.tasks: expected task ids of the campaign's seen tasks (`sim2act tasks` lists them), "
                          f"got {', '.join(unknown)}")
    return [task for task in seen if task.task_id in wanted]


def _score(evaluations: list[TaskEvaluation]) -> tuple[int, int]:
    return sum(e.successes for e in evaluations), sum(e.episodes for e in evaluations)


@keep_workers()  # its explore and five evaluations on one pool of workers
def run_adapt(workspace: Workspace, config: CampaignConfig, source_model: str, source_checkpoint: str) -> AdaptResult:
    """The shifted domain's campaign (target_campaign) runs its own stages, each with its units, then
    fine-tuned and from-scratch models are trained and evaluated per `adapt.episodes_per_task`.

    Unit of work: the adaptation's summary, keyed by the adapt settings, the source model and the
    target dataset (its parts are the other stages' units). Registers an `adapt` unit holding the result."""
    # torch comes with these: here, so `sim2act report` reads an adaptation's results without it
    from stages.index import run_index
    from stages.train import run_train

    catalog = Catalog(workspace.catalog)
    started = time.monotonic()
    target = target_campaign(config)
    # the source campaign's tasks (its own randomisation's weak experts left out): the shifted domain's filter keeps
    # only the episodes its experts finish
    tasks_key = run_generate_tasks(workspace, target, campaign_tasks(workspace, config)[0]).unit_key
    tasks = adapted_tasks(config, load_tasks(workspace, tasks_key))
    embeddings = load_embeddings(workspace, tasks_key, target.train.model.language_encoder)
    explored = run_explore(workspace, target, 0, tasks, None, embeddings)
    filtered = run_filter(workspace, target, 0, explored.unit_keys)
    dataset = run_index(workspace, target, 0, explored.unit_keys, filtered.unit_keys, None)
    cases = [case for case in evaluation_cases(tasks) if case[1] == "seen"]
    seen = len(cases)

    def evaluate(start: Start, per_task: int, model_key: str, checkpoint: str, seed: int = 0) -> AdaptPoint:
        evaluations, _ = evaluate_model(workspace, target, 0, model_key, Agent(kind="sim2act", path=checkpoint),
                                        cases, embeddings, suite=SUITE)
        successes, trials = _score(evaluations)
        log.info("adapt: %s, %d episode(s) per task, seed %d: success %d/%d", start, per_task, seed, successes, trials)
        return AdaptPoint(start=start, episodes_per_task=per_task, episodes=per_task * seen, model_key=model_key,
                          successes=successes, trials=trials, seed=seed)

    points = [evaluate("source", 0, source_model, source_checkpoint)]
    for per_task in sorted(set(config.adapt.episodes_per_task)):
        where = first_episodes(target.name, per_task)
        for start in ("fine-tuned", "scratch"):
            for seed in range(config.adapt.seeds):
                train = target.train.model_copy(update={
                    "where": where, "steps": config.adapt.train_steps, "seed": seed,
                    "init_from": source_model if start == "fine-tuned" else None})
                model = run_train(workspace, target.model_copy(update={"train": train}), 0, dataset, tasks_key, embeddings)
                points.append(evaluate(start, per_task, model.model_key, model.checkpoint, seed))
    result = AdaptResult(campaign=target.name, source_model=source_model, domain=target.randomise,
                         target_success=config.adapt.target_success, points=points,
                         tasks=[task.task_id for task in tasks])
    key = unit_key(STAGE, VERSION, {"adapt": key_fields(config.adapt, set(), LEGACY_VALUES)}, [source_model, dataset.unit_key])
    units = StageUnits(catalog, STAGE, target.name, 0)
    if units.pending([key]):  # its parts are units of their own: only the summary is registered here
        units.register(key, UnitOutput(result.model_dump(mode="json")), time.monotonic() - started)
    return result


def adapt_results(catalog: Catalog, campaign: str) -> list[AdaptResult]:
    """The adaptations registered for `campaign` (its `-adapt` campaign's), oldest first."""
    return [AdaptResult.model_validate_json(summary) for (summary,) in catalog.query(
        "SELECT summary FROM stage_runs WHERE stage = ? AND campaign = ? ORDER BY finished_at", [STAGE, f"{campaign}-adapt"])]
