"""The results protocol: a reported success is N training seeds x M evaluation episodes per case, with
the mean over seeds, their spread, and the Wilson interval of the pooled episodes (docs/evaluation.md).
One training is an anecdote: on this project's small datasets the same data trained again has landed
anywhere in 22-83% (docs/results.md), so a figure without its spread across seeds says little."""

from __future__ import annotations

import json
import statistics

from pydantic import BaseModel

from schemas.tables import CURRENT_DEPLOYMENTS
from schemas.wordings import HELD_OUT_WORDING
from stages.evaluate import SPLITS, TaskEvaluation, evaluated_key, group_success, wilson_interval

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
        """e.g. `87% ± 6 (82, 86, 94) over 3 seeds, 131/150 pooled [81%, 92%]` (± the seeds' sample standard deviation)"""
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
    cases = [sorted(_case(t) for t in evaluations) for evaluations in by_seed]
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


# what a training's summary says that is not its recipe: the seed, what it measured, and the precision the device
# (or, on a CPU where bf16 may pay, a timing of its own step) chose: one recipe's seeds may differ in it by host
NOT_RECIPE = {"seed", "final_loss", "resumed_at_step", "precision"}


def _flat(settings: dict, prefix: str = "train.") -> dict[str, object]:
    flat: dict[str, object] = {}
    for name, value in settings.items():
        flat.update(_flat(value, f"{prefix}{name}.") if isinstance(value, dict) else {f"{prefix}{name}": value})
    return flat


def differing_settings(groups: list[SeedGroup]) -> list[dict[str, object]]:
    """Per group, the train settings (`train.targets`, `train.model.chunk`, ...) whose values are not the same in
    every group: what tells two rows of one dataset apart when their summaries' headline fields agree. A summary
    from before the recipe was recorded (no `recipe`) adds none."""
    flat = [_flat(g.recipe.get("recipe") or {}) for g in groups]
    recorded = [s for s in flat if s]
    names = sorted({name for settings in recorded for name in settings})
    differing = [n for n in names if len({json.dumps(s.get(n), sort_keys=True) for s in recorded}) > 1]
    return [{n: s[n] for n in differing if n in s} for s in flat]


class SeedGroup(BaseModel):
    """Trainings of one dataset with one recipe, differing only in train.seed, evaluated alike."""

    iteration: int  # the campaign iteration whose dataset they trained on
    recipe: dict  # the training summary's recipe fields (chunk, weights, steps, ...)
    weights: str  # which weights were evaluated: registered (the training's own choice) or final
    model_keys: list[str]  # one per seed, in seed order: the training evaluated (a seed's latest, where trained twice)
    trained_keys: list[str] = []  # every training of the group's seeds: a deployment of any of them is this group's
    seeds: list[int]
    precisions: list[str] = []  # per seed: "bf16" or "fp32" as it trained ("" where its summary predates the record)
    figures: list[SeedsSuccess]
    cases: int = 0  # the cases every seed was evaluated on: the figures' cases
    cases_not_shared: int = 0  # cases some seeds met and others not (yet): left out of the figures

    def coverage(self) -> str:
        """"" where the figures hold every case the seeds met; else how many they hold, and why."""
        if not self.cases_not_shared:
            return ""
        return (f"over {self.cases} of {self.cases + self.cases_not_shared} cases: the others not evaluated for "
                f"every seed (yet)")


def _case(evaluation: TaskEvaluation) -> tuple:
    return evaluation.task_id, evaluation.split, evaluation.instruction, evaluation.episodes


def _shared_cases(runs: list[list[TaskEvaluation]]) -> tuple[list[list[TaskEvaluation]], int]:
    """Each seed's evaluations cut to the cases every seed met, each case over the episodes every seed played (a
    seed evaluated again on more, `sim2act eval --episodes 50`: its first N are the others' N), and how many
    cases some seeds met and others not (yet). A held-out wording only some seeds met (`sim2act eval --split`)
    is an extra, not a case missing."""
    by_seed = [{(t.task_id, t.split, t.instruction): t for t in run} for run in runs]
    shared = set.intersection(*(set(cases) for cases in by_seed))
    episodes = {case: min(cases[case].episodes for cases in by_seed) for case in shared}
    cut = [{case: cases[case].first(episodes[case]) for case in shared} for cases in by_seed]
    shared = {case for case in shared if all(cases[case].episodes == episodes[case] for cases in cut)}  # cut or not
    splits = {case[1] for case in shared}
    met = {case for cases in by_seed for case in cases if case[1] != HELD_OUT_WORDING or case[1] in splits}
    return [[cases[case] for case in sorted(shared)] for cases in cut], len(met - shared)


def seed_groups(catalog, campaign: str, suite: str) -> list[SeedGroup]:
    """Every group of two or more trainings of the same dataset and recipe (their registered summaries
    less the seed) whose models were all evaluated on `suite`, once per weights, over the cases every
    seed met (_shared_cases). A seed trained twice under two keys (another train stage version) counts
    once: its latest training evaluated with those weights."""
    from stages.evaluate import read_evaluations

    trainings: dict[str, dict[int, list[str]]] = {}  # group -> seed -> its model keys, oldest training first
    precision: dict[str, str] = {}
    recipes: dict[str, dict] = {}
    iterations: dict[str, int] = {}
    for model_key, summary, digest, iteration in catalog.query(
            "SELECT s.unit_key, s.summary, m.dataset_digest, m.iteration FROM stage_runs s "
            "JOIN models m ON m.model_key = s.unit_key "
            "WHERE s.stage = 'train' AND s.campaign = ? ORDER BY s.finished_at NULLS FIRST, s.unit_key", [campaign]):
        fields = json.loads(summary)
        recipe = {k: v for k, v in sorted(fields.items()) if k not in NOT_RECIPE}
        group = json.dumps([digest, recipe], sort_keys=True)
        recipes[group], iterations[group] = recipe, iteration
        keys = trainings.setdefault(group, {}).setdefault(int(fields.get("seed", 0)), [])
        if model_key not in keys:
            keys.append(model_key)
        precision[model_key] = fields.get("precision", "")
    evaluated: dict[str, list] = {}
    for model_key, evaluation in read_evaluations(catalog, "v.model_key", "WHERE v.campaign = ? AND v.suite = ?",
                                                  [campaign, suite]):
        evaluated.setdefault(model_key, []).append(evaluation)
    groups = []
    for group, by_seed in trainings.items():
        if len(by_seed) < 2:
            continue
        for weights in ("registered", "final"):
            members = []  # (seed, model key): per seed its latest training evaluated with these weights
            for seed, keys in sorted(by_seed.items()):
                evaluated_keys = [key for key in keys if evaluated_key(key, weights) in evaluated]
                if evaluated_keys:
                    members.append((seed, evaluated_keys[-1]))
            if len(members) < len(by_seed):
                continue
            runs, not_shared = _shared_cases([evaluated[evaluated_key(key, weights)] for _, key in members])
            if not runs[0]:
                continue
            groups.append(SeedGroup(iteration=iterations[group], recipe=recipes[group], weights=weights,
                                    model_keys=[k for _, k in members], seeds=[s for s, _ in members],
                                    trained_keys=[k for keys in by_seed.values() for k in keys],
                                    precisions=[precision[k] for _, k in members], figures=protocol_success(runs),
                                    cases=len(runs[0]), cases_not_shared=not_shared))
    # by iteration, then recipe: a loop's iteration 0 reads above its iteration 3
    return sorted(groups, key=lambda g: (g.iteration, json.dumps(g.recipe, sort_keys=True), g.weights != "registered"))


class Ablation(BaseModel):
    """A recipe trained on an iteration's data beside the one the loop trained there, both over seeds, on one split."""

    iteration: int
    changed: dict[str, object]  # the settings in which it differs from the loop's recipe (`train.targets`: ...)
    ablation: SeedsSuccess
    loop: SeedsSuccess

    @property
    def delta(self) -> float:
        return self.ablation.mean - self.loop.mean

    def reading(self) -> str:
        return _against(self.ablation, self.loop, "the loop's")


class Climb(BaseModel):
    """The loop's own recipe at its first and its last iteration trained over seeds, on one split: whether the
    loop climbs (issue 9 item 5: by >= 15 points, the pooled intervals apart)."""

    first_iteration: int
    last_iteration: int
    first: SeedsSuccess
    last: SeedsSuccess

    @property
    def delta(self) -> float:
        return self.last.mean - self.first.mean

    def reading(self) -> str:
        return _against(self.last, self.first, f"iteration {self.first_iteration}'s")


def _against(figure: SeedsSuccess, reference: SeedsSuccess, whose: str) -> str:
    """How `figure` reads against `reference`, by both measures: the pooled episodes' Wilson intervals (the
    episodes' noise alone) and, with two seeds or more on each side, Welch's t on the seeds' rates (which the
    seeds' own disagreement widens or narrows: apart pooled intervals can still be one seed's luck, and
    overlapping ones can hide every seed of one recipe below every seed of the other)."""
    side = "below" if figure.mean < reference.mean else "above"
    apart = figure.ci_high < reference.ci_low or figure.ci_low > reference.ci_high
    p = welch_p(figure.per_seed, reference.per_seed)
    across = "" if p is None else f"Welch's t on the seeds' rates p = {p:.2g}"
    if apart and (p is None or p < 0.05):
        return f"{side} {whose}: the pooled intervals are apart" + (f"; across seeds too ({across})" if across else "")
    if apart:
        return f"{side} {whose} by the pooled episodes (intervals apart), not across seeds ({across})"
    if p is not None and p < 0.05:
        return f"{side} {whose} across seeds ({across}); the pooled intervals overlap"
    return "within the noise: the pooled intervals overlap" + (f" ({across})" if across else "")


def welch_p(rates: list[float], others: list[float]) -> float | None:
    """Two-sided p of Welch's t-test between two groups of seeds' rates; None where a side has fewer than two
    seeds, or neither varies (no spread to measure a difference against)."""
    if len(rates) < 2 or len(others) < 2:
        return None
    from scipy import stats

    if statistics.variance(rates) == 0 and statistics.variance(others) == 0:
        return None
    return float(stats.ttest_ind(rates, others, equal_var=False).pvalue)


def _recipe_changes(loop: dict, other: dict) -> dict[str, object]:
    """Settings of `other` that differ from `loop`'s: the recorded recipes where both have one, else the
    summaries' headline fields."""
    if loop.get("recipe") and other.get("recipe"):
        mine, theirs = _flat(loop["recipe"]), _flat(other["recipe"])
    else:
        mine, theirs = ({k: v for k, v in r.items() if k != "recipe"} for r in (loop, other))
    names = sorted(set(mine) | set(theirs))
    return {n: theirs.get(n) for n in names
            if json.dumps(mine.get(n), sort_keys=True) != json.dumps(theirs.get(n), sort_keys=True)}


def _figure(group: SeedGroup, split: str) -> SeedsSuccess | None:
    return next((f for f in group.figures if f.group == split), None)


def loop_groups(catalog, campaign: str, groups: list[SeedGroup]) -> list[SeedGroup]:
    """The loop's own recipe per iteration: the group (registered weights) holding the model that iteration's
    redeploy stage met, promoted or not (its seed from `sim2act run`, the others from `sim2act train --set
    train.seed=N`), by iteration."""
    deployed = {(iteration, key) for iteration, key in catalog.query(
        f"SELECT iteration, model_key FROM {CURRENT_DEPLOYMENTS} WHERE campaign = ?", [campaign])}
    return sorted((g for g in groups if g.weights == "registered"
                   and any((g.iteration, key) in deployed for key in g.trained_keys)), key=lambda g: g.iteration)


def ablations(loops: list[SeedGroup], groups: list[SeedGroup], split: str = "seen") -> list[Ablation]:
    """Every other recipe of an iteration against the loop's own there (`loops`: loop_groups), registered
    weights, on `split`. Which part of the loop does the work is read off these (issue 9 item 5)."""
    found = []
    for loop in loops:
        loop_figure = _figure(loop, split)
        if loop_figure is None:
            continue
        for other in groups:
            other_figure = _figure(other, split)
            if (other is not loop and other.weights == "registered" and other.iteration == loop.iteration
                    and other_figure is not None):
                found.append(Ablation(iteration=loop.iteration, changed=_recipe_changes(loop.recipe, other.recipe),
                                      ablation=other_figure, loop=loop_figure))
    return found


def climbs(loops: list[SeedGroup]) -> list[Climb]:
    """Per split (not per family: the seeds table has those), the loop's recipe (`loops`: loop_groups) at its first
    iteration trained over seeds against its last: empty until two iterations of the loop have several seeds each."""
    if len({g.iteration for g in loops}) < 2:  # one iteration's loop rows (a redone iteration) do not climb
        return []
    first, last = loops[0], loops[-1]
    return [Climb(first_iteration=first.iteration, last_iteration=last.iteration, first=a, last=b)
            for a in first.figures if a.group in SPLITS and (b := _figure(last, a.group)) is not None]
