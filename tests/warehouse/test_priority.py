"""The next iteration's episode budget, shared out by the champion's evaluation."""

import pytest

from schemas.tasks import TaskRecord
from warehouse.priority import allocate, priority_scores


def _task(task_id: str, family: str = "robosuite") -> TaskRecord:
    return TaskRecord(task_id=task_id, spec="s", family=family, env_name="Lift", object_colours={},
                      instructions=["a", "b", "c"], split="seen", horizon=10)


def test_low_success_and_high_uncertainty_rank_first_within_a_family():
    tasks = [_task("a"), _task("b"), _task("c"), _task("nav", "navigation"), _task("new")]
    evaluated = {"a": (1.0, -9.0), "b": (0.2, -8.0), "c": (0.9, -2.0), "nav": (0.5, 1.3)}
    scores = priority_scores(evaluated, tasks)
    assert scores["b"] == pytest.approx(0.5 * 0.8 + 0.25) and scores["a"] == 0.0
    assert scores["c"] == pytest.approx(0.05 + 0.5)  # mostly solved, but the least sure of its family
    assert scores["nav"] == pytest.approx(0.25 + 0.25)  # alone in its family: the middle rank
    assert scores["new"] == 1.0  # never evaluated: explored most


def test_the_budget_is_kept_whole_every_task_keeps_its_floor_and_shares_follow_the_scores():
    counts = allocate({"a": 0.0, "b": 0.65, "c": 0.55, "new": 1.0}, per_task=8, floor=0.25)
    assert sum(counts.values()) == 32 and min(counts.values()) == 2
    assert counts["a"] == 2 and counts["new"] > counts["b"] > counts["c"] > counts["a"]
    assert allocate({"a": 0.0, "b": 0.0}, per_task=5, floor=0.25) == {"a": 5, "b": 5}  # nothing to tell apart
    assert allocate({"a": 0.0, "b": 1.0}, per_task=4, floor=1.0) == {"a": 4, "b": 4}  # floor 1: prioritising off
    assert allocate({"a": 0.0, "b": 1.0}, per_task=4, floor=0.0) == {"a": 0, "b": 8}
    assert allocate({"a": 0.0, "b": 1.0}, per_task=25, floor=0.28)["a"] == 7  # 0.28 * 25 is 7.000000000000001
