"""Adaptation to a shifted domain on a real warehouse: the expert explores the shifted domain, models
train on its first episodes from the source model and from scratch, and every one is evaluated there."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dashboards.results import adaptation_markdown, family_scores, family_table
from envs.suite import generate_tasks
from policies.policy import checkpoint_members
from schemas.config import CampaignConfig, ConfigError, RandomiseConfig
from schemas.workspace import Workspace
from stages.adapt import AdaptPoint, AdaptResult, adapted_tasks, episodes_to_reach, run_adapt, target_campaign
from stages.generate_tasks import tasks_unit_key
from stages.index import latest_index
from stages.train import run_train
from tests.stages.test_train import _iteration_zero_dataset
from warehouse.catalog import Catalog
from warehouse.tasks import load_embeddings
from warehouse.training_reader import SelectionError

CAMPAIGN = {
    "name": "adapt-test",
    "tasks": {"specs": ["lift"], "colours": ["red", "green"], "horizon": {"lift": 30}},
    "explore": {"episodes_per_task": 2, "episodes_per_shard": 2, "workers": 2},
    "filter": {"min_return": 0.0},
    "train": {"epochs": 2, "batch_size": 16, "loader_workers": 0,
              "model": {"dim": 32, "heads": 4, "vision_depth": 1, "fusion_depth": 1}},
    "evaluate": {"videos": False, "workers": 2},
    "adapt": {"episodes_per_task": [1, 2], "train_steps": 3, "eval_episodes": 1},
}


def _weights(checkpoint: str) -> dict[str, torch.Tensor]:
    return checkpoint_members(torch.load(checkpoint, weights_only=False))[0]


def _distance(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> float:
    return sum(float((a[k].float() - b[k].float()).norm()) for k in a if a[k].is_floating_point())


@pytest.fixture(scope="module")
def adapted(tmp_path_factory):
    config = CampaignConfig.model_validate(CAMPAIGN)
    workspace = Workspace.at(tmp_path_factory.mktemp("adapt") / "workspace")
    tasks_key, embeddings, dataset = _iteration_zero_dataset(workspace, config)
    source = run_train(workspace, config, 0, dataset, tasks_key, embeddings)
    return config, workspace, source, run_adapt(workspace, config, source.model_key, source.checkpoint)


def test_the_shifted_domain_is_explored_by_the_expert_under_its_own_randomisation(adapted):
    config, workspace, _, result = adapted
    rows = Catalog(workspace.catalog).query(
        "SELECT explorer, randomisation.light, randomisation.mass FROM episodes WHERE campaign = ?", [result.campaign])
    assert len(rows) == 2 * 2  # two seen tasks, the largest training's episodes each
    low, high = config.adapt.domain.light
    assert all(explorer == "expert" and low <= light <= high and mass >= config.adapt.domain.mass[0]
               for explorer, light, mass in rows)


def test_each_count_trains_from_the_source_and_from_scratch_and_evaluates_in_the_shifted_domain(adapted):
    config, workspace, source, result = adapted
    assert [(p.start, p.episodes_per_task, p.episodes) for p in result.points] == [
        ("source", 0, 0), ("fine-tuned", 1, 2), ("scratch", 1, 2), ("fine-tuned", 2, 4), ("scratch", 2, 4)]
    catalog = Catalog(workspace.catalog)
    samples = dict(catalog.query("SELECT model_key, train_samples FROM models WHERE campaign = ?", [result.campaign]))
    one, two = (samples[p.model_key] for p in result.points if p.start == "fine-tuned")
    assert 0 < one < two  # the first episode of each task, then the first two
    # fine-tuning starts at the source's weights: three steps later it is still far nearer them than a new model
    start = _weights(source.checkpoint)
    tuned, scratch = (_weights(str(workspace.checkpoint(p.model_key))) for p in result.points[1:3])
    assert _distance(tuned, start) < 0.2 * _distance(scratch, start)
    evaluated = catalog.query("SELECT model_key, count(*), sum(episodes) FROM evaluations WHERE campaign = ? "
                              "AND suite = 'adapt' GROUP BY 1", [result.campaign])
    assert {key: (cases, episodes) for key, cases, episodes in evaluated} == {
        p.model_key: (2, 2 * config.adapt.eval_episodes) for p in result.points}
    assert all(p.trials == 2 for p in result.points)


def test_the_report_tabulates_the_latest_adaptation(adapted):
    _, workspace, _, result = adapted
    catalog = Catalog(workspace.catalog)
    text = "\n".join(adaptation_markdown(catalog, "adapt-test"))
    cell = {(p.episodes, p.start): f"{p.successes}/{p.trials}" for p in result.points}
    assert f"| 0 | {cell[0, 'source']} = " in text and "(the champion as it is)" in text
    assert f"| 4 | {cell[4, 'fine-tuned']} = " in text and "Episodes to reach 80%: fine-tuned " in text
    assert "stand-in" in text and "light (0.35, 0.55)" in text
    assert adaptation_markdown(catalog, "another-campaign")[0].startswith("No adaptation has run")
    # the compute line counts this adaptation's units: another champion's trainings, in the same -adapt campaign,
    # are not its work
    import re

    def compute() -> float:
        line = next(line for line in adaptation_markdown(catalog, "adapt-test") if "Compute: " in line)
        return float(re.search(r"Compute: ([\d,]+) wall seconds", line)[1].replace(",", ""))

    before = compute()
    assert before > 0
    catalog.register_unit(unit_key="train-another-champions", stage="train", campaign=result.campaign, iteration=0,
                          summary={}, wall_s=5000.0)
    assert compute() == before


def test_each_family_s_scores_come_from_the_adaptation_s_own_rows(adapted):
    _, workspace, _, result = adapted
    catalog = Catalog(workspace.catalog)
    families = family_scores(catalog, result)
    assert families == {"robosuite": (2, {p.model_key: (p.successes, p.trials) for p in result.points})}
    assert "Per family" not in "\n".join(adaptation_markdown(catalog, "adapt-test"))  # one family: the pooled table says it


def test_a_case_evaluated_again_counts_once_in_the_family_scores(adapted, tmp_path):
    """Another adaptation (another domain) into the same -adapt campaign evaluates the champion on the same cases:
    each family's score reads each case's latest evaluation, not both."""
    import shutil

    _, workspace, _, result = adapted
    copy = tmp_path / "warehouse"  # the module's workspace stays as the other tests read it
    shutil.copytree(workspace.catalog.parent, copy)
    catalog = Catalog(copy / workspace.catalog.name)
    champion = result.points[0].model_key
    [row] = catalog.query_arrow("SELECT * FROM evaluations WHERE campaign = ? AND suite = 'adapt' AND model_key = ? "
                                "ORDER BY task_id LIMIT 1", [result.campaign, champion]).to_pylist()
    again = {**row, "unit_key": "evaluate-another-domain", "successes": row["episodes"] - row["successes"]}
    catalog.register_unit(unit_key="evaluate-another-domain", stage="evaluate", campaign=result.campaign, iteration=0,
                          summary={}, rows={"evaluations": [again]})
    cases, scores = family_scores(catalog, result)["robosuite"]
    expected = result.points[0].successes - row["successes"] + again["successes"]
    assert cases == 2 and scores[champion] == (expected, result.points[0].trials)


def test_the_per_family_table_counts_each_family_s_episodes_to_its_target():
    def point(start, per_task, key, seed=0):
        return AdaptPoint(start=start, episodes_per_task=per_task, episodes=per_task * 4, model_key=key, successes=0,
                          trials=40, seed=seed)

    points = [point("source", 0, "champion"), point("fine-tuned", 2, "f2"), point("scratch", 2, "s2"),
              point("fine-tuned", 4, "f4"), point("scratch", 4, "s4"), point("fine-tuned", 4, "f4b", seed=1)]
    result = AdaptResult(campaign="c-adapt", source_model="champion", domain=RandomiseConfig(), target_success=0.8,
                         points=points, tasks=["lift-red", "lift-green", "lift-blue", "nav-room-red"])
    families = {  # three Lift tasks (10 episodes each) that adapt with 4 episodes each; one navigation task already there
        "robosuite": (3, {"champion": (3, 30), "f2": (20, 30), "s2": (0, 30), "f4": (26, 30), "f4b": (24, 30),
                          "s4": (6, 30)}),
        "navigation": (1, {"champion": (9, 10), "f2": (8, 10), "s2": (2, 10), "f4": (10, 10), "f4b": (9, 10),
                           "s4": (3, 10)}),
    }
    rows = {tuple(cell.strip() for cell in line.strip("|").split("|")[:3]): line
            for line in family_table(result, families) if line.startswith("| robosuite") or line.startswith("| navigation")}
    assert "50/60 = 83% (seeds 80%–87%)" in rows["robosuite", "3", "4"]  # the two seeds of f4 pooled
    assert "| **12** | not reached within 12 |" in rows["robosuite", "3", "to reach 80%"]  # 4 episodes x 3 tasks
    assert "| **0** | not reached within 4 |" in rows["navigation", "1", "to reach 80%"]  # the champion, as it is
    assert "9/10 = 90%" in rows["navigation", "1", "0"]


def test_a_rerun_does_no_work(adapted):
    config, workspace, source, result = adapted
    catalog = Catalog(workspace.catalog)
    before = catalog.query("SELECT count(*) FROM stage_runs")[0][0]
    again = run_adapt(workspace, config, source.model_key, source.checkpoint)
    assert again == result and catalog.query("SELECT count(*) FROM stage_runs")[0][0] == before


@pytest.mark.parametrize(("init_from", "state_weight", "words"), [
    ("train-nosuchmodel", None, "train.init_from: no model 'train-nosuchmodel'"),
    # the source trained with a state head: a strict load failed, naming "another architecture"
    ("source", 0.0, r"train.state_weight: train-\w+ has a state head .*expected train.state_weight > 0 .*got 0$"),
])
def test_a_source_model_it_cannot_fine_tune_is_refused_naming_the_field(adapted, init_from, state_weight, words):
    config, workspace, source, result = adapted
    assert source.checkpoint and config.train.state_weight > 0
    target = target_campaign(config)
    train = target.train.model_copy(update={"init_from": source.model_key if init_from == "source" else init_from,
                                            **({} if state_weight is None else {"state_weight": state_weight})})
    tasks_key = tasks_unit_key(target, generate_tasks(target.tasks, target.seed))
    catalog = Catalog(workspace.catalog)
    models = catalog.query("SELECT count(*) FROM models")[0][0]
    with pytest.raises(SelectionError, match=words):
        run_train(workspace, target.model_copy(update={"train": train}), 0, latest_index(workspace, result.campaign, 0),
                  tasks_key, load_embeddings(workspace, tasks_key, target.train.model.language_encoder))
    assert catalog.query("SELECT count(*) FROM models")[0][0] == models


def test_the_episodes_to_reach_a_success_count_the_source_at_zero():
    def point(start, episodes, successes):
        return AdaptPoint(start=start, episodes_per_task=episodes // 2, episodes=episodes, model_key="m",
                          successes=successes, trials=10)

    points = [point("source", 0, 3), point("fine-tuned", 6, 8), point("scratch", 6, 2),
              point("fine-tuned", 12, 9), point("scratch", 12, 8)]
    assert episodes_to_reach(points, "fine-tuned", 0.8) == 6
    assert episodes_to_reach(points, "scratch", 0.8) == 12
    assert episodes_to_reach(points, "scratch", 0.9) is None
    assert episodes_to_reach([point("source", 0, 9)] + points[1:], "fine-tuned", 0.8) == 0
    assert episodes_to_reach([point("source", 0, 9)] + points[1:], "scratch", 0.8) == 12
    from dashboards.results import _reached

    dipping = points + [point("fine-tuned", 18, 7)]  # 80% at 6, 70% at 18: reached, and the report says it fell
    assert _reached(dipping, "fine-tuned", 0.8) == "**6** (below it again at 18)"
    assert _reached(points, "fine-tuned", 0.8) == "**6**" and _reached(points, "scratch", 0.9) == "not reached within 12"


def test_the_episodes_to_reach_pool_the_training_seeds():
    def point(start, episodes, successes, seed):
        return AdaptPoint(start=start, episodes_per_task=episodes // 2, episodes=episodes, model_key=f"m{seed}",
                          successes=successes, trials=10, seed=seed)

    points = [point("source", 0, 3, 0), point("scratch", 6, 10, 0), point("scratch", 6, 5, 1),  # 75% pooled
              point("scratch", 12, 8, 0), point("scratch", 12, 9, 1)]  # 85%
    assert episodes_to_reach(points, "scratch", 0.8) == 12  # one seed's 100% at 6 does not count it reached
    result = AdaptResult(campaign="c-adapt", source_model="m", domain=RandomiseConfig(), target_success=0.8, points=points)
    assert result.metrics() == {"adapt.source.success.0": 0.3, "adapt.scratch.success.6": 0.75,
                                "adapt.scratch.success.12": 0.85}


def test_adapt_tasks_name_the_campaign_s_seen_tasks():
    config = CampaignConfig.model_validate({**CAMPAIGN, "tasks": {"specs": ["lift"], "colours": ["red", "green", "orange"]}})
    tasks = generate_tasks(config.tasks, config.seed)  # lift-orange: the spec's held-out colour, unseen
    assert [t.task_id for t in adapted_tasks(config, tasks)] == ["lift-red", "lift-green"]
    chosen = config.model_copy(update={"adapt": config.adapt.model_copy(update={"tasks": ["lift-green"]})})
    assert [t.task_id for t in adapted_tasks(chosen, tasks)] == ["lift-green"]
    for wrong in (["lift-orange"], ["lift-green", "lift-teal"]):
        bad = config.model_copy(update={"adapt": config.adapt.model_copy(update={"tasks": wrong})})
        with pytest.raises(ConfigError, match=f"adapt.tasks: expected task ids of the campaign's seen tasks .*got {wrong[-1]}$"):
            adapted_tasks(bad, tasks)


def test_the_target_campaign_explores_every_task_as_often_as_its_largest_training_counts():
    """A source campaign's smaller first iteration, curriculum or split-wide evaluation count would make the
    target's trainings see fewer episodes than they count (or none on tasks with sub-goals)."""
    config = CampaignConfig.model_validate({
        **CAMPAIGN, "explore": {**CAMPAIGN["explore"], "first_episodes_per_task": 1, "curriculum": True, "relabel": True},
        "evaluate": {**CAMPAIGN["evaluate"], "episodes_per_split": 45}})
    target = target_campaign(config)
    assert target.explore.episodes_at(0) == max(config.adapt.episodes_per_task)
    assert (target.explore.curriculum, target.explore.relabel, target.explore.vlm) == (False, False, None)
    assert target.evaluate.episodes_per_case(2) == config.adapt.eval_episodes


def test_a_chosen_task_with_training_seeds(adapted):
    """adapt.tasks narrows the explored, trained and evaluated tasks; adapt.seeds trains each point's
    models with seeds 0..N-1, and the report pools them with their spread."""
    config, workspace, source, first = adapted
    catalog = Catalog(workspace.catalog)
    # a task the filter kept an episode of (a noisy expert in the shifted domain fails some): 2 episodes per
    # task, as the fixture explored, so its explore units serve again
    [(task,)] = catalog.query("SELECT min(e.task_id) FROM episodes e JOIN filter_decisions f USING (episode_id) "
                              "WHERE e.campaign = ? AND f.kept", [first.campaign])
    chosen = config.model_copy(update={"adapt": config.adapt.model_copy(
        update={"tasks": [task], "seeds": 2, "episodes_per_task": [2]})})
    result = run_adapt(workspace, chosen, source.model_key, source.checkpoint)
    assert result.tasks == [task]
    assert [(p.start, p.seed, p.episodes) for p in result.points] == [
        ("source", 0, 0), ("fine-tuned", 0, 2), ("fine-tuned", 1, 2), ("scratch", 0, 2), ("scratch", 1, 2)]
    assert len({p.model_key for p in result.points}) == 5  # each seed its own training
    assert all(p.trials == config.adapt.eval_episodes for p in result.points)  # one task's cases
    text = "\n".join(adaptation_markdown(catalog, "adapt-test"))
    assert f"seen tasks ({task})" in text and "2 training seeds each" in text and "(seeds " in text


def test_a_fine_tuning_s_states_take_its_source_s_width():
    """The generalist's million holds longer simulator states than the five tasks its adaptation trains on:
    the fine-tuned model keeps its source's state head, so the states are padded or cut to its width."""
    from stages.train import padded_states

    states = padded_states([[1.0, 2.0, 3.0], [4.0]], 2)
    assert states.shape == (2, 2) and states[0].tolist() == [1.0, 2.0]
    assert states[1, 0] == 4.0 and np.isnan(states[1, 1])
    assert padded_states([[1.0]], 3).shape == (1, 3)
