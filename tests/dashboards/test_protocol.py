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


def _figure(rates: list[float], episodes_per_seed: int):
    from dashboards.protocol import SeedsSuccess
    from stages.evaluate import wilson_interval

    successes = round(sum(rates) * episodes_per_seed)
    low, high = wilson_interval(successes, len(rates) * episodes_per_seed)
    return SeedsSuccess(group="seen", per_seed=rates, episodes=len(rates) * episodes_per_seed, successes=successes,
                        mean=sum(rates) / len(rates), spread=0.0, ci_low=low, ci_high=high)


def test_a_reading_weighs_the_seeds_as_well_as_the_pooled_episodes():
    """The pooled episodes' intervals hold the episodes' noise alone. Every seed of one recipe below every seed of
    the other (7% vs 13%, results.md's "champion's episodes left out") read "within the noise" because the pooled
    intervals overlapped; two seeds apart pooled can still be one seed's luck."""
    from dashboards.protocol import _against

    left_out, loop = _figure([0.06, 0.07, 0.09], 60), _figure([0.12, 0.13, 0.14], 60)
    assert _against(left_out, loop, "the loop's").startswith(
        "below the loop's across seeds (Welch's t on the seeds' rates p = 0.0")
    assert _against(left_out, loop, "the loop's").endswith("; the pooled intervals overlap")
    lucky, steady = _figure([0.10, 0.12, 0.70], 300), _figure([0.20, 0.21, 0.22], 300)
    assert _against(lucky, steady, "the loop's").startswith(
        "above the loop's by the pooled episodes (intervals apart), not across seeds (Welch's t")
    assert _against(_figure([0.5], 60), _figure([0.52], 60), "x") == "within the noise: the pooled intervals overlap"
    assert _against(_figure([0.5, 0.6], 60), _figure([0.52, 0.58], 60), "x").startswith(
        "within the noise: the pooled intervals overlap (Welch's t on the seeds' rates p = ")
