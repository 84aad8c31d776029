"""Per-iteration Prefect artifacts, shown on the flow run's page in the UI: what every stage did
(Markdown), success per task (a table), and a link to the iteration's MLflow run."""

from __future__ import annotations

import os
import re

from prefect.artifacts import create_link_artifact, create_markdown_artifact, create_table_artifact

from flows.service import MLFLOW_UI_ENV
from stages.evaluate import EvaluateResult, group_success
from stages.explore import ExploreResult, PolicyExplorer
from stages.filter import FilterResult
from stages.generate_tasks import TasksResult
from stages.index import IndexResult
from stages.redeploy import RedeployResult
from stages.train import TrainResult


def artifact_key(campaign: str, iteration: int, what: str) -> str:
    """Prefect keys allow lowercase letters, digits and dashes only."""
    return re.sub(r"[^a-z0-9-]+", "-", f"{campaign}-iteration-{iteration}-{what}".lower()).strip("-")


def mlflow_run_url(experiment_id: str, run_id: str) -> str | None:
    ui = os.environ.get(MLFLOW_UI_ENV)
    return f"{ui.rstrip('/')}/#/experiments/{experiment_id}/runs/{run_id}" if ui else None


def _ran(skipped: bool) -> str:
    return "already done (skipped)" if skipped else "ran"


def iteration_markdown(
    campaign: str, iteration: int, explorer: PolicyExplorer | None, tasks: TasksResult, explore: ExploreResult,
    filtered: FilterResult, index: IndexResult, model: TrainResult, evaluation: EvaluateResult,
    deployment: RedeployResult, mlflow_run: str,
) -> str:
    reasons = ", ".join(f"{reason} {count}" for reason, count in sorted(filtered.reasons.items())) or "none this run"
    ranked = ", ".join(f"{p.task_id} {p.episodes}" for p in explore.priorities[:5])
    final = model.history[-1] if model.history else {}
    loss = f", final loss {final['loss']:.4f}" if "loss" in final else ""
    splits = ", ".join(f"{g.group} {g.successes}/{g.episodes} ({g.success_rate:.0%})"
                       for g in group_success(evaluation.tasks) if "/" not in g.group)  # splits, families
    promotion = evaluation.promotion
    lines = [
        f"# {campaign}, iteration {iteration}",
        "",
        f"Explorer: **{explorer.name if explorer else 'expert'}**. MLflow run: {mlflow_run}.",
        "",
        "| stage | what it did |",
        "|---|---|",
        f"| generate_tasks | {_ran(tasks.skipped)}: {len(tasks.task_ids)} tasks"
        + ("" if tasks.skipped else f", {tasks.instructions} instructions") + " |",
        f"| explore | {len(explore.unit_keys) - explore.skipped_units}/{len(explore.unit_keys)} units ran: "
        f"{explore.episodes} episodes, {explore.steps:,} triplets"
        + (f"; most episodes to {ranked}" if ranked else "") + " |",
        f"| filter | {len(filtered.unit_keys) - filtered.skipped_units}/{len(filtered.unit_keys)} units ran; "
        f"decisions: {reasons} |",
        f"| index | {_ran(index.skipped)}: {index.kept_episodes}/{index.episodes} episodes kept, "
        f"{index.triplets:,} triplets, digest `{index.dataset_digest[:12]}` |",
        f"| train | {_ran(model.skipped)}: `{model.model_key}` on {model.samples:,} samples{loss} |",
        f"| evaluate | {len(evaluation.tasks) - evaluation.skipped_units}/{len(evaluation.tasks)} cases ran: {splits} |",
        f"| redeploy | {_ran(deployment.skipped)}: {deployment.registered_model} v{deployment.version}; "
        f"{'promoted' if promotion.promote else 'not promoted'} ({promotion.reason}); "
        f"champion `{deployment.champion.name}` |",
    ]
    return "\n".join(lines) + "\n"


def success_rows(evaluation: EvaluateResult) -> list[dict[str, object]]:
    return [
        {"task": t.task_id, "split": t.split, "family": t.family, "successes": t.successes, "episodes": t.episodes,
         "success": round(t.success_rate, 3), "wilson_95": f"[{t.ci_low:.2f}, {t.ci_high:.2f}]",
         "mean_length": round(t.mean_length, 1), "instruction": t.instruction}
        for t in evaluation.tasks
    ]


def publish_iteration_artifacts(campaign: str, iteration: int, markdown: str, evaluation: EvaluateResult,
                                experiment_id: str, run_id: str) -> None:
    """Keyed by campaign and iteration, so a re-run adds a version rather than a stray artifact."""
    create_markdown_artifact(markdown, key=artifact_key(campaign, iteration, "summary"),
                             description=f"{campaign} iteration {iteration}: what every stage did")
    create_table_artifact(success_rows(evaluation), key=artifact_key(campaign, iteration, "success"),
                          description=f"{campaign} iteration {iteration}: success per task (Wilson 95%)")
    url = mlflow_run_url(experiment_id, run_id)
    if url:
        create_link_artifact(url, link_text=f"MLflow run {run_id}", key=artifact_key(campaign, iteration, "mlflow"),
                             description=f"{campaign} iteration {iteration}: metrics, videos and the model")
