"""The results protocol: a reported success is N training seeds x M evaluation episodes per case, with
the mean over seeds, their spread, and the Wilson interval of the pooled episodes (docs/evaluation.md).
One training is an anecdote: on this project's small datasets the same data trained again has landed
anywhere in 22-83% (docs/results.md), so a figure without its spread across seeds says little."""

from __future__ import annotations

import statistics

from pydantic import BaseModel

from stages.evaluate import TaskEvaluation, group_success, wilson_interval

RESULTS_SEEDS, RESULTS_EPISODES = 3, 50  # the protocol's defaults for anything in docs/results*.md


class SeedsSuccess(BaseModel):
    """Success over a group of cases (a split, a family, a split within a family), per training seed and pooled."""

    group: str
    per_seed: list[float]  # each training's success rate over the group's episodes, in the order given
    episodes: int  # pooled over the seeds
    successes: int
    mean: float  # of per_seed
    spread: float  # sample standard deviation of per_seed (0 for one seed)
    ci_low: float  # Wilson 95% of the pooled episodes
    ci_high: float

    @property
    def seeds(self) -> int:
        return len(self.per_seed)

    def describe(self) -> str:
        """e.g. `87% ± 5 (82, 85, 93) over 3 seeds, 131/150 pooled [81%, 92%]`"""
        seeds = ", ".join(f"{rate:.0%}".rstrip("%") for rate in self.per_seed)
        return (f"{self.mean:.0%} ± {100 * self.spread:.0f} ({seeds}) over {self.seeds} seed{'s' * (self.seeds > 1)}, "
                f"{self.successes}/{self.episodes} pooled [{self.ci_low:.0%}, {self.ci_high:.0%}]")


def protocol_success(by_seed: list[list[TaskEvaluation]]) -> list[SeedsSuccess]:
    """Each group's success across trainings: `by_seed` holds one list of case evaluations per training
    seed, the same cases and episode seeds for each. Groups every seed has, sorted by name.

    Raises:
        ValueError: no seed, or seeds evaluated on different cases (their figures would not compare).
    """
    if not by_seed:
        raise ValueError("the results protocol needs at least one training seed's evaluations, got none")
    cases = [sorted((t.task_id, t.split, t.instruction, t.episodes) for t in evaluations) for evaluations in by_seed]
    if any(c != cases[0] for c in cases[1:]):
        raise ValueError("the results protocol compares seeds on the same cases: expected every seed evaluated on "
                         f"{len(cases[0])} identical cases, got case lists that differ")
    per_seed = [{g.group: g for g in group_success(evaluations)} for evaluations in by_seed]
    figures = []
    for group in sorted(per_seed[0]):
        members = [seed[group] for seed in per_seed]
        rates = [g.success_rate for g in members]
        episodes, successes = sum(g.episodes for g in members), sum(g.successes for g in members)
        low, high = wilson_interval(successes, episodes)
        figures.append(SeedsSuccess(
            group=group, per_seed=rates, episodes=episodes, successes=successes, mean=statistics.fmean(rates),
            spread=statistics.stdev(rates) if len(rates) > 1 else 0.0, ci_low=low, ci_high=high,
        ))
    return figures
