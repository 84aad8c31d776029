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

from dashboards.protocol import protocol_success
from dashboards.report import plot_success_by_iteration, success_by_iteration
from envs.pool import keep_workers
from flows.artifacts import iteration_markdown, publish_iteration_artifacts
from flows.rollouts import as_prefect_tasks, rollout_task_runner
from flows.run_lock import exclusive_run
from flows.service import log_to_running_stack
from flows.tracking import Tracking
from flows.training_seeds import SeedResult, other_seeds, run_training_seed, with_seed
from schemas.config import CampaignConfig
from schemas.settings import apply_secrets_file
from schemas.tasks import Split
from schemas.workspace import Workspace
from stages.adapt import AdaptResult, run_adapt
from stages.baselines import BaselinesResult, run_baselines
from stages import StageResult
from stages.evaluate import SPLITS, EvaluateResult, group_success, run_evaluate
from stages.explore import ExploreResult, PolicyExplorer, run_explore
from stages.filter import FilterResult, run_filter
from stages.generate_tasks import TasksResult, run_generate_tasks
from stages.index import IndexResult, run_index
from stages.redeploy import RedeployResult, continued, run_redeploy
from stages.train import TrainResult, run_train
from warehouse.catalog import Catalog
from warehouse.tasks import load_embeddings, load_tasks

log = logging.getLogger("sim2act.flows")
DEPLOYMENT_LOCK_WAIT_S = 12 * 3600.0  # a scheduled run waits this long for a run the CLI started
# Prefect sends the "sim2act" loggers to the API (PREFECT_LOGGING_EXTRA_LOGGERS); they reach the
# console through the root handler, which passes what the logger lets through.
logging.getLogger("sim2act").setLevel(logging.INFO)
# The catalog, not Prefect's result cache, decides what is done: one source of truth.
stage_task = task(cache_policy=NO_CACHE, persist_result=False)


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

    def show_progress(fraction: float) -> None:
        # the bar in the UI is for people: a server that fails to store one value (its database restarting,
        # past the client's retries) costs a warning, never the explore
        try:
            update_progress_artifact(artifact, 100.0 * fraction)
        except Exception as exc:  # noqa: BLE001 - any API error; the next update tries again
            log.warning("explore it%d: progress not shown in Prefect (%s)", iteration, type(exc).__name__)

    return run_explore(
        ws, config, iteration, load_tasks(ws, tasks_key), explorer, embeddings,
        execute=as_prefect_tasks(config.explore), on_progress=show_progress,
    )


@stage_task(name="filter")
def filter_task(workspace: str, config: CampaignConfig, iteration: int, explore_keys: list[str],
                earlier_filter_keys: list[str]) -> FilterResult:
    return run_filter(Workspace.at(workspace), config, iteration, explore_keys, earlier_filter_keys)


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
    tracking = Tracking(ws, config)
    embeddings = load_embeddings(ws, tasks_key, config.train.model.language_encoder)
    model = run_train(ws, config, iteration, dataset, tasks_key, embeddings,
                      on_metrics=tracking.step_logger(mlflow_run_id, "train."))
    if not model.skipped:  # its losses, lr and samples/s went to the run as it trained; now the data it read
        tracking.log_training_dataset(mlflow_run_id, model.dataset_digest, model.dataset_shards, model.samples)
    return model


@stage_task(name="evaluate")
def evaluate_task(
    workspace: str, config: CampaignConfig, iteration: int, model: TrainResult, tasks_key: str
) -> EvaluateResult:
    ws = Workspace.at(workspace)
    embeddings = load_embeddings(ws, tasks_key, config.train.model.language_encoder)
    return run_evaluate(ws, config, iteration, model.model_key, model.checkpoint, load_tasks(ws, tasks_key), embeddings)


@stage_task(name="training seed")
def training_seed_task(
    workspace: str, config: CampaignConfig, iteration: int, dataset: IndexResult, tasks_key: str, mlflow_run_id: str
) -> SeedResult:
    ws = Workspace.at(workspace)
    tracking = Tracking(ws, config)
    embeddings = load_embeddings(ws, tasks_key, config.train.model.language_encoder)
    return run_training_seed(ws, config, iteration, dataset, tasks_key, load_tasks(ws, tasks_key), embeddings,
                             on_metrics=tracking.step_logger(mlflow_run_id, f"train.seed{config.train.seed}."))


def _measure_seeds(workspace: str, tracking: Tracking, run_id: str, config: CampaignConfig, iteration: int,
                   dataset: IndexResult, tasks_key: str, evaluation: EvaluateResult) -> None:
    """The iteration's other training seeds (evaluate.training_seeds), each trained and evaluated; their
    figures and the pooled ones (mean, spread across seeds, Wilson 95% of the pooled episodes) to the run."""
    seeds = [training_seed_task(workspace, with_seed(config, seed), iteration, dataset, tasks_key, run_id)
             for seed in other_seeds(config)]
    for seed in seeds:
        _log_stage(tracking, run_id, seed)
    if not seeds:
        return
    figures = protocol_success([evaluation.tasks, *(seed.tasks for seed in seeds)])
    if any(seed.did_work() for seed in seeds):
        tracking.log_metrics(run_id, {name: value for f in figures for name, value in (
            (f"seeds.success.{f.group}", f.mean), (f"seeds.success.{f.group}.spread", f.spread),
            (f"seeds.success.{f.group}.ci_low", f.ci_low), (f"seeds.success.{f.group}.ci_high", f.ci_high))})
    log.info("iteration %d over %d training seeds: %s", iteration, len(seeds) + 1,
             "; ".join(f"{f.group} {f.describe()}" for f in figures if f.group in SPLITS))


@stage_task(name="baselines")
def baselines_task(workspace: str, config: CampaignConfig, iteration: int, tasks_key: str,
                   explore_units: list[str]) -> BaselinesResult:
    ws = Workspace.at(workspace)
    embeddings = load_embeddings(ws, tasks_key, config.train.model.language_encoder)
    return run_baselines(ws, config, iteration, tasks_key, load_tasks(ws, tasks_key), embeddings, explore_units)


@stage_task(name="adapt")
def adapt_task(workspace: str, config: CampaignConfig, source: PolicyExplorer) -> AdaptResult:
    return run_adapt(Workspace.at(workspace), config, source.model_key, source.checkpoint)


@stage_task(name="redeploy")
def redeploy_task(
    workspace: str, config: CampaignConfig, iteration: int, model: TrainResult, mlflow_run_id: str,
    evaluation: EvaluateResult,
) -> RedeployResult:
    return run_redeploy(Workspace.at(workspace), config, iteration, model.model_key, model.checkpoint, mlflow_run_id,
                        evaluation.promotion)


def _log_stage(tracking: Tracking, run_id: str, result: StageResult) -> None:
    """Log what a stage did, right after it: its metrics, tags and files (none when it did no work:
    a re-run adds no points)."""
    if metrics := result.metrics():
        tracking.log_metrics(run_id, metrics)
    if tags := result.tags():
        tracking.set_tags(run_id, tags)
    for path, folder in result.artifacts():
        tracking.log_artifact(run_id, path, folder)


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
    _log_stage(tracking, run_id, tasks)
    explore = explore_flow.with_options(task_runner=rollout_task_runner(config.explore))(
        workspace, config, iteration, tasks.unit_key, explorer
    )
    _log_stage(tracking, run_id, explore)
    filtered = filter_task(workspace, config, iteration, explore.unit_keys, previous.filter_units if previous else [])
    _log_stage(tracking, run_id, filtered)
    index = index_task(workspace, config, iteration, explore.unit_keys, filtered.unit_keys, previous)
    _log_stage(tracking, run_id, index)
    model = train_task(workspace, config, iteration, index, tasks.unit_key, run_id)
    _log_stage(tracking, run_id, model)
    evaluation = evaluate_task(workspace, config, iteration, model, tasks.unit_key)
    _log_stage(tracking, run_id, evaluation)
    deployment = redeploy_task(workspace, config, iteration, model, run_id, evaluation)
    _measure_seeds(workspace, tracking, run_id, config, iteration, index, tasks.unit_key, evaluation)
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
    stages_run = sum(result.did_work() for result in (tasks, explore, filtered, index, model, evaluation, deployment))
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
    # started by a Prefect worker rather than the CLI: the host's secrets file and the workspace's stack all the same
    apply_secrets_file()
    ws = Workspace.at(workspace).create()
    log_to_running_stack(ws)
    # one pool of rollout workers for every stage, so their processes and scenes are built once
    # a second run on the workspace is refused before any work; one a deployment started (tonight's, behind a
    # `sim2act run` from the CLI) waits for it instead, as the deployments' runs wait for each other
    from prefect.runtime import deployment

    wait_s = DEPLOYMENT_LOCK_WAIT_S if deployment.id else 0.0
    with exclusive_run(ws, config.name, wait_s, lambda holder: log.warning(
            "bootstrap: workspace %s is in use by another run (%s): waiting up to %.0f h for it to end",
            ws.root, holder, wait_s / 3600)), keep_workers():
        return _run_campaign(config, ws, continue_campaign)


def _run_campaign(config: CampaignConfig, ws: Workspace, continue_campaign: bool) -> list[IterationOutcome]:
    started = time.monotonic()
    catalog = Catalog(ws.catalog)
    catalog.initialise()
    if continue_campaign:
        config = continued(config, ws)
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
        if outcomes:
            last = outcomes[-1]  # its dataset aggregates every iteration's explore units
            iteration, tasks_key, explore_units = last.iteration, last.tasks_key, last.dataset.explore_units
        else:  # no iteration (iterations: 0): the baselines alone, on the campaign's tasks, at baselines.env_steps
            tasks = generate_tasks_task(str(ws.root), config)
            _log_stage(tracking, campaign_run_id, tasks)
            iteration, tasks_key, explore_units = 0, tasks.unit_key, []
        baselines = baselines_task(str(ws.root), config, iteration, tasks_key, explore_units)
        _log_stage(tracking, campaign_run_id, baselines)
    if config.adapt.episodes_per_task:
        adapted = adapt_task(str(ws.root), config, outcomes[-1].champion)
        _log_stage(tracking, campaign_run_id, adapted)
    if outcomes:  # the baselines alone (iterations: 0) have no iteration to plot
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
