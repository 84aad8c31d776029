"""`sim2act shadow --placements trained`: the evaluation's cases started where the model's training episodes started."""

import pytest

from envs.suite import generate_tasks
from flows.model_eval import started_as_trained
from schemas.config import ConfigError, RandomiseConfig, RenderConfig, TasksConfig
from stages.evaluate import Agent, EvalUnit


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
