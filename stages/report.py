"""What a campaign measured, for people: success per iteration on each split (Wilson 95%
intervals), from the flow's own evaluations in the warehouse, and its plot (logged to the
campaign's MLflow run)."""

from __future__ import annotations

from pathlib import Path

from schemas.tasks import CAMPAIGN_SUITE
from stages.evaluate import GroupSuccess, TaskEvaluation, group_success, read_evaluations
from warehouse.catalog import Catalog


def evaluations_by_iteration(catalog: Catalog, campaign: str) -> dict[int, list[TaskEvaluation]]:
    """Iteration -> the evaluation cases of the model that iteration deployed (the flow's own)."""
    rows = read_evaluations(
        catalog, "v.iteration",
        "JOIN deployments d ON d.campaign = v.campaign AND d.iteration = v.iteration AND d.model_key = v.model_key "
        "WHERE v.campaign = ? AND v.suite = ? ORDER BY v.iteration, v.task_id, v.split", [campaign, CAMPAIGN_SUITE],
    )
    by_iteration: dict[int, list[TaskEvaluation]] = {}
    for iteration, evaluation in rows:
        by_iteration.setdefault(iteration, []).append(evaluation)
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
