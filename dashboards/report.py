"""What a campaign measured, for people: success per iteration on each split (Wilson 95%
intervals), from the flow's own evaluations in the warehouse, and its plot (logged to the
campaign's MLflow run)."""

from __future__ import annotations

from pathlib import Path

from dashboards.protocol import SeedGroup, seed_groups
from schemas.tables import CURRENT_DEPLOYMENTS
from schemas.tasks import CAMPAIGN_SUITE
from stages.evaluate import SPLITS, GroupSuccess, TaskEvaluation, group_success, read_evaluations
from warehouse.catalog import Catalog


def evaluations_by_iteration(catalog: Catalog, campaign: str) -> dict[int, list[TaskEvaluation]]:
    """Iteration -> the evaluation cases of the model that iteration deployed (the flow's own)."""
    rows = read_evaluations(
        catalog, "v.iteration",
        f"JOIN {CURRENT_DEPLOYMENTS} d ON d.campaign = v.campaign AND d.iteration = v.iteration AND d.model_key = v.model_key "
        "WHERE v.campaign = ? AND v.suite = ? ORDER BY v.iteration, v.task_id, v.split", [campaign, CAMPAIGN_SUITE],
    )
    by_iteration: dict[int, list[TaskEvaluation]] = {}
    for iteration, evaluation in rows:
        by_iteration.setdefault(iteration, []).append(evaluation)
    # each case over as many episodes as its split's others: a case evaluated again with more (`sim2act eval
    # --episodes` on some tasks) would otherwise weigh more in its split, in that iteration alone
    for iteration, found in by_iteration.items():
        fewest = {split: min(e.episodes for e in found if e.split == split) for split in {e.split for e in found}}
        by_iteration[iteration] = [e.first(fewest[e.split]) for e in found]
    return by_iteration


def success_by_iteration(catalog: Catalog, campaign: str) -> dict[int, list[GroupSuccess]]:
    """Iteration -> success per split, family and split within family, of the model that
    iteration deployed, over the flow's evaluation cases."""
    return {iteration: group_success(evaluations)
            for iteration, evaluations in evaluations_by_iteration(catalog, campaign).items()}


def plot_success_by_iteration(by_iteration: dict[int, list[GroupSuccess]], groups: list[str], title: str,
                              path: Path) -> Path:
    """Success vs iteration, one line per group (e.g. seen, unseen), Wilson 95% intervals as bars."""
    import matplotlib

    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(6, 4), dpi=100)
    for offset, group in enumerate(groups):
        points = [(iteration, g) for iteration, summaries in sorted(by_iteration.items())
                  for g in summaries if g.group == group]
        if not points:
            continue
        x = [iteration + 0.05 * offset for iteration, _ in points]  # side by side: equal rates stay visible
        y = [g.success_rate for _, g in points]
        errors = [[g.success_rate - g.ci_low for _, g in points], [g.ci_high - g.success_rate for _, g in points]]
        axes.errorbar(x, y, yerr=errors, marker="o", capsize=4, label=group)
    axes.set(xlabel="iteration", ylabel="success rate", ylim=(-0.02, 1.02), title=title)
    axes.set_xticks(sorted(by_iteration))
    axes.grid(alpha=0.3)
    axes.legend()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.png")
    figure.savefig(tmp, bbox_inches="tight")
    plt.close(figure)
    tmp.replace(path)
    return path


def seeds_by_iteration(catalog: Catalog, campaign: str) -> dict[int, SeedGroup]:
    """Iteration -> the training seeds of the model it deployed (evaluate.training_seeds, or seeds trained by hand
    on its dataset), registered weights, over the flow's cases; iterations whose model has no other seed are
    left out."""
    deployed = dict(catalog.query(f"SELECT model_key, iteration FROM {CURRENT_DEPLOYMENTS} WHERE campaign = ?", [campaign]))
    return {deployed[key]: group for group in seed_groups(catalog, campaign, CAMPAIGN_SUITE)
            if group.weights == "registered" for key in group.trained_keys if key in deployed}


def campaign_summary(catalog: Catalog, campaign: str, look_further: list[str]) -> str:
    """The few lines a person reads when a campaign ends: success per iteration and split (successes,
    rate, Wilson 95%), which iteration holds the champion, and the commands to look further."""
    by_iteration = success_by_iteration(catalog, campaign)
    champions = dict(catalog.query(f"SELECT iteration, promoted FROM {CURRENT_DEPLOYMENTS} WHERE campaign = ?",
                                   [campaign]))
    seeds = seeds_by_iteration(catalog, campaign)
    splits = [s for s in SPLITS if any(g.group == s for groups in by_iteration.values() for g in groups)]
    further = ["look further:", *(f"  {command}" for command in look_further)]
    if not by_iteration:
        return "\n".join([f"campaign {campaign!r}: no iteration was evaluated", *further])
    lines = [f"campaign {campaign!r}: success per iteration (successes/episodes, rate, Wilson 95%)",
             f"  {'iteration':<10}" + "".join(f"{split:<28}" for split in splits)]
    for iteration, groups in sorted(by_iteration.items()):
        cells = {g.group: g for g in groups}
        row = "".join(
            f"{cells[s].successes:>3}/{cells[s].episodes:<3} {cells[s].success_rate:>4.0%} "
            f"[{cells[s].ci_low:.0%}, {cells[s].ci_high:.0%}]".ljust(28) if s in cells else " " * 28
            for s in splits)
        mark = "  promoted" if champions.get(iteration) else ""
        lines.append(f"  {iteration:<10}{row}{mark}".rstrip())
        if iteration in seeds:  # its model's training seeds: mean ± spread across them, the pooled episodes' interval
            pooled = {f.group: f for f in seeds[iteration].figures}
            label = f"{len(seeds[iteration].seeds)} seeds"
            coverage = seeds[iteration].coverage()
            lines.append((f"    {label:<8}" + "".join(
                f"{pooled[s].mean:>7.0%} ± {100 * pooled[s].spread:<3.0f}[{pooled[s].ci_low:.0%}, {pooled[s].ci_high:.0%}]"
                .ljust(28) if s in pooled else " " * 28 for s in splits)).rstrip() + (f"  ({coverage})" if coverage else ""))
    if seeds:
        lines.append("  (N seeds: the iteration's dataset trained N times, mean ± spread across the trainings, "
                     "Wilson 95% of their pooled episodes)")
    return "\n".join([*lines, *further])
