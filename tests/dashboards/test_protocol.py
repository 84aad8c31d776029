"""The results protocol's aggregation: per-seed rates, their mean and spread, the pooled Wilson interval."""

import pytest

from dashboards.protocol import protocol_success
from stages.evaluate import TaskEvaluation, wilson_interval


def _case(task: str, split: str, successes: int, episodes: int = 10) -> TaskEvaluation:
    return TaskEvaluation(task_id=task, family="robosuite", split=split, instruction=f"do {task}", episodes=episodes,
                          successes=successes, ci_low=0.0, ci_high=1.0, mean_return=0.0, mean_length=50.0,
                          episode_lengths=[50] * episodes, episode_successes=[i < successes for i in range(episodes)],
                          uncertainty=0.0, success_video=None, failure_video=None)


def test_seeds_are_averaged_their_spread_kept_and_their_episodes_pooled():
    seeds = [[_case("a", "seen", 9), _case("b", "seen", 7), _case("c", "unseen", 2)],
             [_case("a", "seen", 10), _case("b", "seen", 10), _case("c", "unseen", 5)],
             [_case("a", "seen", 5), _case("b", "seen", 6), _case("c", "unseen", 0)]]
    figures = {f.group: f for f in protocol_success(seeds)}
    seen = figures["seen"]
    assert seen.per_seed == [0.8, 1.0, 0.55] and seen.mean == pytest.approx(0.7833333)
    assert seen.spread == pytest.approx(0.2254625, rel=1e-5)  # sample standard deviation
    assert (seen.successes, seen.episodes) == (47, 60)
    assert (seen.ci_low, seen.ci_high) == pytest.approx(wilson_interval(47, 60))
    assert figures["unseen"].per_seed == [0.2, 0.5, 0.0] and set(figures) == {
        "seen", "unseen", "robosuite", "robosuite/seen", "robosuite/unseen"}
    assert seen.describe() == "78% ± 23 (80, 100, 55) over 3 seeds, 47/60 pooled [66%, 87%]"
    [alone] = [f for f in protocol_success(seeds[:1]) if f.group == "seen"]
    assert alone.spread == 0.0 and alone.seeds == 1


def test_seeds_on_different_cases_or_none_are_refused():
    with pytest.raises(ValueError, match="needs at least one training seed"):
        protocol_success([])
    with pytest.raises(ValueError, match="expected every seed evaluated on 1 identical cases"):
        protocol_success([[_case("a", "seen", 1)], [_case("a", "seen", 1, episodes=20)]])
