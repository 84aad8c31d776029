"""The bootstrap flow: one Prefect flow run per iteration, each chaining the stages as tasks.

Composition only. Tasks pass keys and paths; each stage skips the units already registered in
the warehouse catalog, so re-running a finished campaign does no work and a killed one resumes.
"""

from __future__ import annotations

import logging
import time
from typing import get_args

from prefect import flow, task
from prefect.artifacts import create_progress_artifact, update_progress_artifact
from prefect.cache_policies import NO_CACHE
from pydantic import BaseModel

from flows.artifacts import iteration_markdown, publish_iteration_artifacts
from flows.rollouts import as_prefect_tasks, rollout_task_runner
from flows.run_lock import exclusive_run
from flows.tracking import Tracking
from schemas.config import CampaignConfig
from schemas.tasks import UNSEEN_PARAPHRASE, Split
from schemas.wordings import HELD_OUT_WORDING
from schemas.workspace import Workspace
from stages.adapt import AdaptResult, run_adapt
from stages.baselines import BaselinesResult, run_baselines
from stages.evaluate import EvaluateResult, group_success, run_evaluate
from stages.explore import ExploreResult, PolicyExplorer, run_explore
from stages.filter import FilterResult, run_filter
from stages.generate_tasks import TasksResult, load_embeddings, load_tasks, run_generate_tasks
from stages.index import IndexResult, run_index
from stages.redeploy import RedeployResult, finished_iterations, run_redeploy
from stages.report import plot_success_by_iteration, success_by_iteration
from stages.train import TrainResult, run_train
from warehouse.catalog import Catalog

log = logging.getLogger("sim2act.flows")
# Prefect sends the "sim2act" loggers to the API (PREFECT_LOGGING_EXTRA_LOGGERS); they reach the
# console through the root handler, which passes what the logger lets through.
logging.getLogger("sim2act").setLevel(logging.INFO)
# The catalog, not Prefect's result cache, decides what is done: one source of truth.
stage_task = task(cache_policy=NO_CACHE, persist_result=False)
SPLITS = (*get_args(Split), UNSEEN_PARAPHRASE, HELD_OUT_WORDING)


class IterationOutcome(BaseModel):
    iteration: int
    tasks_key: str
    dataset: IndexResult
    model_key: str
    champion: PolicyExplorer
    success: dict[str, float]  # task_id -> success rate, said canonically
    split_success: dict[str, float]  # seen / unseen / unseen_paraphrase -> mean over its tasks
    stages_run: int  # how many stages did any work; 0 on a finished re-run


def _split_success(evaluation: EvaluateResult) -> dict[str, float]:
    return {g.group: g.success_rate for g in group_success(evaluation.tasks) if g.group in SPLITS}


@stage_task(name="generate_tasks")
def generate_tasks_task(workspace: str, config: CampaignConfig) -> TasksResult:
    return run_generate_tasks(Workspace.at(workspace), config)


@flow(name="explore", flow_run_name="{config.name}-explore-{iteration}")
def explore_flow(
    workspace: str, config: CampaignConfig, iteration: int, tasks_key: str, explorer: PolicyExplorer | None
) -> ExploreResult:
    """A subflow: its task runner (local workers or Dask) is chosen by the caller."""
    ws = Workspace.at(workspace)
    embeddings = load_embeddings(ws, tasks_key, config.train.model.language_encoder)
    artifact = create_progress_artifact(0.0, description=f"explore {config.name} iteration {iteration}: episodes done")
    return run_explore(
        ws, config, iteration, load_tasks(ws, tasks_key), explorer, embeddings,
        execute=as_prefect_tasks(config.explore),
        on_progress=lambda fraction: update_progress_artifact(artifact, 100.0 * fraction),
    )


@stage_task(name="filter")
def filter_task(workspace: str, config: CampaignConfig, iteration: int, explore_keys: list[str]) -> FilterResult:
    return run_filter(Workspace.at(workspace), config, iteration, explore_keys)


@stage_task(name="index")
def index_task(
    workspace: str, config: CampaignConfig, iteration: int, explore_keys: list[str], filter_keys: list[str],
    previous: IndexResult | None,
) -> IndexResult:
    return run_index(Workspace.at(workspace), config, iteration, explore_keys, filter_keys, previous)


@stage_task(name="train")
def train_task(
    workspace: str, config: CampaignConfig, iteration: int, dataset: IndexResult, tasks_key: str, mlflow_run_id: str
) -> TrainResult:
    ws = Workspace.at(workspace)
    embeddings = load_embeddings(ws, tasks_key, config.train.model.language_encoder)
    return run_train(ws, config, iteration, dataset, tasks_key, embeddings,
                     on_metrics=Tracking(ws, config).step_logger(mlflow_run_id, "train."))


@stage_task(name="evaluate")
def evaluate_task(
    workspace: str, config: CampaignConfig, iteration: int, model: TrainResult, tasks_key: str
) -> EvaluateResult:
    ws = Workspace.at(workspace)
    embeddings = load_embeddings(ws, tasks_key, config.train.model.language_encoder)
    return run_evaluate(ws, config, iteration, model.model_key, model.checkpoint, load_tasks(ws, tasks_key), embeddings)


@stage_task(name="baselines")
def baselines_task(workspace: str, config: CampaignConfig, iteration: int, tasks_key: str,
                   explore_units: list[str]) -> BaselinesResult:
    ws = Workspace.at(workspace)
    embeddings = load_embeddings(ws, tasks_key, config.train.model.language_encoder)
    return run_baselines(ws, config, iteration, tasks_key, load_tasks(ws, tasks_key), embeddings, explore_units)


@stage_task(name="adapt")
def adapt_task(workspace: str, config: CampaignConfig, source: PolicyExplorer) -> AdaptResult:
    return run_adapt(Workspace.at(workspace), config, source.model_key, source.checkpoint)


def _adapt_metrics(result: AdaptResult) -> dict[str, float]:
    """adapt.<start>.success.<episodes>: success in the shifted domain after that many target episodes."""
    return {f"adapt.{p.start}.success.{p.episodes}": p.success_rate for p in result.points}


def _baseline_metrics(result: BaselinesResult) -> dict[str, float]:
    """baseline.<agent>[.<family>].success.<split>, for the campaign run beside its own success.<split>."""
    return {f"baseline.{b.agent}{'.' + b.family if b.family else ''}.success.{g.group}": g.success_rate
            for b in result.baselines for g in group_success(b.evaluations) if g.group in SPLITS}


@stage_task(name="redeploy")
def redeploy_task(
    workspace: str, config: CampaignConfig, iteration: int, model: TrainResult, mlflow_run_id: str,
    evaluation: EvaluateResult,
) -> RedeployResult:
    return run_redeploy(Workspace.at(workspace), config, iteration, model.model_key, model.checkpoint, mlflow_run_id,
                        evaluation.promotion)


def _log_stage(tracking: Tracking, run_id: str, stage: str, result: BaseModel) -> None:
    """Log what a stage did, right after it, and only when it did work (a re-run adds no points)."""
    if stage == "generate_tasks" and not result.skipped:
        tracking.log_metrics(run_id, {"tasks.count": len(result.task_ids), "tasks.proposals_valid": result.proposals_valid,
                                      **{f"tasks.proposals_rejected.{k}": v for k, v in result.proposals_rejected.items()}})
    elif stage == "explore" and result.episodes:
        tracking.log_metrics(run_id, {"explore.episodes": result.episodes, "explore.triplets": result.steps,
                                      **{f"explore.episodes.{p.task_id}": p.episodes for p in result.priorities},
                                      **{f"explore.priority.{p.task_id}": p.score for p in result.priorities}})
    elif stage == "filter" and result.reasons:
        total = sum(result.reasons.values())
        tracking.log_metrics(
            run_id,
            {"filter.pass_rate": result.reasons.get("kept", 0) / total,
             **{f"filter.{reason}": count for reason, count in result.reasons.items()}},
        )
    elif stage == "index" and not result.skipped:
        tracking.log_metrics(run_id, {f"dataset.{k}": getattr(result, k) for k in ("episodes", "kept_episodes", "triplets")})
        tracking.set_tags(run_id, {"sim2act.dataset_digest": result.dataset_digest})
    elif stage == "train" and not result.skipped:  # its losses, lr and samples/s went to the run as it trained
        tracking.log_training_dataset(run_id, result.dataset_digest, result.dataset_shards, result.samples)
    elif stage == "evaluate" and result.skipped_units < len(result.tasks):
        tracking.log_evaluation(run_id, result.tasks)


@flow(name="bootstrap-iteration", flow_run_name="{config.name}-iteration-{iteration}")
def iteration_flow(
    config: CampaignConfig,
    iteration: int,
    workspace: str,
    campaign_run_id: str,
    previous: IndexResult | None = None,
    explorer: PolicyExplorer | None = None,
) -> IterationOutcome:
    tracking = Tracking(Workspace.at(workspace), config)
    run_id = tracking.iteration_run(campaign_run_id, iteration)
    tasks = generate_tasks_task(workspace, config)
    _log_stage(tracking, run_id, "generate_tasks", tasks)
    explore = explore_flow.with_options(task_runner=rollout_task_runner(config.explore))(
        workspace, config, iteration, tasks.unit_key, explorer
    )
    _log_stage(tracking, run_id, "explore", explore)
    filtered = filter_task(workspace, config, iteration, explore.unit_keys)
    _log_stage(tracking, run_id, "filter", filtered)
    index = index_task(workspace, config, iteration, explore.unit_keys, filtered.unit_keys, previous)
    _log_stage(tracking, run_id, "index", index)
    model = train_task(workspace, config, iteration, index, tasks.unit_key, run_id)
    _log_stage(tracking, run_id, "train", model)
    evaluation = evaluate_task(workspace, config, iteration, model, tasks.unit_key)
    _log_stage(tracking, run_id, "evaluate", evaluation)
    deployment = redeploy_task(workspace, config, iteration, model, run_id, evaluation)
    tracking.set_tags(run_id, {"sim2act.explorer": explorer.name if explorer else "expert",
                               "sim2act.model_key": model.model_key})
    tracking.finish(run_id)
    publish_iteration_artifacts(
        config.name, iteration,
        iteration_markdown(config.name, iteration, explorer, tasks, explore, filtered, index, model, evaluation,
                           deployment, run_id),
        evaluation, tracking.experiment_id, run_id,
    )
    success = {t.task_id: t.success_rate for t in evaluation.tasks if t.split in get_args(Split)}  # canonical wording
    stages_run = sum([
        not tasks.skipped, explore.skipped_units < len(explore.unit_keys), filtered.skipped_units < len(filtered.unit_keys),
        not index.skipped, not model.skipped, evaluation.skipped_units < len(evaluation.tasks), not deployment.skipped,
    ])
    return IterationOutcome(
        iteration=iteration, tasks_key=tasks.unit_key, dataset=index, model_key=model.model_key,
        champion=deployment.champion, success=success, split_success=_split_success(evaluation), stages_run=stages_run,
    )


@flow(name="bootstrap", flow_run_name="{config.name}")
def bootstrap(
    config: CampaignConfig = CampaignConfig(), workspace: str = "workspace", continue_campaign: bool = False
) -> list[IterationOutcome]:
    """Run a bootstrap campaign: `config.iterations` iterations, each exploring with the last champion.

    Args:
        config: the campaign, as `sim2act run` takes it (preset, file, --set).
        workspace: the folder holding the warehouse, models, MLflow and Prefect state.
        continue_campaign: run one iteration past the campaign's latest finished one (at least
            `config.iterations` in all): what the nightly deployment does.
    """
    ws = Workspace.at(workspace).create()
    with exclusive_run(ws, config.name):  # a second run on the workspace is refused before any work
        return _run_campaign(config, ws, continue_campaign)


def _run_campaign(config: CampaignConfig, ws: Workspace, continue_campaign: bool) -> list[IterationOutcome]:
    started = time.monotonic()
    catalog = Catalog(ws.catalog)
    catalog.initialise()
    if continue_campaign:
        config = config.model_copy(update={"iterations": max(config.iterations, finished_iterations(ws, config.name) + 1)})
        log.info("continuing campaign %s: iterations 0..%d", config.name, config.iterations - 1)
    orphans = catalog.clean_orphans()
    if orphans:
        log.info("removed %d unregistered file(s) left by an interrupted run", len(orphans))
    for path, reason in catalog.verify():
        log.warning("quarantined %s (%s); its unit will be redone", path, reason)
    tracking = Tracking(ws, config)
    campaign_run_id = tracking.campaign_run()
    outcomes: list[IterationOutcome] = []
    previous, explorer = None, None
    for iteration in range(config.iterations):
        outcome = iteration_flow(config, iteration, str(ws.root), campaign_run_id, previous, explorer)
        tracking.log_metrics(
            campaign_run_id, {f"success.{split}": rate for split, rate in outcome.split_success.items()}, step=iteration
        )
        outcomes.append(outcome)
        previous, explorer = outcome.dataset, outcome.champion
    if config.baselines.agents:
        last = outcomes[-1]  # its dataset aggregates every iteration's explore units
        baselines = baselines_task(str(ws.root), config, last.iteration, last.tasks_key, last.dataset.explore_units)
        tracking.log_metrics(campaign_run_id, _baseline_metrics(baselines))
    if config.adapt.episodes_per_task:
        adapted = adapt_task(str(ws.root), config, outcomes[-1].champion)
        tracking.log_metrics(campaign_run_id, _adapt_metrics(adapted))
    plot = plot_success_by_iteration(success_by_iteration(catalog, config.name), list(SPLITS),
                                     f"{config.name}: success per iteration (Wilson 95%)",
                                     ws.media / f"{config.name}-success-by-iteration.png")
    tracking.log_artifact(campaign_run_id, str(plot), "plots")
    tracking.finish(campaign_run_id)
    for outcome in outcomes:
        success = ", ".join(f"{split} {rate:.0%}" for split, rate in outcome.split_success.items())
        log.info(
            "iteration %d: %d triplets in the dataset, success %s, model %s, stages that ran: %d/7",
            outcome.iteration, outcome.dataset.triplets, success, outcome.model_key, outcome.stages_run,
        )
    log.info("campaign %s done in %.1fs; workspace %s", config.name, time.monotonic() - started, ws.root)
    return outcomes
