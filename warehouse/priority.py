"""Where the next iteration spends its exploration: the proposal's "under-explored tasks via
uncertainty quantification". The champion's own evaluation ranks the seen tasks, low success and
high uncertainty first, and the iteration's episode budget (explore.episodes_per_task for each
seen task) is shared out by that rank, every task keeping a floor."""

from __future__ import annotations

import math

from pydantic import BaseModel

from schemas.tasks import CAMPAIGN_SUITE, TaskRecord
from warehouse.catalog import Catalog


class TaskPriority(BaseModel):
    task_id: str
    success: float | None  # the champion's on the task said canonically; None: never evaluated
    uncertainty: float | None  # its mean per-step uncertainty there
    score: float  # in [0, 1]: half failure rate, half uncertainty rank within the family
    episodes: int  # what the task gets this iteration


def priority_scores(evaluated: dict[str, tuple[float, float]], tasks: list[TaskRecord]) -> dict[str, float]:
    """Pure: task id -> 0.5 * (1 - success) + 0.5 * the task's uncertainty rank among its family's
    tasks (0 the surest, 1 the least sure: entropy and log det Sigma do not compare across
    families). A task the champion was never evaluated on scores 1: nothing is known of it."""
    scores = {t.task_id: 1.0 for t in tasks if t.task_id not in evaluated}
    families: dict[str, list[str]] = {}
    for t in tasks:
        if t.task_id in evaluated:
            families.setdefault(t.family, []).append(t.task_id)
    for ids in families.values():
        ranked = sorted(ids, key=lambda task_id: (evaluated[task_id][1], task_id))
        for rank, task_id in enumerate(ranked):
            spread = rank / (len(ranked) - 1) if len(ranked) > 1 else 0.5
            scores[task_id] = 0.5 * (1.0 - evaluated[task_id][0]) + 0.5 * spread
    return scores


def allocate(scores: dict[str, float], per_task: int, floor: float) -> dict[str, int]:
    """Pure: share len(scores) * per_task episodes; each task gets ceil(floor * per_task), the
    rest goes in proportion to score (largest remainders, ties to the lower task id). The total
    is always the same budget, so an iteration costs what it would have cost unprioritised."""
    minimum = min(per_task, math.ceil(floor * per_task - 1e-9))  # 0.28 * 25 is 7.000000000000001: 7, not 8
    spare = (per_task - minimum) * len(scores)
    weights = {task_id: score + 1e-9 for task_id, score in scores.items()}  # all zero: equal shares
    total = sum(weights.values())
    raw = {task_id: spare * weight / total for task_id, weight in weights.items()}
    counts = {task_id: minimum + int(share) for task_id, share in raw.items()}
    leftover = len(scores) * per_task - sum(counts.values())
    for task_id in sorted(raw, key=lambda t: (-(raw[t] - int(raw[t])), t))[:leftover]:
        counts[task_id] += 1
    return counts


def plan_priorities(catalog: Catalog, campaign: str, champion_key: str, tasks: list[TaskRecord], per_task: int,
                    floor: float) -> list[TaskPriority]:
    """The champion's evaluation of each seen task (the flow's, canonical instruction) -> its share.
    The first one registered of each case, not current_evaluations' longest: the shares are in the explore
    units' keys, and a later `sim2act eval --episodes` of the champion would otherwise re-plan, and so
    explore again, every finished iteration it had explored."""
    seen = [t for t in tasks if t.split == "seen"]
    evaluated = {
        task_id: (success, uncertainty) for task_id, success, uncertainty in catalog.query(
            "SELECT e.task_id, e.success_rate, e.uncertainty FROM evaluations e "
            "LEFT JOIN stage_runs r ON r.unit_key = e.unit_key "
            "WHERE e.campaign = ? AND e.model_key = ? AND e.suite = ? AND e.split = 'seen' "
            "QUALIFY row_number() OVER (PARTITION BY e.task_id, e.instruction "
            "ORDER BY r.finished_at NULLS LAST, e.unit_key) = 1",
            [campaign, champion_key, CAMPAIGN_SUITE])
    }
    scores = priority_scores(evaluated, seen)
    counts = allocate(scores, per_task, floor)
    return [TaskPriority(task_id=t.task_id, success=evaluated.get(t.task_id, (None, None))[0],
                         uncertainty=evaluated.get(t.task_id, (None, None))[1], score=scores[t.task_id],
                         episodes=counts[t.task_id]) for t in seen]
