"""The results table's per-spec section, on a real catalog holding registered evaluations."""

from __future__ import annotations

import json

import pyarrow as pa
import pytest

from dashboards import results
from dashboards.results import results_markdown, running_seconds, spec_markdown
from schemas.tables import EPISODES
from schemas.tasks import CAMPAIGN_SUITE
from schemas.workspace import Workspace
from stages.evaluate import wilson_interval
from warehouse.catalog import Catalog
from warehouse.shard_writer import write_shard

CAMPAIGN = "specs"
TASKS = {"nav-room-red": ("nav-room", "seen"), "nav-room-sequence-red-green": ("nav-room-sequence", "seen"),
         "nav-room-sequence-purple-red": ("nav-room-sequence", "unseen")}
METAWORLD = {"mw-reach": "seen", "mw-push": "unseen"}  # task -> split, each its own spec: a second family where asked


def _family(task_id: str) -> str:
    return "metaworld" if task_id in METAWORLD else "navigation"


def _cells(line: str) -> list[str]:
    """A markdown table row's cells, stripped."""
    return [cell.strip() for cell in line.strip("|").split("|")]


def _register(catalog: Catalog, iteration: int, successes: dict[tuple[str, str], int], episodes: int = 10,
              model: str | None = None) -> None:
    """`model` (train-<iteration>) evaluated and deployed at `iteration`; successes: (task, split) -> successful
    episodes of `episodes`."""
    model = model or f"train-{iteration}"
    runs = "" if model == f"train-{iteration}" else f"-{model}"  # a second model's units beside the first's
    rows = []
    for (task_id, split), won in successes.items():
        low, high = wilson_interval(won, episodes)
        rows.append({
            "unit_key": f"evaluate-{iteration}{runs}-{task_id}-{split}", "campaign": CAMPAIGN, "iteration": iteration,
            "suite": CAMPAIGN_SUITE, "model_key": model, "task_id": task_id, "family": _family(task_id),
            "split": split, "instruction": task_id, "episodes": episodes, "successes": won,
            "ci_low": low, "ci_high": high, "mean_return": 0.0, "mean_length": 50.0, "episode_lengths": [50] * episodes,
            "episode_successes": [i < won for i in range(episodes)], "uncertainty": 0.0, "success_video": None,
            "failure_video": None, "episode_achieved": None, "success_rate": won / episodes})
    catalog.register_unit(unit_key=f"evaluate-{iteration}{runs}", stage="evaluate", campaign=CAMPAIGN, iteration=iteration,
                          summary={}, rows={"evaluations": rows})
    catalog.register_unit(unit_key=f"redeploy-{iteration}{runs}", stage="redeploy", campaign=CAMPAIGN,
                          iteration=iteration, summary={}, rows={"deployments": [{
                              "unit_key": f"redeploy-{iteration}{runs}", "model_key": model, "campaign": CAMPAIGN,
                              "iteration": iteration, "registered_model": "m", "version": iteration + 1,
                              "alias": "champion", "champion_version": iteration + 1, "champion_model_key": model,
                              "promoted": True, "decision": "", "mlflow_run_id": ""}]})


def _explored(catalog: Catalog, workspace: Workspace, steps: dict[str, list[int]]) -> None:
    """Iteration 0 explored and indexed: task -> its episodes' lengths, one explore unit (a shard) per task."""
    units = []
    for task_id, lengths in steps.items():
        unit = f"explore-{task_id}"
        table = pa.Table.from_pylist([
            {"campaign": CAMPAIGN, "iteration": 0, "episode_id": f"{task_id}-{i}", "task_id": task_id,
             "instruction": task_id, "explorer": "expert", "seed": i, "shard_key": unit, "num_steps": length,
             "episode_return": 0.0, "success": True} for i, length in enumerate(lengths)], schema=EPISODES)
        shard = write_shard("episodes", table, workspace.shard_path("episodes", 0, unit))
        catalog.register_unit(unit_key=unit, stage="explore", campaign=CAMPAIGN, iteration=0, summary={},
                              shards=[shard])
        units.append(unit)
    catalog.register_unit(unit_key="index-0", stage="index", campaign=CAMPAIGN, iteration=0, summary={}, rows={
        "iterations": [{"unit_key": "index-0", "campaign": CAMPAIGN, "iteration": 0, "dataset_digest": "d",
                        "explore_units": units, "filter_units": [], "episodes": 0, "kept_episodes": 0, "triplets": 0}]})


def _catalog_with_tasks(folder, with_metaworld: bool = False) -> Catalog:
    """A new workspace's catalog holding the campaign's TASKS (navigation), and METAWORLD's if asked."""
    catalog = Catalog(Workspace.at(folder).create().catalog)
    catalog.initialise()
    specs = {**TASKS, **({t: (t, split) for t, split in METAWORLD.items()} if with_metaworld else {})}
    tasks = [{"campaign": CAMPAIGN, "task_id": t, "spec": spec, "family": _family(t), "env_name": "GoToRoom",
              "instruction": t, "instructions": [t, f"{t} now", f"do {t}"], "unseen_instructions": [],
              "object_colours": json.dumps({}), "split": split, "horizon": 50, "unit_key": "tasks-test"}
             for t, (spec, split) in specs.items()]
    catalog.register_unit(unit_key="tasks-test", stage="generate_tasks", campaign=CAMPAIGN, iteration=0, summary={},
                          rows={"tasks": tasks})
    return catalog


def test_success_per_spec_and_split_per_iteration(tmp_path, monkeypatch):
    catalog = _catalog_with_tasks(tmp_path)
    _register(catalog, 0, {("nav-room-red", "seen"): 9, ("nav-room-sequence-red-green", "seen"): 0,
                           ("nav-room-sequence-purple-red", "unseen"): 0})
    _register(catalog, 1, {("nav-room-red", "seen"): 8, ("nav-room-sequence-red-green", "seen"): 4,
                           ("nav-room-sequence-purple-red", "unseen"): 1,
                           ("nav-room-sequence-red-green", "unseen_paraphrase"): 3})
    lines = spec_markdown(catalog, CAMPAIGN)
    assert ("| iteration | nav-room/seen | nav-room/unseen | nav-room/unseen_paraphrase | nav-room-sequence/seen "
            "| nav-room-sequence/unseen | nav-room-sequence/unseen_paraphrase |") in lines
    row0, row1 = (_cells(line) for line in lines[-2:])
    assert row0 == ["0", "9/10 = 90% (60%–98%)", "–", "–", "0/10 = 0% (0%–28%)", "0/10 = 0% (0%–28%)", "–"]
    assert [cell.split(" ")[0] for cell in row1] == ["1", "8/10", "–", "–", "4/10", "1/10", "3/10"]
    monkeypatch.setattr(results, "WIDE_TABLE_NAMES", 1)  # more specs than fit side by side: a row per spec and iteration
    long = spec_markdown(catalog, CAMPAIGN)
    assert "|  | iteration | seen | unseen | unseen paraphrase |" in long
    rows = [_cells(line) for line in long[-4:]]
    assert [row[:2] + [cell.split(" ")[0] for cell in row[2:]] for row in rows] == [
        ["nav-room", "0", "9/10", "–", "–"], ["nav-room", "1", "8/10", "–", "–"],
        ["nav-room-sequence", "0", "0/10", "0/10", "–"], ["nav-room-sequence", "1", "4/10", "1/10", "3/10"]]
    catalog_one_spec = Catalog(Workspace.at(tmp_path / "one").create().catalog)
    catalog_one_spec.initialise()
    assert spec_markdown(catalog_one_spec, CAMPAIGN) == []  # one spec: the split table says it all


def test_a_case_evaluated_again_with_more_episodes_weighs_as_its_splits_others(tmp_path):
    """nav-room-red evaluated again over 50 episodes (0 of them successes): pooled with the other seen case's 10,
    the split read 10/60; each case over its split's 10, 10/20 as before."""
    from dashboards.report import success_by_iteration

    catalog = _catalog_with_tasks(tmp_path)
    _register(catalog, 0, {("nav-room-red", "seen"): 0, ("nav-room-sequence-red-green", "seen"): 10})
    _evaluated(catalog, "train-0", 0, episodes=50, unit="evaluate-0-again")
    seen = next(g for g in success_by_iteration(catalog, CAMPAIGN)[0] if g.group == "seen")
    assert (seen.successes, seen.episodes) == (10, 20)


def _training(catalog: Catalog, key: str, seed: int, chunk: int, digest: str = "d0", iteration: int = 0,
              recipe: dict | None = None, precision: str | None = None) -> None:
    summary = {"final_loss": -seed, "steps": 2400, "members": 1, "resumed_at_step": 0, "where": None,
               "weights": "ema 0.999", "chunk": chunk, "seed": seed, **({} if recipe is None else {"recipe": recipe}),
               **({} if precision is None else {"precision": precision})}
    catalog.register_unit(unit_key=key, stage="train", campaign=CAMPAIGN, iteration=iteration, summary=summary,
                          rows={"models": [{"model_key": key, "campaign": CAMPAIGN, "iteration": iteration,
                                            "checkpoint_path": "x",
                                            "dataset_digest": digest, "dataset_shards": [], "train_samples": 1,
                                            "final_loss": 0.0, "unit_key": key}]})


def _evaluated(catalog: Catalog, model: str, won: int, episodes: int = 10, task: tuple[str, str] | None = None,
               campaign: str = CAMPAIGN, split: str = "seen", unit: str | None = None,
               suite: str = CAMPAIGN_SUITE) -> None:
    """`model`'s evaluation on one case: nav-room-red, or `task` (task id, family), in `split`; its first `won`
    episodes succeeded. `unit`: the case evaluated again, under another unit."""
    task_id, family = task or ("nav-room-red", "navigation")
    low, high = wilson_interval(won, episodes)
    key = unit or f"evaluate-{model}-{task_id}" + ("" if campaign == CAMPAIGN else f"-{campaign}")
    row = {"unit_key": key, "campaign": campaign, "iteration": 0, "suite": suite,
           "model_key": model, "task_id": task_id, "family": family, "split": split,
           "instruction": task_id, "episodes": episodes, "successes": won, "ci_low": low, "ci_high": high,
           "mean_return": 0.0, "mean_length": 50.0, "episode_lengths": [50] * episodes,
           "episode_successes": [i < won for i in range(episodes)], "uncertainty": 0.0, "success_video": None,
           "failure_video": None, "episode_achieved": None, "success_rate": won / episodes}
    catalog.register_unit(unit_key=key, stage="evaluate", campaign=campaign, iteration=0, summary={},
                          rows={"evaluations": [row]})


def test_the_seeds_are_pooled_per_family_where_the_trainings_met_several(tmp_path):
    from dashboards.results import protocol_markdown

    catalog = Catalog(Workspace.at(tmp_path).create().catalog)
    catalog.initialise()
    for seed, (navigated, lifted) in enumerate(((9, 2), (7, 4), (8, 3))):
        _training(catalog, f"train-s{seed}", seed, 8)
        _evaluated(catalog, f"train-s{seed}", navigated)
        _evaluated(catalog, f"train-s{seed}", lifted, task=("lift-red", "robosuite"))
    lines = protocol_markdown(catalog, CAMPAIGN)
    rows = {row[1]: row for row in (_cells(line) for line in lines)
            if len(row) > 1 and row[1] in ("navigation", "robosuite")}
    assert rows["navigation"] == ["0", "navigation", "registered", "0, 1, 2",
                                  "80% ± 10 (90, 70, 80) over 3 seeds, 24/30 pooled [63%, 90%]"]
    assert rows["robosuite"][4].startswith("30% ± 10 (20, 40, 30) over 3 seeds, 9/30 pooled")
    assert any(line.startswith("| 0 | chunk 8") and "55% ±" in line for line in lines)  # both families, above


def test_the_report_pools_trainings_that_differ_only_in_their_seed(tmp_path):
    from dashboards.results import protocol_markdown

    catalog = Catalog(Workspace.at(tmp_path).create().catalog)
    catalog.initialise()
    assert protocol_markdown(catalog, CAMPAIGN)[0].startswith("No dataset of this campaign was trained with several")
    for seed, won in enumerate((9, 7, 8)):  # one recipe, three seeds, evaluated with both weights
        _training(catalog, f"train-c8-s{seed}", seed, 8, iteration=3)
        _evaluated(catalog, f"train-c8-s{seed}", won)
        _evaluated(catalog, f"train-c8-s{seed}:final", won - 1)
    extra = {"unit_key": "evaluate-extra", "campaign": CAMPAIGN, "iteration": 0, "suite": CAMPAIGN_SUITE,
             "model_key": "train-c8-s0", "task_id": "nav-room-red", "family": "navigation", "split": "held_out_wording",
             "instruction": "proceed to the crimson chamber", "episodes": 10, "successes": 0, "ci_low": 0.0,
             "ci_high": 0.3, "mean_return": 0.0, "mean_length": 50.0, "episode_lengths": [50] * 10,
             "episode_successes": [False] * 10, "uncertainty": 0.0, "success_video": None, "failure_video": None,
             "episode_achieved": None,
             "success_rate": 0.0}  # a split only seed 0 met (sim2act eval --split): left out of the pooling
    catalog.register_unit(unit_key="evaluate-extra", stage="evaluate", campaign=CAMPAIGN, iteration=0, summary={},
                          rows={"evaluations": [extra]})
    _training(catalog, "train-c1-s0", 0, 1)  # another recipe, one seed: no row
    _evaluated(catalog, "train-c1-s0", 10)
    _training(catalog, "train-c8-s1-other-data", 1, 8, digest="d1")  # another dataset: no row
    lines = protocol_markdown(catalog, CAMPAIGN)
    rows = [_cells(line) for line in lines if "| chunk" in line]
    assert rows == [  # the dataset's iteration first: iteration 0 and 3 of one loop are told apart at a glance
        ["3", "chunk 8, members 1, steps 2400, weights ema 0.999", "registered", "0, 1, 2",
         "80% ± 10 (90, 70, 80) over 3 seeds, 24/30 pooled [63%, 90%]"],
        ["3", "chunk 8, members 1, steps 2400, weights ema 0.999", "final", "0, 1, 2",
         "70% ± 10 (80, 60, 70) over 3 seeds, 21/30 pooled [52%, 83%]"]]


def test_a_seed_trained_twice_counts_once_and_a_seed_mid_evaluation_is_said(tmp_path):
    """Seed 0 trained again under another key (a new train stage version): the group holds its latest training
    once, not seed 0 twice, and the loop's deployment of the older one still finds the group. Seed 2 evaluated on
    one of three cases so far (another case of its split, and a whole split, not yet): the figures hold the case
    every seed met, and the row says how many it left out. Seed 1 evaluated again on 20 episodes: its first 10
    are the others' 10, so the case stays shared."""
    from dashboards.report import campaign_summary
    from dashboards.results import protocol_markdown

    catalog = Catalog(Workspace.at(tmp_path).create().catalog)
    catalog.initialise()
    # registered in this order: train-b-s0 is seed 0's older training, train-a-s0 its latest
    for key, seed, won in (("train-b-s0", 0, 1), ("train-s1", 1, 7), ("train-a-s0", 0, 9), ("train-s2", 2, 8)):
        _training(catalog, key, seed, 8)
        _evaluated(catalog, key, won)
        if seed != 2:  # seed 2 is still being evaluated: lift-red and the paraphrase not yet
            _evaluated(catalog, key, 5, task=("lift-red", "robosuite"))
            _evaluated(catalog, key, 3, task=("nav-room-sequence-red-green", "navigation"), split="unseen_paraphrase")
    lines = protocol_markdown(catalog, CAMPAIGN)
    rows = [_cells(line) for line in lines if line.startswith("| 0 | chunk")]
    assert [row[3:] for row in rows] == [
        ["0, 1, 2 (over 1 of 3 cases: the others not evaluated for every seed (yet))",
         "80% ± 10 (90, 70, 80) over 3 seeds, 24/30 pooled [63%, 90%]"]]
    _register(catalog, 0, {}, model="train-b-s0")  # the loop deployed seed 0's older training: the seeds line
    assert ("    3 seeds     80% ± 10 [63%, 90%]  (over 1 of 3 cases: the others not evaluated for every "
            "seed (yet))") in campaign_summary(catalog, CAMPAIGN, []).splitlines()
    _evaluated(catalog, "train-s2", 5, task=("lift-red", "robosuite"))  # seed 2's evaluation done
    _evaluated(catalog, "train-s2", 3, task=("nav-room-sequence-red-green", "navigation"), split="unseen_paraphrase")
    _evaluated(catalog, "train-s1", 15, episodes=20, unit="evaluate-train-s1-again")  # its first 10 all succeeded
    rows = [_cells(line) for line in protocol_markdown(catalog, CAMPAIGN) if line.startswith("| 0 | chunk")]
    assert rows[0][3:] == ["0, 1, 2", "70% ± 5 (70, 75, 65) over 3 seeds, 42/60 pooled [57%, 80%]",
                           "30% ± 0 (30, 30, 30) over 3 seeds, 9/30 pooled [17%, 48%]"]
    [seeds] = [line for line in campaign_summary(catalog, CAMPAIGN, []).splitlines() if "3 seeds" in line]
    assert seeds.split() == ["3", "seeds", "70%", "±", "5", "[57%,", "80%]", "30%", "±", "0", "[17%,", "48%]"]


def test_a_refusal_names_the_campaigns_of_no_iteration_too(tmp_path):
    """A campaign of the baselines alone has no `iterations` row: its evaluations, or mid-training its agents'
    plans, are what the workspace holds of it, and a report asked for another name lists it."""
    catalog, models = _catalog_with_tasks(tmp_path), tmp_path / "models"
    (models / "baselines-k").mkdir(parents=True)
    (models / "baselines-k" / "plan.json").write_text(json.dumps(
        {"campaign": "sac-only", "algorithm": "sac", "family": "robosuite", "env_steps": 100}))
    with pytest.raises(ValueError, match=r"campaign 'other' has no .* \(it holds 'sac-only': name it with --preset"):
        results_markdown(catalog, "other", "sim2act report", models=models)
    with pytest.raises(ValueError, match=r"\(it holds no campaign yet\)"):  # plans not read: none held
        results_markdown(catalog, "other", "sim2act report")
    _evaluated(catalog, "expert", 10, campaign="ceiling")  # the expert alone evaluated
    _evaluated(catalog, "train-x", 3, campaign="ceiling-adapt", suite="adapt")  # an adaptation's: not a campaign
    with pytest.raises(ValueError, match=r"\(it holds 'ceiling', 'sac-only': name it with --preset"):
        results_markdown(catalog, "other", "sim2act report", models=models)


def test_a_campaign_indexed_but_not_evaluated_reports_its_dataset(tmp_path):
    """The generalist's million before its training: no evaluation yet, the dataset and compute sections alone."""
    catalog = _catalog_with_tasks(tmp_path)
    with pytest.raises(ValueError, match=r"has no evaluated iteration in this warehouse \(it holds no campaign yet\)"):
        results_markdown(catalog, CAMPAIGN, "sim2act report")
    catalog.register_unit(unit_key="index-0", stage="index", campaign=CAMPAIGN, iteration=0, summary={}, wall_s=2.0,
                          rows={"iterations": [{
                              "unit_key": "index-0", "campaign": CAMPAIGN, "iteration": 0, "dataset_digest": "d",
                              "explore_units": [], "filter_units": [], "episodes": 0, "kept_episodes": 0,
                              "triplets": 0}]})
    with pytest.raises(ValueError, match=rf"campaign 'other' has no .* \(it holds '{CAMPAIGN}': name it with --preset"):
        results_markdown(catalog, "other", "sim2act report")  # the campaigns it does hold, named
    text = results_markdown(catalog, CAMPAIGN, "sim2act report")
    assert "No iteration of this campaign is evaluated yet" in text
    rows = [line for line in text.splitlines() if line.startswith("| navigation |") or line.startswith("| all |")]
    assert rows == ["| navigation | seen | 2 | 0 | 0 | 0 | 0 | 0 | 0 |", "| navigation | unseen | 1 | 0 | 0 | 0 | 0 | 0 | 0 |",
                    "| all |  | 3 | 0 | 0 | 0 | 0 | 0 | 0 |"], text
    assert "| index | 0 | 1 | 2 | 0.00 | 0.00 | 0.00 |" in text


def test_a_relabelled_episode_moves_its_counts_but_its_units_bytes_count_once(tmp_path):
    """`explore.relabel` files a failed episode under the task it did instead: the episode counts there, and the
    unit's shard bytes stay under the task it explored, once (they were counted under both)."""
    from dashboards.results import dataset_rows

    catalog = _catalog_with_tasks(tmp_path)
    unit = "explore-nav-room-red"
    episodes = [{"campaign": CAMPAIGN, "iteration": 0, "episode_id": f"e{i}", "task_id": task_id, "instruction": "x",
                 "explorer": "policy", "seed": i, "shard_key": unit, "num_steps": 10, "episode_return": 0.0,
                 "success": True, "explorer_stats": stats}
                for i, (task_id, stats) in enumerate([
                    ("nav-room-red", None), ("nav-room-red", None),
                    ("nav-room-sequence-red-green", json.dumps({"relabelled_from": "nav-room-red"}))])]
    shard = write_shard("episodes", pa.Table.from_pylist(episodes, schema=EPISODES),
                        Workspace.at(tmp_path).shard_path("episodes", 0, unit))
    catalog.register_unit(unit_key=unit, stage="explore", campaign=CAMPAIGN, iteration=0, summary={}, shards=[shard])
    rows = dataset_rows(catalog, CAMPAIGN, [unit], [])
    assert [row[:8] for row in rows] == [("navigation", "seen", 2, 2, 3, 30, 0, 0),
                                         ("navigation", "unseen", 1, 0, 0, 0, 0, 0)]
    assert [row[8] for row in rows] == [shard.num_bytes, 0]


def test_running_time_is_the_union_of_the_units_spans():
    # two workers overlapping, a unit inside another, then a pause of 1,000 s before a resume
    assert running_seconds([(0, 10), (5, 12), (6, 7), (1012, 1020)]) == 20
    assert running_seconds([(3, 4)]) == 1 and running_seconds([]) == 0


def test_the_compute_table_counts_a_pause_between_sessions_in_elapsed_time_only(tmp_path):
    """The generalist's exploration: 61 minutes of running, stopped with the session for 26 and resumed; its
    elapsed time counts the pause, its running time does not."""
    catalog = _catalog_with_tasks(tmp_path)
    for n, (finished, wall) in enumerate([(1_000, 600), (1_300, 600), (5_200, 900)]):  # two in parallel, then 3,000 s idle
        catalog.register_unit(unit_key=f"explore-{n}", stage="explore", campaign=CAMPAIGN, iteration=0, summary={},
                              wall_s=wall)
        with catalog.connect() as con:
            con.execute("UPDATE stage_runs SET finished_at = make_timestamp(?::BIGINT) WHERE unit_key = ?",
                        [finished * 1_000_000, f"explore-{n}"])
    catalog.register_unit(unit_key="index-0", stage="index", campaign=CAMPAIGN, iteration=0, summary={}, wall_s=1.0,
                          rows={"iterations": [{
                              "unit_key": "index-0", "campaign": CAMPAIGN, "iteration": 0, "dataset_digest": "d",
                              "explore_units": [], "filter_units": [], "episodes": 0, "kept_episodes": 0,
                              "triplets": 0}]})
    text = results_markdown(catalog, CAMPAIGN, "sim2act report")
    # summed 2,100 s; elapsed 400 -> 5,200 s (1.33 h); running 400 -> 1,300 and 4,300 -> 5,200 (1,800 s: 0.50 h)
    assert "| explore | 0 | 3 | 2,100 | 0.58 | 1.33 | 0.50 |" in text, text


def _deployed(catalog: Catalog, iteration: int, model_key: str, promoted: bool = True) -> None:
    catalog.register_unit(unit_key=f"redeploy-{iteration}", stage="redeploy", campaign=CAMPAIGN, iteration=iteration,
                          summary={}, rows={"deployments": [{
                              "unit_key": f"redeploy-{iteration}", "model_key": model_key, "campaign": CAMPAIGN,
                              "iteration": iteration, "registered_model": "m", "version": iteration + 1,
                              "alias": "champion", "champion_version": iteration + 1,
                              "champion_model_key": model_key, "promoted": promoted, "decision": "",
                              "mlflow_run_id": ""}]})


def test_the_report_sets_the_loops_last_iteration_over_seeds_against_its_first(tmp_path):
    """Issue 9 item 5's reading: the loop's recipe at iteration 0 and 3, three seeds each, 50 episodes per seed;
    an ablation at iteration 3 (three seeds of its own) and seeds of an iteration the loop never met stay out of
    it."""
    from dashboards.results import protocol_markdown

    catalog = Catalog(Workspace.at(tmp_path).create().catalog)
    catalog.initialise()
    for iteration, wins in ((0, (5, 10, 15)), (3, (30, 35, 40))):
        for seed, won in enumerate(wins):
            _training(catalog, f"train-it{iteration}-s{seed}", seed, 8, digest=f"d{iteration}", iteration=iteration,
                      recipe={"targets": "expert"})
            _evaluated(catalog, f"train-it{iteration}-s{seed}", won, episodes=50)
    for seed, won in enumerate((48, 49, 50)):  # an ablation at iteration 3, far above the loop: not its climb
        _training(catalog, f"train-it3-executed-s{seed}", seed, 8, digest="d3", iteration=3,
                  recipe={"targets": "executed"})
        _evaluated(catalog, f"train-it3-executed-s{seed}", won, episodes=50)
    assert "### The loop over seeds" not in "\n".join(protocol_markdown(catalog, CAMPAIGN))  # nothing deployed yet
    _deployed(catalog, 0, "train-it0-s0")
    _deployed(catalog, 3, "train-it3-s0", promoted=False)  # met by the redeploy stage, not promoted: still the loop's
    for seed, won in enumerate((49, 50)):  # seeds of a recipe at iteration 5 whose dataset the loop never deployed from
        _training(catalog, f"train-it5-s{seed}", seed, 8, digest="d5", iteration=5, recipe={"targets": "expert"})
        _evaluated(catalog, f"train-it5-s{seed}", won, episodes=50)
    lines = protocol_markdown(catalog, CAMPAIGN)
    assert "### The loop over seeds: iteration 0 against iteration 3" in lines
    rows = [_cells(line) for line in lines if line.startswith("| seen |")]
    assert rows == [["seen", "20% ± 10 (10, 20, 30) over 3 seeds, 30/150 pooled [14%, 27%]",
                     "70% ± 10 (60, 70, 80) over 3 seeds, 105/150 pooled [62%, 77%]", "+50.0",
                     "above iteration 0's: the pooled intervals are apart; across seeds too (Welch's t on the seeds' rates p = 0.0036)"]]
    climb = lines[lines.index("### The loop over seeds: iteration 0 against iteration 3"):]
    assert [line.split("|")[1].strip() for line in climb[:climb.index("### Ablations: each recipe against the loop's own")]
            if line.startswith("| ") and not line.startswith("| split")] == ["seen"]  # splits; families are above
    ablation = lines[lines.index("### Ablations: each recipe against the loop's own"):]
    assert [line.split("|")[2].strip() for line in ablation if line.startswith("| 3")] == ["train.targets executed"]


def test_an_ablation_is_its_own_row_named_by_what_it_changes_and_read_against_the_loops_recipe(tmp_path):
    """train.targets=executed on the loop's dataset: the headline fields (chunk, steps, weights) equal the
    recipe it ablates, so only the recorded recipe keeps its seeds out of that recipe's pool. The precision a
    seed trained in is not its recipe (the loop's seed 0 in fp32, its other seeds where the probe chose bf16):
    one row, which names it per seed."""
    from dashboards.results import protocol_markdown

    catalog = Catalog(Workspace.at(tmp_path).create().catalog)
    catalog.initialise()
    for arm, targets, wins in (("expert", "expert", (9, 7, 8)), ("executed", "executed", (2, 1, 3))):
        for seed, won in enumerate(wins):
            recipe = {"targets": targets, "epochs": 65, "model": {"chunk": 8, "vision": "hybrid"}}
            precision = "fp32" if (arm, seed) == ("expert", 0) else "bf16"
            _training(catalog, f"train-{arm}-s{seed}", seed, 8, iteration=3, recipe=recipe, precision=precision)
            _evaluated(catalog, f"train-{arm}-s{seed}", won)
    lines = protocol_markdown(catalog, CAMPAIGN)
    rows = [_cells(line) for line in lines if "| chunk" in line]
    assert [row[1] for row in rows] == [
        "chunk 8, members 1, steps 2400, weights ema 0.999, train.targets executed, bf16",
        "chunk 8, members 1, steps 2400, weights ema 0.999, train.targets expert"]
    assert [row[3] for row in rows] == ["0, 1, 2", "0 (fp32), 1 (bf16), 2 (bf16)"]
    assert [row[4].split(" over")[0] for row in rows] == ["20% ± 10 (20, 10, 30)", "80% ± 10 (90, 70, 80)"]
    assert not any(line.startswith("### Ablations") for line in lines)  # no deployed model: no loop to compare with

    _deployed(catalog, 3, "train-expert-s0")  # the loop's seed: the other recipe at iteration 3 is its ablation
    lines = protocol_markdown(catalog, CAMPAIGN)
    ablations = [_cells(line) for line in lines[lines.index(
        "### Ablations: each recipe against the loop's own"):] if line.startswith("| 3")]
    assert ablations == [["3", "train.targets executed", "20% ± 10 (20, 10, 30) over 3 seeds, 6/30 pooled [10%, 37%]",
                          "80% ± 10 (90, 70, 80) over 3 seeds, 24/30 pooled [63%, 90%]", "-60.0",
                          "below the loop's: the pooled intervals are apart; across seeds too (Welch's t on the seeds' rates p = 0.0018)"]]


def test_the_report_lists_the_baselines_not_evaluated_yet_as_far_as_each_got(tmp_path):
    """The generalist's SACs train for ~15 h: a report read meanwhile names each agent of the campaign's latest plan
    not evaluated yet (waiting; training, to resume or stopped, at its latest progress and where a restart resumes
    it; trained and not evaluated) and drops it once its rows are in; plans no run makes any more go."""
    import os
    import time
    from types import SimpleNamespace

    from dashboards.results import pending_baselines_markdown
    from policies.rl_agent import save_checkpoint
    from schemas.config import RandomiseConfig, RenderConfig
    from stages.baselines import RLTrained, RLUnit, write_plans, write_progress

    catalog = _catalog_with_tasks(tmp_path)
    models = Workspace.at(tmp_path).models

    def unit(name: str, algorithm: str, family: str, steps: int) -> RLUnit:
        return RLUnit(unit_key=f"baselines-{name}", algorithm=algorithm, family=family, tasks=[], embeddings={},
                      render=RenderConfig(), randomise=RandomiseConfig(), env_steps=steps, replay_size=steps,
                      checkpoint_every=5_000, seed=0, path=str(models / f"baselines-{name}" / "agent.zip"))

    def trained(key: str, campaign: str = CAMPAIGN) -> None:
        catalog.register_unit(unit_key=key, stage="baselines", campaign=campaign, iteration=0, summary=RLTrained(
            algorithm="ppo", family="navigation", env_steps=254_522, steps_taken=254_976, episodes=2_300, successes=41,
            resumed_at=0, path="x").model_dump())

    units = [unit("trained", "ppo", "navigation", 254_522), unit("sac-metaworld", "sac", "metaworld", 382_023),
             unit("sac-robosuite", "sac", "robosuite", 455_956), unit("ppo-navigation", "ppo", "navigation", 254_522),
             unit("ppo-robosuite", "ppo", "robosuite", 455_956), unit("ppo-metaworld", "ppo", "metaworld", 1_000)]
    write_plans(models, CAMPAIGN, units)
    write_plans(models, "other", [unit("other", "ppo", "robosuite", 9)])  # another campaign's, in the same workspace
    write_plans(models, CAMPAIGN, units[:-1])  # a later run: ppo on metaworld has another budget since (another key)
    assert not (models / "baselines-ppo-metaworld" / "plan.json").exists()
    write_plans(models, CAMPAIGN, [], ["robosuite"])  # a run of robosuite's agents alone (baselines.families)...
    assert not (models / "baselines-sac-robosuite" / "plan.json").exists()
    assert (models / "baselines-sac-metaworld" / "plan.json").exists()  # ...leaves the others' plans as they were
    write_plans(models, CAMPAIGN, units[:-1])
    assert (models / "baselines-other" / "plan.json").exists() and (models / "baselines-trained" / "plan.json").exists()
    trained("baselines-trained")  # trained, not evaluated
    trained("baselines-other", "other")  # another campaign's
    trained("baselines-ppo-metaworld")  # of a plan since dropped: no run evaluates it

    class Agent:  # what save_checkpoint asks of an SB3 agent: its step count and a save
        def __init__(self, steps: int) -> None:
            self.num_timesteps = steps

        def save(self, path):
            path.write_bytes(b"weights")

    def written(path, at: int) -> None:
        os.utime(path, (at, at))

    noon = 1_796_040_000  # 2026-11-30 12:00 UTC
    save_checkpoint(Agent(120_000), SimpleNamespace(episodes_finished=650, successes=3),
                    models / "baselines-sac-robosuite")
    written(models / "baselines-sac-robosuite" / "checkpoint" / "state.json", noon)
    write_progress(models / "baselines-sac-robosuite", 123_093, 667, 3, 7.0)  # ran on past its checkpoint, 7 steps/s
    written(models / "baselines-sac-robosuite" / "progress.json", noon + 600)
    save_checkpoint(Agent(130_000), SimpleNamespace(episodes_finished=653, successes=6),
                    models / "baselines-sac-metaworld")
    written(models / "baselines-sac-metaworld" / "checkpoint" / "state.json", noon + 60)
    write_progress(models / "baselines-sac-metaworld", 129_880, 652, 6)  # its last run's, older than the checkpoint
    written(models / "baselines-sac-metaworld" / "progress.json", noon)
    (models / "baselines-sac-metaworld" / "checkpoint").rename(models / "baselines-sac-metaworld" / "checkpoint.old")
    write_progress(models / "baselines-ppo-robosuite", 2_048, 20, 0, 40.0)  # started, no checkpoint yet; not now
    written(models / "baselines-ppo-robosuite" / "progress.json", noon)
    # run_holder's: a run of this campaign that started at 12:05 (robosuite's SAC has run in it since; the others not)
    holder = {"campaign": CAMPAIGN, "pid": 4242, "host": "runner", "since": "2026-11-30 12:05:00 UTC",
              "started": noon + 300}
    lines = pending_baselines_markdown(catalog, CAMPAIGN, models, holder)
    assert "A `sim2act run` of this campaign holds the workspace (pid 4242 on runner, since 2026-11-30 12:05 UTC)" \
        in lines[1]
    rows = [_cells(line) for line in lines if line.startswith("| ")][1:]
    assert rows == [
        ["PPO from scratch (navigation)", "trained, not evaluated yet", "254,976 / 254,522", "2,300 (41)", "–",
         "–", "–"],
        ["SAC from scratch (metaworld)", "to resume", "130,000 / 382,023 (34%)", "653 (6)", "2026-11-30 12:01 UTC",
         "–", "130,000 (2026-11-30 12:01 UTC)"],
        # 332,863 steps to go at 7.0/s from 12:10: 13.2 h
        ["SAC from scratch (robosuite)", "training", "123,093 / 455,956 (27%)", "667 (3)", "2026-11-30 12:10 UTC",
         "7.0/s, ends ~2026-12-01 01:22 UTC", "120,000 (2026-11-30 12:00 UTC)"],
        ["PPO from scratch (navigation)", "waiting", "0 / 254,522", "–", "–", "–", "–"],
        ["PPO from scratch (robosuite)", "to resume", "2,048 / 455,956 (0%)", "20 (0)", "2026-11-30 12:00 UTC",
         "–", "0: no checkpoint yet"]]
    older_code = {**holder, "since": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(noon + 300))}
    del older_code["started"]  # a run of code before `started`: its local `since` read instead
    assert pending_baselines_markdown(catalog, CAMPAIGN, models, older_code) == lines
    # robosuite's SAC checkpointed since (12:11:40): the row reads the checkpoint, at the pace its run logged last
    save_checkpoint(Agent(125_000), SimpleNamespace(episodes_finished=680, successes=3),
                    models / "baselines-sac-robosuite")
    written(models / "baselines-sac-robosuite" / "checkpoint" / "state.json", noon + 700)
    [row] = [_cells(line) for line in pending_baselines_markdown(catalog, CAMPAIGN, models, holder)
             if "SAC from scratch (robosuite)" in line]
    # 330,956 steps to go at 7.0/s from 12:11:40: 13.1 h
    assert row == ["SAC from scratch (robosuite)", "training", "125,000 / 455,956 (27%)", "680 (3)",
                   "2026-11-30 12:11 UTC", "7.0/s, ends ~2026-12-01 01:19 UTC", "125,000 (2026-11-30 12:11 UTC)"]

    _register(catalog, 0, {("nav-room-red", "seen"): 9})  # an evaluated iteration: the report's success table
    assert "Baselines not in the table yet" in results_markdown(catalog, CAMPAIGN, "sim2act report", models, holder)
    assert "Baselines not in the table yet" not in results_markdown(catalog, CAMPAIGN, "sim2act report")
    _evaluated(catalog, "baselines-trained", 2)  # its rows are in the table now
    trained("baselines-sac-robosuite")
    for held_by, said in ((None, "No `sim2act run` holds the workspace now."),  # the session's end, a kill
                          ({**holder, "campaign": "warehouse compact"}, "Another run (`warehouse compact`) holds")):
        lines = pending_baselines_markdown(catalog, CAMPAIGN, models, held_by)
        assert said in lines[1]
        states = [line.split(" | ")[:2] for line in lines if "from scratch" in line]
        assert states == [["| PPO from scratch (navigation)", "trained, not evaluated yet"],  # sac-robosuite's summary
                          ["| SAC from scratch (metaworld)", "stopped"], ["| PPO from scratch (navigation)", "waiting"],
                          ["| PPO from scratch (robosuite)", "stopped"]]


def test_a_baseline_read_mid_evaluation_says_how_many_of_its_cases_are_in(tmp_path):
    """The experts' ceiling is in the report from its first case on: pooled over the cases so far, it says so (the
    cases the last iteration's model met); another campaign's expert on the same task is not this one's."""
    catalog = _catalog_with_tasks(tmp_path)
    _register(catalog, 0, {("nav-room-red", "seen"): 9, ("nav-room-sequence-red-green", "seen"): 5,
                           ("nav-room-sequence-purple-red", "unseen"): 1,  # the last iteration's model: 3 cases,
                           ("nav-room-red", "held_out_wording"): 7})  # and one the baselines never meet
    for task_id in ("nav-room-red", "nav-room-sequence-red-green"):
        _evaluated(catalog, "expert", 10, task=(task_id, "navigation"))
    [row] = [line for line in results_markdown(catalog, CAMPAIGN, "sim2act report").splitlines()
             if line.startswith("| scripted expert")]
    assert row.startswith("| scripted expert, noiseless (ceiling), evaluating: 2/3 cases | – | 20/20 = 100%"), row
    _evaluated(catalog, "expert", 10, task=("nav-room-sequence-purple-red", "navigation"))
    _evaluated(catalog, "expert", 4, task=("nav-room-red", "navigation"), campaign="other")  # later, another's
    [row] = [line for line in results_markdown(catalog, CAMPAIGN, "sim2act report").splitlines()
             if line.startswith("| scripted expert")]
    assert row.startswith("| scripted expert, noiseless (ceiling) | – | 30/30 = 100%"), row
    # the held-out wording is the policy's test alone: a column of its own, which the baselines leave empty
    lines = results_markdown(catalog, CAMPAIGN, "sim2act report").splitlines()
    assert "| agent | env steps (training data) | seen | unseen | unseen paraphrase | held out wording |" in lines
    [policy] = [_cells(line) for line in lines if line.startswith("| Sim2Act iteration 0")]
    assert policy[-1].startswith("7/10") and _cells(row)[-1] == "–"


def test_each_family_reads_sim2act_beside_its_own_baselines(tmp_path):
    """The pooled table mixes families; the per-family one sets each family's Sim2Act rows beside the expert's
    (narrowed to the family) and that family's RL agents, and says which agent is still being evaluated."""
    from stages.baselines import RLTrained

    catalog = _catalog_with_tasks(tmp_path, with_metaworld=True)
    _explored(catalog, Workspace.at(tmp_path), {"nav-room-red": [40, 60], "mw-reach": [150]})
    _register(catalog, 0, {("nav-room-red", "seen"): 9, ("mw-reach", "seen"): 3, ("mw-push", "unseen"): 1})
    for task_id, won, split in (("nav-room-red", 10, "seen"), ("mw-reach", 10, "seen"), ("mw-push", 9, "unseen")):
        _evaluated(catalog, "expert", won, task=(task_id, _family(task_id)), split=split)
    assert "### Per family, against the baselines" in results_markdown(catalog, CAMPAIGN, "sim2act report")
    for key, algorithm, family in (("baselines-ppo", "ppo", "navigation"), ("baselines-sac", "sac", "metaworld")):
        catalog.register_unit(unit_key=key, stage="baselines", campaign=CAMPAIGN, iteration=0, summary=RLTrained(
            algorithm=algorithm, family=family, env_steps=1_000, steps_taken=1_024, episodes=20, successes=0,
            resumed_at=0, path="x").model_dump())
    _evaluated(catalog, "baselines-ppo", 2)
    _evaluated(catalog, "baselines-sac", 0, task=("mw-reach", "metaworld"))  # mw-push not yet
    lines = results_markdown(catalog, CAMPAIGN, "sim2act report").splitlines()
    at = lines.index("### Per family, against the baselines")
    assert lines[at + 2] == "| family | agent | env steps (training data) | seen | unseen | unseen paraphrase |"
    rows = [_cells(line) for line in lines[at + 4:at + 9]]
    assert [row[:3] + [cell.split(" ")[0] for cell in row[3:]] for row in rows] == [
        ["metaworld", "Sim2Act iteration 0", "150", "3/10", "1/10", "–"],  # its own family's steps, not the pool's
        ["metaworld", "scripted expert, noiseless (ceiling)", "–", "10/10", "9/10", "–"],
        ["metaworld", "SAC from scratch, evaluating: 1/2 cases", "1,024", "0/10", "–", "–"],
        ["navigation", "Sim2Act iteration 0", "100", "9/10", "–", "–"],
        ["navigation", "scripted expert, noiseless (ceiling)", "–", "10/10", "–", "–"]]
    assert _cells(lines[at + 9])[:4] == ["navigation", "PPO from scratch", "1,024", "2/10 = 20% (6%–51%)"]
    [pooled] = [_cells(line) for line in lines if line.startswith("| Sim2Act iteration 0 (BC")]
    assert pooled[1] == "250"  # the pooled table's: every family's steps

    # a second SAC on the same family and budget (another encoder layout): its own row, not pooled with the first
    catalog.register_unit(unit_key="baselines-sac-critic", stage="baselines", campaign=CAMPAIGN, iteration=0,
                          summary=RLTrained(algorithm="sac", family="metaworld", env_steps=1_000, steps_taken=1_024,
                                            episodes=20, successes=0, resumed_at=0, path="y").model_dump())
    _evaluated(catalog, "baselines-sac-critic", 4, task=("mw-reach", "metaworld"))
    lines = results_markdown(catalog, CAMPAIGN, "sim2act report").splitlines()
    sacs = sorted(_cells(line)[:2] for line in lines if line.startswith("| SAC from scratch"))
    assert [(name, cell.split(" ")[0]) for name, cell in sacs] == [
        ("SAC from scratch [baselines-sac-critic] (metaworld), evaluating: 1/2 cases", "1,024"),
        ("SAC from scratch [baselines-sac] (metaworld), evaluating: 1/2 cases", "1,024")], sacs
    seen = {_cells(line)[1]: _cells(line)[3].split(" ")[0] for line in lines if line.startswith("| metaworld | SAC")}
    assert seen == {"SAC from scratch [baselines-sac-critic], evaluating: 1/2 cases": "4/10",
                    "SAC from scratch [baselines-sac], evaluating: 1/2 cases": "0/10"}, seen


def test_the_unseen_split_is_cut_into_held_out_colours_and_whole_tasks_per_family(tmp_path):
    """An unseen task whose spec the campaign trains on is a held-out colouring; one whose spec it never trains on
    is a whole task. Navigation holds one of each here (nav-ball has no seen task), MetaWorld a whole task alone:
    each family's unseen cases are cut in two, a row per iteration and per baseline (an RL agent on its family
    alone); a paraphrase is no unseen case, nor one evaluated unseen whose task the campaign now holds as seen."""
    from stages.baselines import RLTrained

    catalog = _catalog_with_tasks(tmp_path, with_metaworld=True)
    catalog.register_unit(unit_key="tasks-ball", stage="generate_tasks", campaign=CAMPAIGN, iteration=0, summary={},
                          rows={"tasks": [{
                              "campaign": CAMPAIGN, "task_id": "nav-ball-blue", "spec": "nav-ball", "family": "navigation",
                              "env_name": "FindBall", "instruction": "find the blue ball", "instructions": ["a", "b", "c"],
                              "unseen_instructions": [], "object_colours": json.dumps({"ball": "blue"}),
                              "split": "unseen", "horizon": 50, "unit_key": "tasks-ball"}]})
    assert results.unseen_kinds(catalog, CAMPAIGN) == {
        "nav-room-sequence-purple-red": "unseen colours", "nav-ball-blue": "unseen whole tasks",
        "mw-push": "unseen whole tasks"}
    _register(catalog, 0, {("nav-room-red", "seen"): 9, ("nav-room-sequence-purple-red", "unseen"): 3,
                           ("nav-ball-blue", "unseen"): 0, ("mw-reach", "seen"): 5, ("mw-push", "unseen"): 1,
                           ("nav-room-sequence-red-green", "unseen_paraphrase"): 4,
                           ("nav-room-red", "unseen"): 7})  # evaluated unseen once; its task is seen now
    _register(catalog, 1, {("nav-room-sequence-purple-red", "unseen"): 5, ("nav-ball-blue", "unseen"): 2,
                           ("mw-push", "unseen"): 4})
    for task_id, won in (("nav-room-sequence-purple-red", 10), ("nav-ball-blue", 8)):
        _evaluated(catalog, "expert", won, task=(task_id, "navigation"), split="unseen")
    catalog.register_unit(unit_key="baselines-sac", stage="baselines", campaign=CAMPAIGN, iteration=0, summary=RLTrained(
        algorithm="sac", family="metaworld", env_steps=1_000, steps_taken=1_024, episodes=20, successes=0,
        resumed_at=0, path="x").model_dump())
    _evaluated(catalog, "baselines-sac", 6, task=("mw-push", "metaworld"), split="unseen")
    lines = results_markdown(catalog, CAMPAIGN, "sim2act report").splitlines()
    at = lines.index("### Unseen, by kind, per family")
    assert lines[at + 4] == "| family (colours + whole) | agent | unseen colours | unseen whole tasks |"
    rows = [_cells(line) for line in lines[at + 6:at + 12]]
    assert [row[:2] + [cell.split(" ")[0] for cell in row[2:]] for row in rows] == [
        ["metaworld (0 + 1)", "Sim2Act iteration 0", "–", "1/10"],
        ["metaworld (0 + 1)", "Sim2Act iteration 1", "–", "4/10"],
        ["metaworld (0 + 1)", "SAC from scratch", "–", "6/10"],
        ["navigation (1 + 1)", "Sim2Act iteration 0", "3/10", "0/10"],
        ["navigation (1 + 1)", "Sim2Act iteration 1", "5/10", "2/10"],
        ["navigation (1 + 1)", "scripted expert, noiseless (ceiling)", "10/10", "8/10"]], rows
    assert lines[at + 12] == ""  # the expert met no MetaWorld case, the SAC no navigation one: no rows of them there

    colours_only = _catalog_with_tasks(tmp_path / "colours")  # navigation alone: its one unseen task a colouring
    _register(colours_only, 0, {("nav-room-red", "seen"): 9, ("nav-room-sequence-purple-red", "unseen"): 3})
    assert "### Unseen, by kind" not in results_markdown(colours_only, CAMPAIGN, "sim2act report")
