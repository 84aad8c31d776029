"""Training seeds: an iteration's dataset trained again under other seeds (`evaluate.training_seeds`) and
each model evaluated on the campaign's cases beside the iteration's own, so every iteration's success
comes with its spread across trainings (the results protocol, docs/evaluation.md). Measured, never
deployed: the campaign's model (the first seed) alone competes for champion and explores the next
iteration. Composition, not a stage: its units are the train and evaluate stages' own, so a seed
trained by `sim2act train --set train.seed=N` on the same dataset is the same model, not trained again."""

from __future__ import annotations

import numpy as np

from schemas.config import CampaignConfig
from schemas.tasks import TaskRecord
from schemas.workspace import Workspace
from stages import StageResult
from stages.evaluate import Agent, TaskEvaluation, evaluate_model, evaluation_cases, group_success
from stages.index import IndexResult
from stages.train import OnMetrics, run_train


class SeedResult(StageResult):
    seed: int  # train.seed of this training
    model_key: str
    tasks: list[TaskEvaluation]  # the campaign's cases, as the iteration's own model met them
    trained: bool  # False: the model was registered already
    skipped_units: int  # evaluation cases already registered

    def did_work(self) -> bool:
        return self.trained or self.skipped_units < len(self.tasks)

    def metrics(self) -> dict[str, float]:
        """Success per split and family of this seed, under `seed<N>.` (the iteration's own are unprefixed)."""
        if not self.did_work():
            return {}
        return {f"seed{self.seed}.success.{g.group}": g.success_rate for g in group_success(self.tasks)}


def other_seeds(config: CampaignConfig) -> list[int]:
    """The seeds trained beside the campaign's own (train.seed): train.seed + 1, ... (evaluate.training_seeds - 1 of them)."""
    return [config.train.seed + offset for offset in range(1, config.evaluate.training_seeds)]


def with_seed(config: CampaignConfig, seed: int) -> CampaignConfig:
    """The campaign's config with another training seed, everything else alike."""
    return config.model_copy(update={"train": config.train.model_copy(update={"seed": seed})})


def run_training_seed(
    workspace: Workspace,
    config: CampaignConfig,
    iteration: int,
    dataset: IndexResult,
    tasks_key: str,
    tasks: list[TaskRecord],
    embeddings: dict[str, np.ndarray],
    on_metrics: OnMetrics | None = None,
) -> SeedResult:
    """One more training seed of an iteration, measured.

    1. Train `config` (its train.seed) on the iteration's dataset: the train stage's unit, resumable.
    2. Evaluate the model on the campaign's evaluation cases (the evaluate stage's units, the same
       episode seeds as every other model): no promotion decision, no deployment.

    Args:
        config: the campaign's config with this seed (`with_seed`).
        dataset, tasks_key, tasks, embeddings: the iteration's, as its own training read them.
        on_metrics: the training's loss curve, as the train stage reports it.

    Returns:
        The seed, its model key and its evaluations.
    """
    model = run_train(workspace, config, iteration, dataset, tasks_key, embeddings, on_metrics=on_metrics)
    evaluations, skipped = evaluate_model(workspace, config, iteration, model.model_key,
                                          Agent(kind="sim2act", path=model.checkpoint),
                                          evaluation_cases(tasks, config.evaluate.held_out_wordings), embeddings)
    return SeedResult(seed=config.train.seed, model_key=model.model_key, tasks=evaluations,
                      trained=not model.skipped, skipped_units=skipped)
