"""The results table's per-spec section, on a real catalog holding registered evaluations."""

from __future__ import annotations

import json

from schemas.tasks import CAMPAIGN_SUITE
from schemas.workspace import Workspace
from stages.evaluate import wilson_interval
from stages.results import spec_markdown
from warehouse.catalog import Catalog

CAMPAIGN = "specs"
TASKS = {"nav-room-red": ("nav-room", "seen"), "nav-room-sequence-red-green": ("nav-room-sequence", "seen"),
         "nav-room-sequence-purple-red": ("nav-room-sequence", "unseen")}


def _register(catalog: Catalog, iteration: int, successes: dict[tuple[str, str], int], episodes: int = 10) -> None:
    """successes: (task, split) -> successful episodes of `episodes`."""
    model = f"train-{iteration}"
    rows = []
    for (task_id, split), won in successes.items():
        low, high = wilson_interval(won, episodes)
        rows.append({
            "unit_key": f"evaluate-{iteration}-{task_id}-{split}", "campaign": CAMPAIGN, "iteration": iteration,
            "suite": CAMPAIGN_SUITE, "model_key": model, "task_id": task_id, "family": "navigation",
            "split": split, "instruction": task_id, "episodes": episodes, "successes": won,
            "ci_low": low, "ci_high": high, "mean_return": 0.0, "mean_length": 50.0, "episode_lengths": [50] * episodes,
            "episode_successes": [i < won for i in range(episodes)], "uncertainty": 0.0, "success_video": None,
            "failure_video": None, "success_rate": won / episodes})
    catalog.register_unit(unit_key=f"evaluate-{iteration}", stage="evaluate", campaign=CAMPAIGN, iteration=iteration,
                          summary={}, rows={"evaluations": rows})
    catalog.register_unit(unit_key=f"redeploy-{iteration}", stage="redeploy", campaign=CAMPAIGN, iteration=iteration,
                          summary={}, rows={"deployments": [{
                              "unit_key": f"redeploy-{iteration}", "model_key": model, "campaign": CAMPAIGN,
                              "iteration": iteration, "registered_model": "m", "version": iteration + 1,
                              "alias": "champion", "champion_version": iteration + 1, "champion_model_key": model,
                              "promoted": True, "decision": "", "mlflow_run_id": ""}]})


def test_success_per_spec_and_split_per_iteration(tmp_path):
    workspace = Workspace.at(tmp_path).create()
    catalog = Catalog(workspace.catalog)
    catalog.initialise()
    tasks = [{"campaign": CAMPAIGN, "task_id": t, "spec": spec, "family": "navigation", "env_name": "GoToRoom",
              "instruction": t, "instructions": [t], "unseen_instructions": [], "object_colours": json.dumps({}),
              "split": split, "horizon": 50, "unit_key": "tasks-test"} for t, (spec, split) in TASKS.items()]
    catalog.register_unit(unit_key="tasks-test", stage="generate_tasks", campaign=CAMPAIGN, iteration=0, summary={},
                          rows={"tasks": tasks})
    _register(catalog, 0, {("nav-room-red", "seen"): 9, ("nav-room-sequence-red-green", "seen"): 0,
                           ("nav-room-sequence-purple-red", "unseen"): 0})
    _register(catalog, 1, {("nav-room-red", "seen"): 8, ("nav-room-sequence-red-green", "seen"): 4,
                           ("nav-room-sequence-purple-red", "unseen"): 1,
                           ("nav-room-sequence-red-green", "unseen_paraphrase"): 3})
    lines = spec_markdown(catalog, CAMPAIGN)
    assert ("| iteration | nav-room/seen | nav-room/unseen | nav-room/unseen_paraphrase | nav-room-sequence/seen "
            "| nav-room-sequence/unseen | nav-room-sequence/unseen_paraphrase |") in lines
    row0, row1 = ([cell.strip() for cell in line.strip("|").split("|")] for line in lines[-2:])
    assert row0 == ["0", "9/10 = 90% (60%–98%)", "–", "–", "0/10 = 0% (0%–28%)", "0/10 = 0% (0%–28%)", "–"]
    assert [cell.split(" ")[0] for cell in row1] == ["1", "8/10", "–", "–", "4/10", "1/10", "3/10"]
    catalog_one_spec = Catalog(Workspace.at(tmp_path / "one").create().catalog)
    catalog_one_spec.initialise()
    assert spec_markdown(catalog_one_spec, CAMPAIGN) == []  # one spec: the split table says it all
