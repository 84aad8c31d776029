"""`sim2act eval`'s suites and `sim2act shadow --placements trained`: the evaluation's cases started where the
model's training episodes started."""

from pathlib import Path

import pyarrow as pa
import pytest

from envs.suite import generate_tasks
from flows.model_eval import _suite, conditions_apart, eval_cases, started_as_trained
from schemas.config import ConfigError, RandomiseConfig, RenderConfig, TasksConfig, load_config
from schemas.tables import EPISODES
from schemas.tasks import TaskRecord
from schemas.workspace import Workspace
from stages.evaluate import Agent, EvalUnit
from stages.explore import ExploreUnit, unit_summary
from tests.campaign import NEW_TASKS
from warehouse.catalog import Catalog
from warehouse.shard_writer import ShardFile, write_shard

def test_an_evaluation_under_other_frames_than_the_campaign_explored_is_a_suite_of_its_own(tmp_path):
    """The campaign explored at mesh_detail 0.1: `sim2act eval --set render.mesh_detail=1.0` (or another
    randomisation) is not the campaign's figure, so its rows go under a suite naming what differs, not under
    the campaign's cases where the report would take them for the model's score."""
    workspace = Workspace.at(tmp_path / "ws").create()
    catalog = Catalog(workspace.catalog)
    catalog.initialise()
    config = load_config("smoke", None, {"render": {"mesh_detail": 0.1}})
    assert conditions_apart(workspace, config) == []  # nothing explored yet: nothing to differ from
    episode = {"campaign": config.name, "iteration": 0, "episode_id": "e0", "task_id": "lift-red", "instruction": "x",
               "explorer": "expert", "seed": 0, "shard_key": "explore-a", "num_steps": 5, "episode_return": 0.0,
               "success": True, "render": {"camera": "agentview", "image_size": 84, "shadows": False,
                                           "reflections": False, "multisamples": 0, "depth": False}}
    shard = write_shard("episodes", pa.Table.from_pylist([episode], schema=EPISODES),
                        workspace.shard_path("episodes", 0, "explore-a"))
    summary = unit_summary(ExploreUnit.model_construct(render=config.render, randomise=config.randomise),
                           [shard, ShardFile("steps", Path("steps.parquet"), 5, 0, "")])
    catalog.register_unit(unit_key="explore-a", stage="explore", campaign=config.name, iteration=0, summary=summary,
                          shards=[shard])
    assert conditions_apart(workspace, config) == []
    other = load_config("smoke", None, {"render": {"shadows": True, "mesh_detail": 1.0},
                                        "randomise": {"light": [0.5, 1.5]}})
    assert conditions_apart(workspace, other) == ["randomise.light=[0.5, 1.5]", "render.mesh_detail=1.0",
                                                  "render.shadows=true"]
    # evaluate.metaworld_placements names the suite where MetaWorld cases are evaluated (exploration takes MT1's)
    fresh = config.model_copy(update={"evaluate": config.evaluate.model_copy(update={"metaworld_placements": "fresh"})})
    assert conditions_apart(workspace, fresh) == []
    metaworld = TaskRecord(task_id="mw-reach", spec="mw-reach", family="metaworld", env_name="reach-v3",
                           object_colours={}, instructions=["reach the goal", "go to the goal", "move to the goal"], split="seen",
                           horizon=150)
    assert _suite("campaign", [], fresh, [(metaworld, "seen", "reach the goal")]) == \
        "campaign @ evaluate.metaworld_placements=fresh"
    assert _suite("campaign", ["render.shadows=true"], fresh, []) == "campaign @ render.shadows=true"
    # episodes cut short (evaluate.max_steps) are no full-horizon figure, whatever the family
    short = config.model_copy(update={"evaluate": config.evaluate.model_copy(update={"max_steps": 10})})
    assert _suite("campaign", [], short, []) == "campaign @ evaluate.max_steps=10"
    tasks = tmp_path / "elsewhere.yaml"
    tasks.write_text(NEW_TASKS)
    assert eval_cases(workspace, config, tasks, None)[0] == "file:elsewhere.yaml"
    assert eval_cases(workspace, other, tasks, None)[0] == ("file:elsewhere.yaml @ randomise.light=[0.5, 1.5], "
                                                            "render.mesh_detail=1.0, render.shadows=true")


def test_a_workspace_explored_before_the_ranges_were_recorded_still_tells_randomisation_off(tmp_path):
    """An explore unit whose summary predates the recorded ranges: its episodes' draws say whether randomisation
    was on (null: off). Off on both sides, the ranges draw nothing: the same episodes, the campaign's suite. An
    episodes shard that cannot be read leaves the summary's record, not a failed command."""
    workspace = Workspace.at(tmp_path / "ws").create()
    catalog = Catalog(workspace.catalog)
    catalog.initialise()
    off = load_config("smoke", None, {"randomise": {"enabled": False}})
    episode = {"campaign": off.name, "iteration": 0, "episode_id": "e0", "task_id": "lift-red", "instruction": "x",
               "explorer": "expert", "seed": 0, "shard_key": "explore-a", "num_steps": 5, "episode_return": 0.0,
               "success": True, "randomisation": None}
    shard = write_shard("episodes", pa.Table.from_pylist([episode], schema=EPISODES),
                        workspace.shard_path("episodes", 0, "explore-a"))
    catalog.register_unit(unit_key="explore-a", stage="explore", campaign=off.name, iteration=0,
                          summary={"episodes": 1, "steps": 5, "mesh_detail": 0.1}, shards=[shard])
    assert conditions_apart(workspace, off.model_copy(update={"randomise": RandomiseConfig(enabled=False, tint=0.5)})) == []
    assert conditions_apart(workspace, load_config("smoke")) == ["randomise.enabled=true"]
    shard.path.unlink()  # gone from under the catalog: the summary's fields alone
    assert conditions_apart(workspace, load_config("smoke", None, {"render": {"mesh_detail": 0.2}})) == [
        "render.mesh_detail=0.2"]


@pytest.fixture(scope="module")
def units():
    tasks = generate_tasks(TasksConfig(specs=["lift"], colours=["red", "green"]), 0)
    return [EvalUnit(unit_key=f"u-{task.task_id}", task=task, split="seen", instruction=task.instructions[0],
                     render=RenderConfig(), randomise=RandomiseConfig(), agent=Agent(kind="expert"),
                     seeds=[101, 102, 103], embedding=[], video_stem=None) for task in tasks]


def test_each_case_plays_its_trained_seeds_in_order_as_many_as_it_asked(units):
    red, green = (unit.task.task_id for unit in units)
    started = started_as_trained(units, {red: [7, 8, 9, 10], green: [5]})
    assert [(unit.task.task_id, unit.seeds) for unit in started] == [(red, [7, 8, 9]), (green, [5])]


def test_a_case_never_trained_on_is_left_out_and_none_at_all_is_refused(units):
    red, green = (unit.task.task_id for unit in units)
    assert [unit.task.task_id for unit in started_as_trained(units, {green: [5]})] == [green]
    with pytest.raises(ConfigError, match=f"expected cases the model trained on, got only {green}, {red}"):
        started_as_trained(units, {"lift-blue": [1], red: []})
